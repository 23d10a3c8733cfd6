"""Fleets (issue 28): eight structures' windows tested and absorbed by one program; the
same program sharded over 8 virtual CPU devices, in one process and (``pytest -m slow``) in
two processes joined by jax.distributed, gives the same alarms, inclusion probabilities and
draws, and the same numbers to rounding."""

import os
import socket
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from fleet_settings import STATIC

import dtwin_jax  # noqa: F401  (float64)
from dtwin_jax.models import zoo
from dtwin_jax.models.lives import simulate_life
from dtwin_jax.monitor.fleet import fleet_init, fleet_step

F = 8


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """Zoo members 0-7 (one SDOF of each family), 2 windows; members 0-3 gain their term in
    window 1, members 4-7 stay linear. The plain (one-device, unsharded) run."""
    members = [zoo.draw_member(s) for s in range(F)]
    lives = [simulate_life(m.example, jax.random.key(i), scale=[0.0, float(i < 4)]) for i, m in enumerate(members)]
    data = {k: np.stack([[w[k] for w in life] for life in lives]) for k in ("x", "u", "xdot")}
    nominal = jax.tree.map(lambda *a: jnp.stack(a), *[m.example.system.nominal for m in members])
    keys = [jax.vmap(lambda i: jax.random.fold_in(jax.random.key(w), i))(jnp.arange(F)) for w in range(2)]
    step = jax.jit(lambda *a: fleet_step(*a, **STATIC))
    state, runs = fleet_init(F, 1, STATIC["lib"].K), []
    for w in range(2):
        state, report = step(state, data["x"][:, w], data["u"][:, w], data["xdot"][:, w], nominal, keys[w])
        runs.append((state, report))
    src = tmp_path_factory.mktemp("fleet") / "in.npz"
    np.savez(src, **data, **{k: np.asarray(getattr(nominal, k)) for k in ("M", "C", "K", "B", "F0")},
             keys=np.stack([jax.random.key_data(k) for k in keys]))
    return members, runs, src


def test_one_program_flags_the_structures_that_changed(fleet):
    members, runs, _ = fleet
    (_, first), (_, second) = runs
    assert not np.any(first.alarm) and np.all(first.p_value == 1.0)
    assert np.array_equal(np.asarray(second.alarm), [True] * 4 + [False] * 4)
    assert np.all(np.asarray(second.p_value[:4]) < 1e-6) and np.all(np.asarray(second.p_value[4:]) > 1e-3)
    # After the restart each changed twin holds its term (example names of zoo.FAMILIES).
    names = STATIC["lib"].names
    for i in range(4):
        (term,) = members[i].example.true_terms["x2"]
        assert float(second.pip[i, 0, names.index(term)]) > 0.5, (members[i].family, term)


def _sharded(src, out_dir, processes):
    """Every leaf of the sharded run over 8 CPU devices in ``processes`` processes
    (jax.distributed on localhost when more than one), the shards put back together."""
    env = {**os.environ, "XLA_FLAGS": f"--xla_force_host_platform_device_count={8 // processes}",
           "PYTHONPATH": str(Path(__file__).parent)}
    script = str(Path(__file__).parent / "fleet_sharded.py")
    outs = [out_dir / f"out{r}.npz" for r in range(processes)]
    if processes == 1:
        commands = [[sys.executable, script, str(src), str(outs[0])]]
    else:
        with socket.socket() as s:  # a free port for the coordinator
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        commands = [[sys.executable, script, str(src), str(o), str(r), str(processes), str(port)]
                    for r, o in enumerate(outs)]
    running = [subprocess.Popen(c, env=env) for c in commands]
    try:
        assert all(p.wait(timeout=300) == 0 for p in running)
    finally:
        for p in running:
            p.kill()
    shards = {}
    for o in outs:
        with np.load(o) as f:
            for name in f.files:
                leaf, start = name.rsplit("_", 1)
                shards.setdefault(leaf, []).append((int(start), f[name]))
    return {leaf: np.concatenate([a for _, a in sorted(parts, key=lambda p: p[0])]) for leaf, parts in shards.items()}


def _assert_sharded_equals_plain(runs, sharded):
    for w, run in enumerate(runs):
        for i, (a, name) in enumerate(zip(jax.tree.leaves(run), _names(run))):
            b, a = sharded[f"w{w}_{i}"], np.asarray(a)
            if a.dtype == bool or name in ("pip",):  # decisions and inclusion frequencies: the same
                assert np.array_equal(a, b), (w, name)
            else:  # the same arithmetic compiled for another batch: rounding apart
                np.testing.assert_allclose(b, a, rtol=1e-6, atol=1e-12, err_msg=f"window {w}, {name}")


def test_sharded_over_eight_devices_in_one_process_equals_one_device(fleet, tmp_path):
    """8 virtual CPU devices in one process: the sharded program's numbers are the plain one's."""
    _, runs, src = fleet
    _assert_sharded_equals_plain(runs, _sharded(src, tmp_path, 1))


@pytest.mark.slow  # both processes compile the sharded program: twice the one-process test's time
def test_sharded_over_eight_devices_in_two_processes_equals_one_device(fleet, tmp_path):
    """8 virtual CPU devices, 4 in each of two processes joined by jax.distributed on
    localhost."""
    _, runs, src = fleet
    _assert_sharded_equals_plain(runs, _sharded(src, tmp_path, 2))


def _names(run):
    state, report = run
    return ["mean", "cov", "sigma2", "gram", "xty", "yty", "n", "rgram", "rxty", "ryty", "rn", "rmean", "rcov",
            "rsigma2", "count", "ratio_sum", "ratio_count", "fresh", *report._fields]
