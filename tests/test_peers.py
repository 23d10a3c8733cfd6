"""benchmarks/peers.py (the pysindy peer benchmark): its one-line refusal without pysindy,
and, where pysindy is installed (`pip install -e .[peers]`), that its nominal removal is
exact on noise-free data in every route (measured rates, pysindy-differentiated, weak form)."""

import os
import subprocess
import sys

import numpy as np
import pytest

PEERS = os.path.join(os.path.dirname(__file__), "..", "benchmarks", "peers.py")


def test_without_pysindy_one_line_message():
    code = ("import sys, runpy; sys.modules['pysindy'] = None; sys.argv = ['peers.py']; "
            f"runpy.run_path({PEERS!r}, run_name='__main__')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 1
    assert out.stderr.strip() == "benchmarks/peers.py needs pysindy: pip install -e .[peers]"


def test_nominal_removed_exact_on_clean_data():
    pytest.importorskip("pysindy")
    import jax

    sys.path.insert(0, os.path.dirname(PEERS))
    import peers

    from dtwin_jax.models import systems, zoo

    member = zoo.draw_member(0)  # cubic-hardening: x2' perturbed by x1**3
    ex = member.example
    sim = systems.simulate_example(ex, jax.random.fold_in(jax.random.key(member.seed), 1), duration=2.0)
    clean = type("Clean", (), {k: sim[k] for k in ("t", "x", "u", "xdot")})
    truth = ex.true_terms["x2"]["x1**3"]
    for method, layout, rtol in (("STLSQ", "accelerations", 1e-6), ("STLSQ", "states", 2e-3),
                                 ("weak STLSQ", "states", 2e-3)):
        (eq,) = peers._pysindy(method, member, clean, layout, 0, 0)
        assert [eq.names[k] for k in np.flatnonzero(eq.selected)] == ["x1**3"], (method, layout)
        assert abs(eq.mean[eq.names.index("x1**3")] / truth - 1) < rtol, (method, layout)
