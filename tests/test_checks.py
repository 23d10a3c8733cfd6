"""Posterior-predictive residual checks: white residuals pass; a missing sign(v) term, a
missing x1**3 term and an autocorrelated residual are each named; negligible structure in a
long record is not flagged."""

import numpy as np

from dtwin_jax.checks import residual_checks

NAMES = ("x1", "x2")
VEL = (1,)


def _states(seed=0, R=4, N=2000, dt=1e-3):
    """Displacement and velocity ``(R, N, 2)``: sums of three sinusoids per record."""
    rng = np.random.default_rng(seed)
    t = np.arange(N) * dt
    w = rng.uniform(10, 60, size=(R, 3, 1))
    a = rng.uniform(0.5, 1.0, size=(R, 3, 1))
    ph = rng.uniform(0, 2 * np.pi, size=(R, 3, 1))
    q = np.sum(a * np.sin(w * t + ph), axis=1)
    v = np.sum(a * w * np.cos(w * t + ph), axis=1)
    return np.stack([q, v], axis=-1)


def _noise(seed, shape):
    return np.random.default_rng(seed).normal(size=shape)


def test_white_residual_independent_of_states_is_ok():
    x = _states()
    out = residual_checks(_noise(1, x.shape[:2]), x, VEL, NAMES)
    assert out["ok"] and out["warnings"] == []
    assert out["whiteness"]["p_value"] > out["threshold"]
    assert 0.9 < out["variance_inflation"] < 1.2
    assert set(out["state"]) == {"x1", "x2"} and set(out["velocity_sign"]) == {"x2"}


def test_missing_sign_of_velocity_is_named():
    x = _states()
    e = _noise(2, x.shape[:2]) + 0.4 * np.sign(x[..., 1])
    out = residual_checks(e, x, VEL, NAMES)
    assert not out["ok"]
    assert any(w.startswith("sign of x2:") for w in out["warnings"]), out["warnings"]
    assert out["velocity_sign"]["x2"]["effect"] > 0.1
    assert not out["state"]["x1"]["flag"]  # (the slowly switching sign(x2) also colours it)


def test_missing_cubic_of_displacement_is_named():
    x = _states()
    q = x[..., 0] / x[..., 0].std()
    e = _noise(3, x.shape[:2]) + 0.3 * q**3
    out = residual_checks(e, x, VEL, NAMES)
    assert not out["ok"]
    assert any(w.startswith("state x1:") for w in out["warnings"]), out["warnings"]
    assert not out["velocity_sign"]["x2"]["flag"]


def test_autocorrelated_residual_fails_whiteness_only():
    x = _states()
    w = _noise(4, x.shape[:2])
    e = np.zeros_like(w)
    for t in range(1, w.shape[1]):
        e[:, t] = 0.6 * e[:, t - 1] + w[:, t]
    out = residual_checks(e, x, VEL, NAMES)
    assert [s.split(":")[0] for s in out["warnings"]] == ["whiteness"], out["warnings"]
    assert 0.3 < out["whiteness"]["effect"] < 0.42  # an AR(1) predicts phi^2 = 0.36 of its variance
    assert out["variance_inflation"] > 3  # (1 + phi) / (1 - phi) = 4 for the mean


def test_negligible_structure_in_a_long_record_is_not_flagged():
    x = _states(R=50, N=4000)
    e = _noise(5, x.shape[:2]) + 0.05 * np.sign(x[..., 1])  # 0.25% of the variance
    out = residual_checks(e, x, VEL, NAMES)
    assert out["velocity_sign"]["x2"]["p_value"] < out["threshold"]  # detectable ...
    assert out["ok"]  # ... but below the minimum effect


def test_single_record_shapes():
    x = _states(R=1)[0]
    out = residual_checks(_noise(6, x.shape[0]), x, VEL, NAMES)
    assert out["ok"] and out["samples"] == x.shape[0]
