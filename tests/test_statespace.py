"""Diffusion by the extended Kalman likelihood, given the drift."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dtwin_jax.models import systems
from dtwin_jax.output_only import kramers_moyal, statespace
from dtwin_jax.preprocess.measurement import add_noise


def test_drift_step_matches_the_true_rate_and_a_fine_diffrax_solve():
    ex = systems.example2()
    step = statespace.DriftStep.true(ex)
    x = jnp.array([0.3, 0.2, 1.0, -2.0])
    assert np.allclose(step.rate(x), ex.system.rate(x, jnp.zeros(2)), rtol=1e-12, atol=1e-9)
    t = jnp.array([0.0, 1e-3])
    ref, _ = systems.simulate(ex.system, x, t, jnp.zeros((2, 2)))
    assert np.allclose(step(x), ref[-1], rtol=0, atol=1e-8)


def test_segments_share_their_end_samples():
    x = jnp.arange(2 * 2501 * 1, dtype=float).reshape(2, 2501, 1)
    seg = statespace.segments(x, length=1000)
    assert seg.shape == (6, 834, 1)
    assert float(seg[0, -1, 0]) == float(seg[1, 0, 0])  # pieces share a sample
    assert float(seg[3, 0, 0]) == 2501.0  # record 2 starts a new piece


@pytest.mark.slow  # every default-run output-only update (tests/test_output_only.py) maximizes this likelihood
def test_likelihood_recovers_example2_diffusion_where_preaveraging_fails():
    ex = systems.example2()
    nominal = ex.system.nominal
    sim = systems.simulate_example_sde(ex, jax.random.key(0), num_records=20)
    x = add_noise(jax.random.key(1), sim["x"], 0.05)
    step = statespace.DriftStep.true(ex)
    s2 = kramers_moyal.noise_variance(x)
    pilot, _ = kramers_moyal.preaveraged_diffusion(nominal, x, 1e-3, s2, step.perturbation)
    y = statespace.segments(x)
    gamma, cov, noise, lin = statespace.diffusion_mle(step, y, s2, pilot)
    sigma_err = np.sqrt(np.asarray(gamma) / 0.25) - 1
    sd = np.sqrt(np.diag(np.asarray(cov))) / np.asarray(gamma) / 2
    # 20 records: the pilot's sigma is far off, the likelihood's within 3 standard errors (~4%)
    assert np.max(np.abs(np.sqrt(np.asarray(pilot) / 0.25) - 1)) > 0.3
    assert np.all(np.abs(sigma_err) < 3 * sd) and np.all(sd < 0.06), (sigma_err, sd)
    # EM fixed point: the targets' mean is the likelihood maximum.
    Y, X = statespace.diffusion_targets(lin, y, noise, gamma, (2, 3))
    assert np.allclose(np.mean(np.asarray(Y), axis=(0, 1)), gamma, rtol=5e-3)
    assert X.shape == (y.shape[0], y.shape[1] - 1, 4)


def test_linearization_in_blocks_equals_every_sample_at_once():
    """:func:`statespace.linearize` runs its samples in padded blocks: the same numbers as one
    vmap over every sample (3 records x 400 steps: one whole block and a padded one)."""
    ex = systems.example2()
    step = statespace.DriftStep.true(ex)
    points = 0.2 * jax.random.normal(jax.random.key(0), (3, 401, 4))
    lin = statespace.linearize(step, points)
    x = points[:, :-1].reshape(-1, 4)
    vel = step.nominal.velocity_index
    value = jax.vmap(step)(x)
    jac = jax.vmap(jax.jacfwd(step))(x)
    local = jax.vmap(lambda xk: statespace.local_gramians(jax.jacfwd(step.rate)(xk), vel, step.dt))(x)
    assert lin.jac.shape == (3, 400, 4, 4) and lin.unit_cov.shape == (3, 400, 2, 4, 4)
    for got, want in ((lin.value, value), (lin.jac, jac), (lin.unit_cov, local)):
        np.testing.assert_allclose(np.asarray(got).reshape(want.shape), np.asarray(want), rtol=1e-12, atol=1e-300)
