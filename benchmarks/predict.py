"""The updated twin on a 10 s excitation never seen in training (issue 9's first must-show).

    python benchmarks/predict.py example1 input-output     # or output-only; example1..3

Updates the twin at 5% noise (input-output: 1 s at 1 kHz; output-only: 100 records x 1 s),
draws 100 joint posterior twins and simulates them: input-output under a new white-noise
input, output-only on the truth's own Brownian path (`shared_path`), then on independent
paths for the calibration of the 95% band. Prints the normalised RMSE (RMS error / std of
the truth) of the twin's mean and of the nominal model, per state.
"""

import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import dtwin_jax  # noqa: F401  (float64)
from dtwin_jax import (
    SamplerSettings,
    posterior_twins,
    predict,
    simulation_error,
    update_input_output,
    update_output_only,
)
from dtwin_jax.models import systems
from dtwin_jax.preprocess.measurement import add_noise, measure


def main(name: str, mode: str):
    settings = SamplerSettings(num_chains=2, num_draws=1000, num_burnin=500)
    ex = systems.EXAMPLES[name]()
    start = time.perf_counter()
    if mode == "input-output":
        sim = systems.simulate_example(ex, jax.random.key(0))
        meas = measure(jax.random.key(1), sim["t"], sim["x"], sim["xdot"], sim["u"], level=0.05)
        result = update_input_output(ex.system.nominal, meas.t, meas.x, meas.u, meas.xdot, library=ex.library,
                                     settings=settings)
        new = systems.simulate_example(ex, jax.random.key(7), duration=10.0)
        twins = posterior_twins(result, 100, jax.random.key(3))
        updated = time.perf_counter()
        pred = predict(twins, ex.x0, new["t"], new["u"])
        nominal = systems.simulate(ex.system.nominal, ex.x0, new["t"], new["u"])[0]
        truth = new["x"]
    else:
        ex = ex.for_output_only()
        sim = systems.simulate_example_sde(ex, jax.random.key(0), num_records=100)
        x = add_noise(jax.random.key(1), sim["x"], 0.05)
        result = update_output_only(ex.system.nominal, sim["t"], x, library=ex.library_output_only,
                                    settings=settings)
        t = jnp.arange(10001) * ex.dt
        key = jax.random.key(7)
        truth = systems.simulate_sde(ex.system, ex.x0, t, key)
        twins = posterior_twins(result, 100, jax.random.key(3))
        updated = time.perf_counter()
        pred = predict(twins, ex.x0, t, key=key, shared_path=True)
        nominal = systems.simulate_sde(ex.system.nominal, ex.x0, t, key)
        band = predict(twins, ex.x0, t, key=jax.random.key(11))
        other = np.asarray(systems.simulate_sde(ex.system, ex.x0, t, jax.random.key(12)))
        inside = np.mean((other >= np.asarray(band["lower"])) & (other <= np.asarray(band["upper"])), axis=0)
        print("independent paths: share of samples inside the 95% band", np.round(inside, 3))
    print(result.summary())
    pct = lambda e: np.round(100 * e, 2).tolist()
    print(f"{name} {mode}: normalised RMSE of the twin's mean {pct(simulation_error(pred['mean'], truth)['nrmse'])}%, "
          f"nominal {pct(simulation_error(nominal, truth)['nrmse'])}% "
          f"(update {updated - start:.1f} s, prediction {time.perf_counter() - updated:.1f} s)")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
