"""A Coulomb-friction twin predicted over 25 s at 1 kHz under a held input (issue 25).

    taskset -c 0 python benchmarks/predict_friction.py [DRAWS]     # default 100, the CLI's

The twin: the nominal oscillator M = 1, C = 2, K = 1000 (5 Hz) plus `-2 sign(x2)` (library
poly:1,sign; the draws spread 5% around it), x0 = [0.01, 0], a random input of std 10 held
over each 1 ms sample (the mass sticks at some velocity reversals). Adaptive Dopri8
chattered on sign(x2) for minutes and then ran out of steps; predict now takes fixed Bosh3
steps (4 per sample here, `prediction.fixed_substeps`). Prints the wall time of `predict`
(compilation included, a fresh process; then a second call, compiled), the same with the
progress bar (chunks of a tenth of the draws, as the CLI runs it), and the relative RMS
error per state (RMS difference / RMS of the reference) of every draw against the same draw
simulated at 16x smaller fixed steps.
"""

import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import dtwin_jax  # noqa: F401  (float64)
from dtwin_jax.library import parse_library
from dtwin_jax.models import systems
from dtwin_jax.models.prediction import UpdatedTwin, fixed_substeps, predict
from dtwin_jax.models.systems import LinearSecondOrder


def main(draws: int = 100) -> None:
    nominal = LinearSecondOrder.create([[1.0]], [[2.0]], [[1000.0]], [[1.0]])
    lib = parse_library("poly:1,sign", 2, 1)
    coef = np.zeros((draws, 1, lib.K))
    coef[:, 0, lib.names.index("sign(x2)")] = -2.0 * (1 + 0.05 * np.random.default_rng(0).standard_normal(draws))
    twins = UpdatedTwin(nominal, lib, (1,), jnp.asarray(coef), state_range=jnp.array([[-0.05, 0.05], [-1.0, 1.0]]))
    t = np.arange(25000) * 1e-3
    u = 10.0 * np.asarray(jax.random.normal(jax.random.key(1), (t.size, 1)))
    x0 = np.array([0.01, 0.0])
    sub = fixed_substeps(nominal, t)
    for label, progress in (("first call (compilation included)", False), ("second call", False),
                            ("with the progress bar (first call)", True)):
        start = time.perf_counter()
        out = predict(twins, x0, t, u, progress=progress)
        jax.block_until_ready(out["mean"])
        print(f"predict, {draws} draws, 25 s at 1 kHz, {sub} fixed steps per sample, {label}: "
              f"{time.perf_counter() - start:.2f} s")
    fine = jax.jit(jax.vmap(lambda c: systems.simulate(
        UpdatedTwin(nominal, lib, (1,), c), jnp.asarray(x0), jnp.asarray(t), jnp.asarray(u), substeps=16 * sub)[0]))
    reference = np.asarray(fine(twins.coefficients))
    paths = np.asarray(out["paths"])
    error = np.sqrt(np.mean((paths - reference) ** 2, axis=1)) / np.sqrt(np.mean(reference**2, axis=1))
    print(f"relative RMS error against {16 * sub} steps per sample, per state: max over draws "
          f"{error.max(axis=0)}, median {np.median(error, axis=0)}")
    print(f"share of samples where the input is below the friction force: {np.mean(np.abs(u) < 2.0):.3f}")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 100)
