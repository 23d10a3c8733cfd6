"""The weak (integral) form of framework 1: states without rates (dtwin_jax.preprocess.weak_form)."""

import jax
import numpy as np
import pytest

from dtwin_jax import SamplerSettings, update_input_output
from dtwin_jax.errors import DataError
from dtwin_jax.models import systems
from dtwin_jax.preprocess.measurement import measure
from dtwin_jax.preprocess.weak_form import (
    bump_functions,
    derivative_terms,
    effective_share,
    weak_input_output_stats,
    weak_windows,
    window_filter,
    window_grams,
    window_quadrature,
)
from dtwin_jax.update.sampling import resolve_library


def test_window_quadrature_integrates_by_parts():
    # int phi g' dt = -int phi' g dt for phi vanishing at the window's ends.
    t = np.arange(1000) * 1e-3
    Phi, dPhi, Phi_u = window_quadrature(t.size, 1e-3, 200, 25, 6)
    g, dg = np.sin(30 * t), 30 * np.cos(30 * t)
    np.testing.assert_allclose(Phi @ dg, -dPhi @ g, atol=1e-6)
    np.testing.assert_allclose(Phi.sum(axis=1), 1.0, rtol=1e-12)  # unit integral
    np.testing.assert_allclose(Phi_u.sum(axis=1), 1.0, rtol=1e-12)  # held weights: exact integral
    assert Phi.shape == (33, 1000)


@pytest.mark.parametrize("num_samples, width, stride", [(1000, 200, 25), (2003, 97, 12), (300, 17, 2), (64, 64, 8)])
def test_window_grams_and_filters_equal_the_dense_products(num_samples, width, stride):
    # From the kernels alone, whatever the width's remainder by the stride: the matrices'
    # products and their action on a signal.
    Phi, dPhi, _, ddPhi = window_quadrature(num_samples, 1e-3, width, stride, 6, held=False, second=True)
    mats = (Phi, dPhi, ddPhi)
    kernels = bump_functions(width, 1e-3, 6)[:3]
    W = mats[0].shape[0]
    dense = np.array([[a @ b.T for b in mats] for a in mats])
    banded = window_grams(kernels, W, stride)
    assert banded.shape == dense.shape == (3, 3, W, W)
    np.testing.assert_allclose(banded, dense, rtol=0, atol=1e-14 * np.max(np.abs(dense)))
    x = np.random.default_rng(0).normal(size=(2, num_samples, 3))
    for A, kernel in zip(mats, kernels):
        want = np.einsum("wn,rnc->rwc", A, x)
        np.testing.assert_allclose(window_filter(kernel, stride, x), want, rtol=0,
                                   atol=1e-13 * np.max(np.abs(want)))


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
    short = SamplerSettings(num_chains=2, num_draws=50, num_burnin=10)
    args = (ex.system.nominal, sim["t"], sim["x"], sim["u"])
    res = update_input_output(*args, library="poly:2,input", settings=short)
    assert res.preprocessing["smoothing"] == "weak"
    assert res.preprocessing["state_smoothing"]["regression"]["method"] == "weak-form"
    res = update_input_output(*args, library="poly:2,input", settings=short, smoothing="savgol")
    assert res.preprocessing["rates"].startswith("savitzky-golay derivative")


def test_terms_that_are_time_derivatives_are_found_and_integrated():
    lib = resolve_library("poly:3,sign,xabs", systems.example1().system.nominal, 1)
    t = np.linspace(0, 1, 2001)
    q, v = np.sin(7 * t), 7 * np.cos(7 * t)
    x = np.stack([q, v], axis=-1)[None]
    found = derivative_terms(lib, x, np.zeros((1, t.size, 1)), [(0, 1)])
    names = sorted(lib.names[k] for k in found)
    assert names == ["x1**2*x2", "x1*x2", "x2", "x2*Abs(x1)"]
    G = found[lib.names.index("x1**2*x2")][0]  # q^3 / 3, up to a constant
    np.testing.assert_allclose(G - G[0], (q**3 - q[0] ** 3) / 3, atol=1e-6)


def test_displacement_alone_duffing_at_5_percent_noise():
    # benchmarks/zoo.py --layout displacement covers random members; this is the README's Duffing.
    ex = systems.example1()
    settings = SamplerSettings(num_chains=2, num_draws=1000, num_burnin=500)
    sim = systems.simulate_example(ex, jax.random.key(3), duration=2.0)
    meas = measure(jax.random.key(4), sim["t"], sim["x"], None, sim["u"], level=0.05)
    res = update_input_output(ex.system.nominal, meas.t, meas.x[:, :1], meas.u, x_names=["x1"],
                              library="poly:3,sign,xabs,input", settings=settings, seed=0)
    info = res.preprocessing["state_smoothing"]["regression"]
    assert res.preprocessing["smoothing"] == "weak" and res.preprocessing["layout"] == "displacement"
    assert info["velocities_estimated"] == ["x2"] and "x1**2*x2" in info["integrated_by_parts"]
    eq = res.equations[0]
    k = eq.names.index("x1**3")
    truth = ex.true_coefficients(eq.names)[0][k]
    print("selected", [eq.names[j] for j in np.flatnonzero(eq.selected)], "error", eq.mean[k] / truth - 1,
          "share", info["equation_error_share"], "model error", res.preprocessing["model_error_sd"])
    assert [eq.names[j] for j in np.flatnonzero(eq.selected)] == ["x1**3"]
    assert abs(eq.mean[k] / truth - 1) < 0.01
    lo, hi = eq.hdi_95[k]
    assert lo <= truth <= hi


def test_input_noise_is_taken_up_by_the_equation_error():
    # Noise on the measured input acts as a white force: REML gives the equation error a
    # growing share of the rows' covariance. Measured (2% state noise): 0.26, 0.57, 0.998 at
    # 0, 5% and 20% input noise.
    ex = systems.example1()
    nominal = ex.system.nominal
    lib = resolve_library("poly:3,input", nominal, nominal.n)
    sim = systems.simulate_example(ex, jax.random.key(0), duration=2.0)
    x = np.asarray(measure(jax.random.key(1), sim["t"], sim["x"], level=0.02).x)[None]
    shares = []
    for level in (0.0, 0.05, 0.2):
        u = np.asarray(measure(jax.random.key(2), sim["t"], sim["u"], level=level).x)[None] if level else \
            np.asarray(sim["u"])[None]
        shares.append(weak_input_output_stats(nominal, lib, sim["t"], x, u)[1]["equation_error_share"][0])
    assert shares[0] < 0.35 and shares[0] < shares[1] < shares[2] and shares[2] > 0.95, shares


@pytest.mark.optimized
def test_long_records_are_cut_into_segments():
    ex = systems.example1()
    nominal = ex.system.nominal
    lib = resolve_library("poly:3,input", nominal, nominal.n)
    sim = systems.simulate_example(ex, jax.random.key(0), duration=30.0)
    x, u = np.asarray(sim["x"])[None], np.asarray(sim["u"])[None]
    stats, info = weak_input_output_stats(nominal, lib, sim["t"], x, u)
    assert info["segments"] > 1 and info["samples_used"] >= 0.9 * info["samples"]
    coef = np.linalg.solve(np.asarray(stats.gram[0]), np.asarray(stats.xty[0]))
    k = lib.names.index("x1**3")
    assert abs(coef[k] / ex.true_coefficients(lib.names)[0][k] - 1) < 1e-3


def test_effective_share_is_one_where_the_fit_leaves_too_few_dimensions_and_finds_correlated_errors():
    """A short record's 34 windows and a 46-term library: the least-squares residual is
    rounding, whose ESS once gave 0.24 or 1.0 by the BLAS's thread count (and dropped a true
    input term); the share is then 1. With rows to spare, an AR(1) error at 0.9 keeps about
    (1 - 0.9) / (1 + 0.9) of them."""
    rng = np.random.default_rng(0)
    W = 34
    assert effective_share(rng.normal(size=(1, W, 46)), rng.normal(size=(1, W)), np.eye(W)) == 1.0
    W, phi = 4000, 0.9
    e = np.zeros(W)
    for i in range(1, W):
        e[i] = phi * e[i - 1] + rng.normal()
    L = rng.normal(size=(1, W, 5))
    share = effective_share(L, L[..., 0] + e[None], np.eye(W))
    assert 0.7 * (1 - phi) / (1 + phi) < share < 1.3 * (1 - phi) / (1 + phi), share
