"""Cold and warm end-to-end updates of example 1, stage by stage (issue 10 groundwork).

    taskset -c 0 python benchmarks/update_speed.py

Input-output: one 1 s record, measured rates (kinematic smoother), 4 chains x 2000 draws.
Output-only: 100 records x 1 s at 5% noise, 2 chains x 600 draws (the suite's settings).
Each update runs twice in one process: the first includes compilation, the second reuses it.
"""

import time

import jax
import numpy as np

import dtwin_jax  # noqa: F401  (float64)
from dtwin_jax import SamplerSettings, systems, update_input_output, update_output_only
from dtwin_jax.measurement import add_noise, measure


def timed(label, fn):
    for run in ("cold", "warm"):
        start = time.perf_counter()
        fn()
        print(f"{label:32s} {run}: {time.perf_counter() - start:6.2f} s")


def main():
    ex = systems.EXAMPLES["example1"]()
    sim = systems.simulate_example(ex, jax.random.key(0))
    meas = measure(jax.random.key(1), sim["t"], sim["x"], sim["xdot"], sim["u"], level=0.05)
    timed("input-output, 1 s, 4 x 2000", lambda: update_input_output(
        ex.system.nominal, meas.t, meas.x, meas.u, meas.xdot, library=ex.library))
    oo = ex.for_output_only()
    sde = systems.simulate_example_sde(oo, jax.random.key(0), num_records=100)
    x = np.asarray(add_noise(jax.random.key(1), sde["x"], 0.05))
    fast = SamplerSettings(num_chains=2, num_draws=600, num_burnin=300)
    timed("output-only, 100 x 1 s, 2 x 600", lambda: update_output_only(
        oo.system.nominal, sde["t"], x, library=oo.library_output_only, settings=fast))


if __name__ == "__main__":
    main()
