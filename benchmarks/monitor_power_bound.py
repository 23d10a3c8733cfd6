"""What a change leaves in the data: the most any test could see of it (issue 28).

    taskset -c 0 python benchmarks/monitor_power_bound.py --kind stiffness --lives 50
    taskset -c 0 python benchmarks/monitor_power_bound.py --kind term --framework output-only --seconds 10 --windows 6 --change-at 3

For each life of `monitor_lives.py` with the same arguments (the same zoo members, force, noise
and schedule; output-only lives from accelerometers), the windows' own drift statistics: the
`within` windows after the change pooled (`G1`, their spread `Omega1`) against the (at most
`within`) windows before it (`G0`, `Omega0`). A test that knew the change's direction `c_j` on
each drift equation's library (a 5% drop of row j of `M^-1 K` on the displacement terms, or the
zoo term that appears) and tested nothing else, with the coefficients common to both sides
unknown (as they are), sees `z^2 = sum_j (c_j^T H_j c_j)^2 / c_j^T V_j c_j`: `H = G1 (G0 +
G1)^+ G0` the two sides' parallel sum (the shift's signal in the window's score) and `V` the
score's covariance (`s^2 (G1 - H)` plus the states' error through `Omega`, as
`dtwin_jax.monitor.change` has it; `s^2` the windows' residual variance). Below 3.09
(one-sided, p = 0.001, the monitor's false-alarm rate with no correction for its several
tests) not even that test flags the change in time. `z_fixed` is the same with the common
coefficients known (each side's information along `c` alone): it ignores what the unknown
coefficients absorb, so it overstates what any test sees. `z_seen` is the data's realized
score along the change, standardized (it scatters around `z` by about 1 if the data shift by
`c`; well below, the regression on estimated states sees less of the change than its column
says). Prints each life's numbers, then the count.
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


def _sums(results, j):
    """Equation j's Gram matrix, score spread, residual sum of squares and degrees of freedom,
    and ``X^T y``, over ``results``."""
    G = sum(np.asarray(r.statistics["drift"].gram)[j] for r in results)
    b = sum(np.asarray(r.statistics["drift"].xty)[j] for r in results)
    omega = sum(np.asarray(r.statistics["drift_spread"].gram)[j] if r.statistics.get("drift_spread") is not None
                else np.zeros_like(G) for r in results)
    rss = dof = 0.0
    for r in results:
        st = r.statistics["drift"]
        Gw, bw = np.asarray(st.gram)[j], np.asarray(st.xty)[j]
        rss += max(float(np.asarray(st.yty)[j]) - bw @ np.linalg.pinv(Gw) @ bw, 0.0)
        dof += max(float(np.asarray(st.n)[j]) - np.linalg.matrix_rank(Gw), 1.0)
    return G, omega, rss, dof, b


def _signal_to_noise(ex, kind: str, before, after) -> tuple[float, float, float]:
    """``(z, z_fixed, z_seen)`` of the change between the windows ``before`` and ``after``
    (updates); ``z_seen`` is the score's realized projection on the change, ``c^T g / sqrt(c^T V
    c)``, signed and summed over equations as ``z`` is (a draw around ``z`` if the data shift by
    ``c``)."""
    z2 = z2_fixed = seen = 0.0
    for j, eq in enumerate(e for e in after[0].equations if e.kind == "drift"):
        c = _change(ex, kind, eq)
        (G0, O0, r0, d0, b0), (G1, O1, r1, d1, b1) = _sums(before, j), _sums(after, j)
        scale = 1.0 / np.sqrt(np.maximum(np.diag(G1), 1e-300))  # unit diagonal, as the test scales
        G0, G1, O0, O1 = (scale[:, None] * A * scale[None, :] for A in (G0, G1, O0, O1))
        b0, b1, c = scale * b0, scale * b1, c / scale
        s2 = (r0 + r1) / (d0 + d1)
        P = np.linalg.pinv(G0 + G1)
        B = G1 @ P
        A = np.eye(len(c)) - B
        H = B @ G0
        V = s2 * (G1 - B @ G1) + A @ O1 @ A.T + B @ O0 @ B.T
        signal, noise = c @ H @ c, c @ V @ c
        if signal > 0:
            z2 += signal**2 / noise
            seen += signal / np.sqrt(noise) * (c @ (b1 - G1 @ P @ (b0 + b1))) / np.sqrt(noise)
        i0, i1 = (c @ G @ c for G in (G0, G1))
        if i0 > 0 and i1 > 0:
            info = [i**2 / (s2 * i + c @ O @ c) for i, O in ((i0, O0), (i1, O1))]
            z2_fixed += 1.0 / (1.0 / info[0] + 1.0 / info[1])
    z = float(np.sqrt(z2))
    return z, float(np.sqrt(z2_fixed)), float(seen / z) if z > 0 else 0.0


def life(seed: int, kind: str, framework: str, seconds: float, W: int, k: int, within: int) -> dict:
    member = zoo.draw_member(seed)
    ex = member.example._replace(duration=seconds)
    scale, stiffness = _schedules(kind, W, k)
    output_only = framework == "output-only"
    windows = simulate_life(ex, jax.random.key(seed), scale=scale, stiffness=stiffness, level=0.05,
                            output_only=output_only)
    library = ex.library_output_only if output_only else ex.library
    results = []
    for i in range(max(0, k - within), min(W, k + within)):
        w = windows[i]
        data = {"t": w["t"], "xdot": w["xdot"], "xdot_names": w["xdot_names"]} if output_only else w
        results.append(update_from_data(framework, ex.system.nominal, data, library=library, settings=MONITOR_SETTINGS))
    split = min(k, within)
    z, z_fixed, z_seen = _signal_to_noise(ex, kind, results[:split], results[split:])
    return {"seed": seed, "family": member.family, "z": z, "z_fixed": z_fixed, "z_seen": z_seen}


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
            f"- median z: {np.median([r['z'] for r in rows]):.2f} (with the common coefficients known: "
            f"{np.median([r['z_fixed'] for r in rows]):.2f}, {sum(r['z_fixed'] < THRESHOLD for r in rows)} below)",
            "- realized score along the change more than 3 below z: "
            + (", ".join(f"{r['seed']} {r['family']} ({r['z_seen']:.2f} against {r['z']:.2f})"
                         for r in rows if r["z_seen"] < r["z"] - 3) or "none")], a.out)


if __name__ == "__main__":
    main()
