"""Gibbs sweep cost versus library size K and number of samples N.

    python benchmarks/sampler_speed.py

The kernel works from sufficient statistics, so a sweep's cost depends on K (and the active
set), not on N. Times exclude compilation; 4 chains vmapped. The last column: the plain Gibbs
sweep without the exchange move (``swap=False``), for its cost.
"""

import time

import jax
import numpy as np

import dtwin_jax  # noqa: F401
from dtwin_jax import sampler as S


def main():
    print(f"{jax.devices()[0].platform}")
    print("| K | N | sweeps/s (4 chains) | ms per chain-sweep | without the exchange move |")
    print("|---|---|---|---|---|")
    for K in (15, 46, 115, 258):
        for N in (1_000, 100_000):
            rng = np.random.default_rng(0)
            L = rng.normal(size=(N, K))
            y = L[:, :3] @ np.array([1.0, -2.0, 0.5]) + 0.1 * rng.normal(size=N)
            st = S.suff_stats(L, y)
            draws = 500
            ms = {}
            for swap in (True, False):
                kwargs = {"num_draws": draws, "num_burnin": 0, "num_chains": 4, "swap": swap}
                S.sample_jit(jax.random.key(0), st, **kwargs).gamma.block_until_ready()
                t0 = time.perf_counter()
                S.sample_jit(jax.random.key(1), st, **kwargs).gamma.block_until_ready()
                ms[swap] = time.perf_counter() - t0
            dt = ms[True]
            print(f"| {K} | {N} | {draws / dt:.0f} | {1e3 * dt / draws / 4:.3f} | {1e3 * ms[False] / draws / 4:.3f} |")

if __name__ == "__main__":
    main()
