"""Output-only from accelerometers alone (formats.md: ``x`` left out, no ``u``): the ambient
vibration of a structure in service. The drift from the accelerometer samples as Kramers-Moyal
increments at the anchored states; the constant diffusion from the accelerations' white floor,
split from the sensors' noise."""

import dataclasses

import jax
import numpy as np
import pytest

from dtwin_jax import SamplerSettings, update_output_only
from dtwin_jax.errors import DataError
from dtwin_jax.io.store import load_twin, save_twin
from dtwin_jax.library import parse_library
from dtwin_jax.models import systems, zoo
from dtwin_jax.models.prediction import posterior_twins
from dtwin_jax.output_only.accelerometers import increment_stats


def _ambient(index: int, records: int, level: float = 0.03):
    """Zoo member ``index`` in ambient vibration: ``records`` x 2 s, the accelerometers'
    interval averages with ``level`` white noise; the true states for comparison."""
    member = zoo.draw_member(index)
    ex = member.example.for_output_only()
    sim = systems.simulate_example_sde(ex, jax.random.fold_in(jax.random.key(member.seed), 1), num_records=records,
                                       duration=2.0, accelerations=True)
    a = np.asarray(sim["xdot"])
    a = a + level * np.std(a, axis=(0, 1)) * np.random.default_rng(member.seed).standard_normal(a.shape)
    return member, ex, np.asarray(sim["t"]), a, np.asarray(sim["x"])


def test_the_increments_regressors_see_no_force_of_their_own_interval():
    # zoo-0002 (quadratic stiffness) with its true states: regressors at the samples themselves
    # see half of each interval's white force, which least squares reads as a damping; at the
    # drift's prediction from the sample before they see none (measured: x2 +6.26 /s against
    # -0.10 /s, the truth 0; x1**2 -3601 against -3944, 8.7% off).
    member, ex, t, a, x = _ambient(2, 10)
    nominal = ex.system.nominal
    lib = parse_library("terms:x1**2;x2", nominal.m, 0)
    fit = np.linalg.solve(*(np.asarray(v)[0] for v in increment_stats(nominal, lib, ex.dt, a, x)[:2]))
    assert abs(fit[1]) < 1.0 and abs(fit[0] / ex.true_terms["x2"]["x1**2"] - 1) < 0.1, fit
    L = np.asarray(lib(x.reshape(-1, 2)))
    y = (a - np.asarray(jax.vmap(nominal.rate_batch)(x, np.zeros(x.shape[:2] + (1,))))[..., 1:]).reshape(-1)
    naive = np.linalg.lstsq(L, y, rcond=None)[0]
    assert naive[1] > 4.0, naive


@pytest.fixture(scope="module")
def hardening(tmp_path_factory):
    """zoo-0000 (cubic hardening) from 10 records x 2 s of accelerations at 3% noise."""
    member, ex, t, a, x = _ambient(0, 10)
    nominal = ex.system.nominal
    result = update_output_only(nominal, t, None, xdot=a, xdot_names=["x2"], library=ex.library_output_only,
                                settings=SamplerSettings(num_chains=2, num_draws=1000, num_burnin=500), seed=member.seed)
    return ex, result


def test_ambient_vibration_finds_the_cubic_and_the_diffusion(hardening):
    # Measured: x1**3 alone, 1.0% off inside its 95% HDI; Gamma 0.1060 +- 0.0011 (truth 0.1056).
    ex, result = hardening
    drift, diffusion = result.equations
    assert drift.kind == "drift" and diffusion.kind == "diffusion" and diffusion.names == ("1",)
    assert [drift.names[k] for k in np.flatnonzero(drift.selected)] == ["x1**3"]
    k = drift.names.index("x1**3")
    truth = ex.true_terms["x2"]["x1**3"]
    draws = drift.theta[..., k][drift.gamma[..., k]]
    assert abs(draws.mean() / truth - 1) < 0.03
    lo, hi = np.quantile(draws, [0.025, 0.975])
    assert lo < truth < hi
    gamma = diffusion.theta[..., 0].ravel()
    g_true = ex.true_diffusion()["x2"]
    assert abs(gamma.mean() / g_true - 1) < 0.05
    lo, hi = np.quantile(gamma, [0.025, 0.975])
    assert lo < g_true < hi and hi - lo < 0.1 * g_true
    pre = result.preprocessing
    assert pre["layout"] == "accelerometers" and pre["diffusion_library"] == "terms:1"
    # The white floor is the force's: the sensors' 3% is 0.09% of its variance (estimated 0.3%).
    assert pre["acceleration_noise_std"][0] ** 2 < 0.01 * g_true / ex.dt


def test_the_twin_from_accelerometers_saves_loads_and_draws(hardening, tmp_path):
    ex, result = hardening
    folder = save_twin(result, tmp_path / "twin")
    loaded = load_twin(folder)
    assert [e.names for e in loaded.equations] == [e.names for e in result.equations]
    np.testing.assert_array_equal(loaded.equations[1].theta, result.equations[1].theta)
    twins = posterior_twins(loaded, num_draws=8)
    assert twins.stochastic and twins.diffusion_library.names == ("1",)
    # The window's score spread over its states' error (the monitor's test) travels too: a
    # covariance over the 16 draws, positive on the diagonal.
    spread = result.statistics["drift_spread"]
    K = len(result.equations[0].names)
    assert np.shape(spread.gram) == (1, K, K) and float(spread.n[0]) == 16
    assert np.all(np.diag(spread.gram[0]) > 0) and np.allclose(spread.gram[0], spread.gram[0].T)
    np.testing.assert_array_equal(loaded.statistics["drift_spread"].gram, spread.gram)


@pytest.mark.parametrize("case", ["re-update", "diffusion library", "one accelerometer of two"])
def test_what_accelerometers_alone_cannot_give_is_refused_in_one_line(hardening, case):
    ex, result = hardening
    t = np.arange(200) * 1e-3
    rng = np.random.default_rng(0)
    nominal = ex.system.nominal
    if case == "re-update":
        states_twin = dataclasses.replace(result, preprocessing={**result.preprocessing, "diffusion_library": "poly:2"})
        call = lambda: update_output_only(nominal, t, None, xdot=rng.normal(size=(200, 1)), xdot_names=["x2"],
                                          previous=states_twin)
        message = "a re-update from accelerometers alone needs a twin updated from accelerometers alone"
    elif case == "diffusion library":
        call = lambda: update_output_only(nominal, t, None, xdot=rng.normal(size=(200, 1)), xdot_names=["x2"],
                                          diffusion_library="poly:2")
        message = "constant diffusion only"
    else:
        chain = systems.LinearSecondOrder.create(np.eye(2), [[8.0, -4.0], [-4.0, 4.0]],
                                                 [[6000.0, -2000.0], [-2000.0, 2000.0]], np.eye(2))
        call = lambda: update_output_only(chain, t, None, xdot=rng.normal(size=(200, 1)), xdot_names=["x3"])
        message = "missing 'xdot' of x4"
    with pytest.raises(DataError, match=message) as err:
        call()
    assert "\n" not in str(err.value)
