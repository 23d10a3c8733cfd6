"""The output-only pipeline's two heavy programs, timed apart: the Kramers-Moyal drift
statistics (with their first-pass sampler) and the diffusion likelihood's maximum.

    taskset -c 1 python benchmarks/output_only_speed.py [--examples example1 example2] [--records 300 100]

For each example (5% noise, `records` x 1 s): compilation and run time of
`output_only_drift_stats`, and the first (tracing and compilation included) and second call
of `statespace.diffusion_mle` from the true drift, started 30% off.
"""

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax.library import parse_library
from dtwin_jax.models import systems
from dtwin_jax.output_only import kramers_moyal, statespace
from dtwin_jax.output_only.stats import output_only_drift_stats
from dtwin_jax.preprocess.measurement import add_noise


def _seconds(fn) -> float:
    start = time.perf_counter()
    jax.block_until_ready(fn())
    return time.perf_counter() - start


def run(name: str, records: int) -> None:
    ex = systems.EXAMPLES[name]().for_output_only()
    sim = systems.simulate_example_sde(ex, jax.random.key(0), num_records=records)
    x = jnp.asarray(add_noise(jax.random.key(1), sim["x"], 0.05))
    nominal = ex.system.nominal
    lib = parse_library(ex.library_output_only, nominal.m, 0)
    noise = kramers_moyal.noise_variance(x)
    args = (nominal, lib, x, ex.dt, noise, jax.random.key(0))
    start = time.perf_counter()
    compiled = output_only_drift_stats.lower(*args).compile()
    compile_s = time.perf_counter() - start
    dynamic = args[:1] + args[2:]  # lib is static
    run_s = min(_seconds(lambda: compiled(*dynamic)) for _ in range(2))
    print(f"{name}, {records} x 1 s, K = {lib.K}: drift statistics compile {compile_s:.1f} s, run {run_s:.2f} s")
    step = statespace.DriftStep.true(ex)
    y = statespace.segments(x)
    start_gamma = 1.3 * jnp.asarray(list(ex.true_diffusion().values()))
    mle = lambda: statespace.diffusion_mle(step, y, noise, start_gamma)
    first, second = _seconds(mle), _seconds(mle)
    gamma = np.asarray(mle()[0])
    print(f"{name}: diffusion likelihood first call {first:.1f} s, second {second:.2f} s, Gamma {gamma}")


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--examples", nargs="+", default=["example1", "example2"])
    p.add_argument("--records", type=int, nargs="+", default=[300, 100])
    a = p.parse_args()
    for name, records in zip(a.examples, a.records):
        run(name, records)


if __name__ == "__main__":
    main()
