"""The weak form's covariance on long records: banded against dense, record by record length.

    taskset -c 0 python benchmarks/weak_form_long.py --seconds 10 20 40

For records of each length at 1 kHz (window 100 samples, stride 12: one period of a 10 Hz
mode, as the accelerometer route picks), times (a) the Gram matrices of the three smooth
filters (``window_grams`` from the kernels against the dense ``(W, N)`` products) and (b)
the equation error's REML weight over its 33 grid points (``reml_weight``, the banded
Cholesky factor against the dense one), on a random 19-column library, and checks that the
two give the same numbers. ``--dense-up-to`` skips the dense products above that length
(they grow as ``W^2 N``).
"""

import argparse
import time

import numpy as np

import dtwin_jax  # noqa: F401  (float64)
from dtwin_jax.preprocess import weak_form as wf


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seconds", type=float, nargs="+", default=[10, 20, 40])
    parser.add_argument("--dense-up-to", type=float, default=40.0, help="record length (s)")
    args = parser.parse_args()
    width, stride, dt = 100, 12, 1e-3
    kernels = wf.bump_functions(width, dt, wf.TEST_POWER)[:3]
    rng = np.random.default_rng(0)
    print("| record | windows W | Gram, banded | Gram, dense | REML, banded | REML, dense | largest difference |")
    print("|---|---|---|---|---|---|---|")
    for seconds in args.seconds:
        N = int(round(seconds / dt))
        W = (N - width) // stride + 1
        t0 = time.perf_counter()
        G = wf.window_grams(kernels, W, stride)
        t_band = time.perf_counter() - t0
        t_dense, diff = float("nan"), 0.0
        if seconds <= args.dense_up_to:
            Phi, dPhi, _, ddPhi = wf.window_quadrature(N, dt, width, stride, wf.TEST_POWER, held=False, second=True)
            t0 = time.perf_counter()
            dense = np.array([[a @ b.T for b in (Phi, dPhi, ddPhi)] for a in (Phi, dPhi, ddPhi)])
            t_dense = time.perf_counter() - t0
            diff = float(np.max(np.abs(dense - G)) / np.max(np.abs(dense)))
            del Phi, dPhi, ddPhi, dense
        S_x, S_w = 0.3 * G[0, 0] + 0.1 * G[1, 1] + 0.05 * (G[0, 1] + G[1, 0]), G[2, 2]
        L = rng.normal(size=(1, W, 19))
        Y = L @ rng.normal(size=19) + rng.normal(size=(1, W))
        t0 = time.perf_counter()
        lam_band = wf.reml_weight(L, Y, S_x, S_w)
        t_reml_band = time.perf_counter() - t0
        t_reml_dense = float("nan")
        if seconds <= args.dense_up_to:
            banded_width = wf._bandwidth
            wf._bandwidth = lambda c: c.shape[0]  # the dense factor, as before the band
            try:
                t0 = time.perf_counter()
                lam_dense = wf.reml_weight(L, Y, S_x, S_w)
                t_reml_dense = time.perf_counter() - t0
            finally:
                wf._bandwidth = banded_width
            diff = max(diff, abs(lam_band - lam_dense) / abs(lam_dense))
        print(f"| {seconds:g} s | {W} | {t_band:.2f} s | {t_dense:.2f} s | {t_reml_band:.2f} s | "
              f"{t_reml_dense:.2f} s | {diff:.1e} |", flush=True)


if __name__ == "__main__":
    main()
