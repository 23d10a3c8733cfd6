"""Gibbs sweep cost versus library size K and number of samples N.

    python benchmarks/sampler_speed.py
    taskset -c 0 python benchmarks/sampler_speed.py --slots

``--slots``: the monitor's sampler (``MONITOR_SETTINGS``, chunked) on libraries of 17-24
terms, padded to 32 columns, in the default 24 active-set slots against 32 (the default
before), with the draws compared.

The kernel works from sufficient statistics, so a sweep's cost depends on K (and the active
set), not on N. Times exclude compilation; 4 chains vmapped. The last column: the plain Gibbs
sweep without the exchange move (``swap=False``), for its cost.
"""

import sys
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

def slots():
    from dtwin_jax.monitor import MONITOR_SETTINGS

    print(f"{jax.devices()[0].platform}; MONITOR_SETTINGS, sample_in_chunks, mean of 10 calls after one")
    print("| K | 24 slots (default) | 32 slots | same draws |")
    print("|---|---|---|---|")
    for K in (17, 19, 24):
        rng = np.random.default_rng(0)
        L = rng.normal(size=(1000, K))
        st = S.suff_stats(L, L[:, 0] - 0.5 * L[:, 3] + rng.normal(size=1000))
        seconds, draws = [], []
        for max_active in (None, 32):
            S.sample_in_chunks(jax.random.key(0), st, MONITOR_SETTINGS, max_active=max_active)
            t0 = time.perf_counter()
            for i in range(10):
                trace = S.sample_in_chunks(jax.random.key(i), st, MONITOR_SETTINGS, max_active=max_active)
            seconds.append((time.perf_counter() - t0) / 10)
            draws.append(trace)
        same = all(np.array_equal(getattr(draws[0], f), getattr(draws[1], f)) for f in ("gamma", "theta", "sigma2"))
        print(f"| {K} | {seconds[0]:.3f} s | {seconds[1]:.3f} s | {same} |")


if __name__ == "__main__":
    if "--slots" in sys.argv[1:]:
        slots()
        raise SystemExit
    main()
