"""Example 3's degradation forecast (issue 9): damage, stiffness loss and failure probability.

    python benchmarks/degradation.py [--horizon 20] [--draws 100]

Updates example 3 (input-output, 5% noise, 1 s), then simulates 100 joint posterior twins
over a longer service window under a new white-noise input, beside the true system.
Prints how often the true damage and stiffness loss lie inside the twins' 95% band, and
the failure probability for a critical damage the truth passes at 2/3 of the horizon;
writes docs/degradation-example3.png and docs/prediction-example3.png.
"""

import argparse
import time

import jax
import numpy as np

import dtwin_jax  # noqa: F401  (float64)
from dtwin_jax import (
    SamplerSettings,
    posterior_twins,
    predict,
    simulation_error,
    update_input_output,
)
from dtwin_jax.models import systems
from dtwin_jax.models.prediction import degradation_forecast
from dtwin_jax.plots import plot_degradation, plot_prediction
from dtwin_jax.preprocess.measurement import measure


def main(horizon: float, draws: int):
    ex = systems.EXAMPLES["example3"]()
    sim = systems.simulate_example(ex, jax.random.key(0))
    meas = measure(jax.random.key(1), sim["t"], sim["x"], sim["xdot"], sim["u"], level=0.05)
    result = update_input_output(ex.system.nominal, meas.t, meas.x, meas.u, meas.xdot, library=ex.library,
                                 settings=SamplerSettings(num_chains=2, num_draws=1000, num_burnin=500))
    print(result.summary())
    new = systems.simulate_example(ex, jax.random.key(7), duration=horizon)
    twins = posterior_twins(result, draws, jax.random.key(3))
    start = time.perf_counter()
    pred = predict(twins, ex.x0, new["t"], new["u"])
    seconds = time.perf_counter() - start
    truth = np.asarray(new["x"][:, 2])
    critical = float(truth[2 * truth.size // 3])
    fc = degradation_forecast(twins, pred, 2, critical)
    inside = np.mean((truth >= fc["damage_lower"]) & (truth <= fc["damage_upper"]))
    true_loss = 0.5 * (1.0 - np.exp(-truth[::10]))
    loss_in = np.mean((true_loss >= fc["loss_lower"][:, 0] - 1e-4) & (true_loss <= fc["loss_upper"][:, 0] + 1e-4))
    crossing = np.flatnonzero(truth > critical)[0]
    p = fc["probability"]
    half = fc["t"][np.flatnonzero(p >= 0.5)[0]]
    print(f"{draws} twins over {horizon:g} s ({seconds:.1f} s): true damage inside the 95% band {100 * inside:.2f}% "
          f"of samples, true stiffness loss {100 * loss_in:.2f}%; final loss {100 * true_loss[-1]:.2f}% (twins "
          f"{100 * fc['loss_lower'][-1, 0]:.2f}..{100 * fc['loss_upper'][-1, 0]:.2f}%)")
    print(f"critical damage {critical:.4f}: the truth passes it at {fc['t'][crossing]:.2f} s; failure probability "
          f"there {p[crossing]:.2f}, 1/2 reached at {half:.2f} s, {p[-1]:.2f} at {horizon:g} s")
    print("normalised RMSE of the mean, x1 x2 x3:", np.round(100 * simulation_error(pred["mean"], new["x"])["nrmse"], 2), "%")
    plot_degradation(fc, truth, "docs/degradation-example3.png")
    # The first 3 s of every (N, m) array (and of t); per-state summaries as they are.
    short = {k: np.asarray(v)[:3000] if k == "t" else np.asarray(v)[..., :3000, :] if np.ndim(v) >= 2 else v
             for k, v in pred.items() if k != "paths"}
    plot_prediction(short, np.asarray(new["x"])[:3000], names=["x1", "x2", "x3 (damage)"], units=["m", "m/s", "-"],
                    path="docs/prediction-example3.png")
    print("wrote docs/degradation-example3.png, docs/prediction-example3.png")


if __name__ == "__main__":
    a = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    a.add_argument("--horizon", type=float, default=20.0)
    a.add_argument("--draws", type=int, default=100)
    args = a.parse_args()
    main(args.horizon, args.draws)
