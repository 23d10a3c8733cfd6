"""The weak (integral) form of framework 1: states without rates (dtwin_jax.weak_form)."""

import jax
import numpy as np
import pytest

from dtwin_jax import systems
from dtwin_jax.errors import DataError
from dtwin_jax.measurement import measure
from dtwin_jax.twin import SamplerSettings, update_input_output
from dtwin_jax.update.sampling import resolve_library
from dtwin_jax.weak_form import window_quadrature, weak_input_output_stats, weak_windows


def test_window_quadrature_integrates_by_parts():
    # int phi g' dt = -int phi' g dt for phi vanishing at the window's ends.
    t = np.arange(1000) * 1e-3
    Phi, dPhi, Phi_u = window_quadrature(t.size, 1e-3, 200, 25, 6)
    g, dg = np.sin(30 * t), 30 * np.cos(30 * t)
    np.testing.assert_allclose(Phi @ dg, -dPhi @ g, atol=1e-6)
    np.testing.assert_allclose(Phi.sum(axis=1), 1.0, rtol=1e-12)  # unit integral
    np.testing.assert_allclose(Phi_u.sum(axis=1), 1.0, rtol=1e-12)  # held weights: exact integral
    assert Phi.shape == (33, 1000)


def test_noise_free_duffing_recovers_the_cubic_term():
    ex = systems.example1()
    nominal = ex.system.nominal
    assert weak_windows(nominal, 1e-3, 1000) == (199, 24)
    sim = systems.simulate_example(ex, jax.random.key(0))
    lib = resolve_library("poly:3,input", nominal, nominal.n)
    stats, info = weak_input_output_stats(nominal, lib, sim["t"], np.asarray(sim["x"])[None],
                                          np.asarray(sim["u"])[None])
    assert info["method"] == "weak-form"
    coef = np.linalg.solve(np.asarray(stats.gram[0]), np.asarray(stats.xty[0]))
    truth = ex.true_coefficients(lib.names)[0]
    k = lib.names.index("x1**3")
    assert abs(coef[k] - truth[k]) / abs(truth[k]) < 1e-3
    # Every other term's contribution stays below 1e-3 of the cubic's over the record.
    x = np.asarray(sim["x"])
    scale = np.std(np.asarray(lib(x, np.asarray(sim["u"]))), axis=0)
    assert np.max(np.abs(np.delete(coef * scale, k))) < 1e-3 * abs(truth[k]) * scale[k]


def test_weak_route_needs_every_state_and_no_rates():
    ex = systems.example1()
    sim = systems.simulate_example(ex, jax.random.key(0), duration=0.3)
    with pytest.raises(DataError, match="weak"):
        update_input_output(ex.system.nominal, sim["t"], sim["x"], sim["u"], sim["xdot"], smoothing="weak")


def test_weak_route_duffing_at_5_percent_noise():
    # benchmarks/weak_form.py: median 0.79 %, max 1.7 % over these 4 seeds (poly:3,input).
    ex = systems.example1()
    settings = SamplerSettings(num_chains=2, num_draws=1000, num_burnin=500)
    errors = []
    for seed in range(4):
        sim = systems.simulate_example(ex, jax.random.key(seed))
        meas = measure(jax.random.key(seed + 1), sim["t"], sim["x"], None, sim["u"], level=0.05)
        res = update_input_output(ex.system.nominal, meas.t, meas.x, meas.u, library="poly:3,input",
                                  smoothing="weak", settings=settings, seed=seed)
        assert res.preprocessing["state_smoothing"]["regression"]["method"] == "weak-form"
        eq = res.equations[0]
        k = eq.names.index("x1**3")
        assert [eq.names[i] for i in np.flatnonzero(eq.selected)] == ["x1**3"]
        errors.append(abs(eq.mean[k] + 1e5) / 1e5)
    assert np.median(errors) < 0.012


def test_default_route_without_rates_is_the_weak_form():
    ex = systems.example1()
    sim = systems.simulate_example(ex, jax.random.key(0), duration=0.5)
    short = SamplerSettings(num_chains=1, num_draws=50, num_burnin=10)
    args = (ex.system.nominal, sim["t"], sim["x"], sim["u"])
    res = update_input_output(*args, library="poly:2,input", settings=short)
    assert res.preprocessing["smoothing"] == "weak"
    assert res.preprocessing["state_smoothing"]["regression"]["method"] == "weak-form"
    res = update_input_output(*args, library="poly:2,input", settings=short, smoothing="savgol")
    assert res.preprocessing["rates"].startswith("savitzky-golay derivative")
