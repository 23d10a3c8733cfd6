"""Posterior-predictive checks of an updated twin (dtwin_jax.models.prediction), called from the tests
that already update each example in each framework (one update, not two).

10 s of excitation never seen in training; normalised RMSE = RMS error / std of the truth.
"""

import tempfile

import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax import posterior_twins, predict, simulate, simulation_error
from dtwin_jax.io.store import load_twin, save_twin
from dtwin_jax.models import systems
from dtwin_jax.models.prediction import degradation_forecast


def check_input_output_prediction(ex, result, tol=0.05, draws=30):
    new = systems.simulate_example(ex, jax.random.key(7), duration=10.0)
    twins = posterior_twins(result, draws, jax.random.key(3))  # the mean needs few draws
    assert twins.coefficients.shape == (draws, len(result.equations), len(result.library.names))
    pred = predict(twins, ex.x0, new["t"], new["u"])
    twin_err = simulation_error(pred["mean"], new["x"])["nrmse"]
    nominal_err = simulation_error(simulate(ex.system.nominal, ex.x0, new["t"], new["u"])[0], new["x"])["nrmse"]
    # The twin at the posterior mean is a pytree that the package's simulator jits.
    x, _ = simulate(result.twin, ex.x0, new["t"][:2000], new["u"][:2000])
    point_err = simulation_error(x, new["x"][:2000])["nrmse"]
    print("normalised RMSE on a new 10 s input, twin", twin_err, "nominal", nominal_err,
          "; posterior-mean twin over 2 s", point_err)
    assert np.all(twin_err < tol) and np.all(nominal_err > 1.0)
    assert np.all(pred["lower"] <= pred["upper"])  # (a skewed spread may put the mean outside)
    assert np.all(point_err < tol)


def check_output_only_prediction(ex, result, tol=0.10, *, mean_draws=100, band_draws=100, band_states=None,
                                 round_trip=True):
    """The truth's own Brownian path drives the twins (`shared_path`): the mean within
    `tol`; then independent paths: the truth inside the 95% band 90-99% of the time.

    `ex` as framework 2 simulates it (`Example.for_output_only`: its x0). The 90-99% applies
    to the states of `band_states` (default all); the others (an extra state such as a
    damage, which integrates the response: its band is the parameter uncertainty, not the
    path's, and one truth either lies inside all the time or not) must lie inside more
    than 95% of the time (`band_draws=0`: no band check). `round_trip`: also save, load and
    predict again."""
    mean_twins = posterior_twins(result, mean_draws, jax.random.key(3))
    assert mean_twins.stochastic
    t = jnp.arange(10001) * ex.dt
    key = jax.random.key(7)
    truth = systems.simulate_sde(ex.system, ex.x0, t, key)
    pred = predict(mean_twins, ex.x0, t, key=key, shared_path=True)
    twin_err = simulation_error(pred["mean"], truth)["nrmse"]
    nominal_err = simulation_error(systems.simulate_sde(ex.system.nominal, ex.x0, t, key), truth)["nrmse"]
    print("normalised RMSE on the truth's path, twin", twin_err, "nominal", nominal_err)
    assert np.all(twin_err < tol) and np.all(nominal_err > 1.0)
    if not band_draws:
        return
    twins = mean_twins if mean_draws == band_draws else posterior_twins(result, band_draws, jax.random.key(3))
    band = predict(twins, ex.x0, t, key=jax.random.key(11))
    other = np.asarray(systems.simulate_sde(ex.system, ex.x0, t, jax.random.key(12)))
    inside = np.mean((other >= np.asarray(band["lower"])) & (other <= np.asarray(band["upper"])), axis=0)
    print("independent paths inside the 95% band", inside)
    calibrated = np.zeros(inside.size, bool)
    calibrated[list(range(inside.size)) if band_states is None else list(band_states)] = True
    assert np.all((inside[calibrated] > 0.90) & (inside[calibrated] < 0.99)), inside
    assert np.all(inside[~calibrated] > 0.95), inside
    if not round_trip:
        return
    # Round trip: the saved and loaded twin (diffusion included) predicts identically.
    with tempfile.TemporaryDirectory() as tmp:
        save_twin(result, f"{tmp}/twin")
        loaded = load_twin(f"{tmp}/twin")
    again = predict(posterior_twins(loaded, band_draws, jax.random.key(3)), ex.x0, t, key=jax.random.key(11))
    np.testing.assert_array_equal(np.asarray(again["mean"]), np.asarray(band["mean"]))
    np.testing.assert_array_equal(np.asarray(again["upper"]), np.asarray(band["upper"]))


def check_degradation_forecast(ex, result, horizon=10.0, draws=30):
    """Example 3 over a `horizon` s service window under a new input: the twins' 95% band
    of the damage brackets the true damage path, and the failure-probability curve for a
    critical level the truth passes at 2/3 of the horizon rises from 0 to above 1/2."""
    new = systems.simulate_example(ex, jax.random.key(7), duration=horizon)
    twins = posterior_twins(result, draws, jax.random.key(3))
    pred = predict(twins, ex.x0, new["t"], new["u"])
    # Refined by output error: 0.93/0.86/0.43% (the Gibbs posterior's twins: 5.1/4.7/0.6%,
    # the truth's late-damage stiffness 1.9 posterior std from its mean on this seed).
    nrmse = simulation_error(pred["mean"], new["x"])["nrmse"]
    nominal = simulation_error(simulate(ex.system.nominal, ex.x0, new["t"], new["u"])[0], new["x"])["nrmse"]
    inside_band = np.mean((new["x"] >= pred["lower"]) & (new["x"] <= pred["upper"]), axis=0)
    print("normalised RMSE of the twins' mean", nrmse, "nominal", nominal, "; truth inside the 95% band", inside_band)
    assert np.all(nrmse < 0.01) and np.all(nominal[:2] > 1.0)
    truth = np.asarray(new["x"][:, 2])
    critical = float(truth[2 * truth.size // 3])
    fc = degradation_forecast(twins, pred, 2, critical)
    inside = np.mean((truth >= fc["damage_lower"]) & (truth <= fc["damage_upper"]))
    crossing = np.flatnonzero(truth > critical)[0]
    p = fc["probability"]
    true_loss = 0.5 * (1.0 - np.exp(-truth[:: 10]))  # 1 - lambda(x3) of the true law
    loss_inside = np.mean((true_loss >= fc["loss_lower"][:, 0] - 1e-4) & (true_loss <= fc["loss_upper"][:, 0] + 1e-4))
    print(f"damage inside the band {inside:.4f}; stiffness loss inside {loss_inside:.4f}; failure probability "
          f"at 2 s {p[2000]:.2f}, at the true crossing {p[crossing]:.2f}, at the end {p[-1]:.2f}")
    assert inside > 0.95 and loss_inside > 0.95
    assert np.all(np.diff(p) >= 0) and p[2000] == 0.0 and p[-1] > 0.5
