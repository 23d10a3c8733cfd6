"""What a change leaves in the data: the most any test could see of it (issue 28).

    taskset -c 0 python benchmarks/monitor_power_bound.py --kind stiffness --lives 50
    taskset -c 0 python benchmarks/monitor_power_bound.py --kind term --framework output-only --seconds 10 --windows 6 --change-at 3

For each life of `monitor_lives.py` with the same arguments (the same zoo members, force, noise
and schedule; output-only lives from accelerometers), the first changed window's drift
statistics give the change's signal-to-noise ratio along its own direction,
`z1^2 = sum_j (c_j^T G_j c_j)^2 / (s_j^2 c_j^T G_j c_j + c_j^T Omega_j c_j)` over the drift
equations: `c_j` the change of equation j's coefficients (a 5% drop of row j of `M^-1 K` on
the displacement terms, or the zoo term that appears), `G_j` the window's Gram matrix, `s_j`
its residual standard deviation and `Omega_j` its score's spread from the states' estimation
error (output-only; zero otherwise). That is the most a window can say about a change known to
lie in that one direction. Pooling the `within` windows after the change against a twin that
holds as many before it (half the information goes to the twin's own uncertainty), a test
that knew the direction and tested nothing else would see `z = z1 sqrt(within / 2)`; below
3.09 (one-sided, p = 0.001, the monitor's false-alarm rate with no correction for its several
tests) not even that test flags the change in time. Prints each life's `z1` and `z`, then the
count.
"""

import argparse
import json

import jax
import numpy as np
from monitor_lives import _schedules, report

import dtwin_jax  # noqa: F401  (float64)
from dtwin_jax.models import zoo
from dtwin_jax.models.lives import simulate_life
from dtwin_jax.monitor import MONITOR_SETTINGS
from dtwin_jax.update.from_data import update_from_data

THRESHOLD = 3.09  # one-sided normal quantile at 1e-3


def _change(ex, kind: str, eq) -> np.ndarray:
    """The change of one drift equation's coefficients, on its library's columns."""
    c = np.zeros(len(eq.names))
    nominal = ex.system.nominal
    if kind == "stiffness":
        drop = 0.05 * np.linalg.solve(np.asarray(nominal.M), np.asarray(nominal.K))  # (d, d)
        r = list(nominal.velocity_index).index(nominal.state_names.index(eq.state))
        for i in range(nominal.d):
            c[eq.names.index(nominal.state_names[i])] = drop[r, i]
    else:
        for term, value in ex.true_terms.get(eq.state, {}).items():
            c[eq.names.index(term)] = value
    return c


def life(seed: int, kind: str, framework: str, seconds: float, W: int, k: int, within: int) -> dict:
    member = zoo.draw_member(seed)
    ex = member.example._replace(duration=seconds)
    scale, stiffness = _schedules(kind, W, k)
    output_only = framework == "output-only"
    w = simulate_life(ex, jax.random.key(seed), scale=scale, stiffness=stiffness, level=0.05,
                      output_only=output_only)[k]
    data = {"t": w["t"], "xdot": w["xdot"], "xdot_names": w["xdot_names"]} if output_only else w
    result = update_from_data(framework, ex.system.nominal, data,
                              library=ex.library_output_only if output_only else ex.library, settings=MONITOR_SETTINGS)
    st, spread = result.statistics["drift"], result.statistics.get("drift_spread")
    z2 = 0.0
    for j, eq in enumerate(e for e in result.equations if e.kind == "drift"):
        c = _change(ex, kind, eq)
        G, b = np.asarray(st.gram)[j], np.asarray(st.xty)[j]
        yty, n = float(np.asarray(st.yty)[j]), float(np.asarray(st.n)[j])
        s2 = (yty - b @ np.linalg.pinv(G) @ b) / max(n - np.linalg.matrix_rank(G), 1.0)
        omega = np.asarray(spread.gram)[j] if spread is not None else np.zeros_like(G)
        signal = c @ G @ c
        if signal > 0:
            z2 += signal**2 / (s2 * signal + c @ omega @ c)
    z1 = float(np.sqrt(z2))
    return {"seed": seed, "family": member.family, "z1": z1, "z": z1 * np.sqrt(within / 2.0)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kind", choices=("term", "stiffness"), default="stiffness")
    ap.add_argument("--framework", choices=("input-output", "output-only"), default="input-output")
    ap.add_argument("--lives", type=int, default=50)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--windows", type=int, default=11)
    ap.add_argument("--change-at", type=int, default=5)
    ap.add_argument("--within", type=int, default=None, help="windows after the change (default: 3 for a term, 5 for stiffness)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    within = a.within or (3 if a.kind == "term" else 5)
    rows = []
    for seed in range(a.first_seed, a.first_seed + a.lives):
        rows.append(life(seed, a.kind, a.framework, a.seconds, a.windows, a.change_at, within))
        print(json.dumps(rows[-1]), flush=True)
    below = [r for r in rows if r["z"] < THRESHOLD]
    report([f"## {a.framework}, {a.kind} at window {a.change_at}, {a.seconds:g} s windows: the best test's "
            f"signal-to-noise over {within} windows, {a.lives} lives (seeds {a.first_seed}..)", "",
            f"- below {THRESHOLD} (no test flags it within {within} windows at 1e-3): **{len(below)} / {len(rows)}**: "
            + ", ".join(f"{r['seed']} {r['family']} ({r['z']:.2f})" for r in below),
            f"- median z: {np.median([r['z'] for r in rows]):.2f}"], a.out)


if __name__ == "__main__":
    main()
