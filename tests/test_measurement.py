import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.signal

import dtwin_jax  # noqa: F401  (float64)
from dtwin_jax.errors import DataError
from dtwin_jax.models.systems import example1, example2
from dtwin_jax.preprocess.measurement import (
    Measurements,
    add_noise,
    estimate_rates,
    highest_natural_frequency_hz,
    measure,
    savgol_coefficients,
    smooth,
    smoothing_half_width,
)

DT = 1e-3


def _rms(e):
    return float(jnp.sqrt(jnp.mean(e**2)))


def test_noise_std_matches_level():
    t = jnp.arange(20000) * DT
    signal = jnp.stack([jnp.sin(2 * np.pi * 5 * t), 30.0 * jnp.cos(2 * np.pi * 2 * t) + 7.0], 1)
    level = 0.1
    noise = add_noise(jax.random.PRNGKey(0), signal, level) - signal
    ratio = jnp.std(noise, axis=0) / (level * jnp.std(signal, axis=0))
    print(f"noise std / (level * signal std): {np.asarray(ratio)}")
    assert jnp.all(jnp.abs(ratio - 1.0) < 0.1)

    # Records get their own scale.
    records = jnp.stack([signal, 5.0 * signal])
    noise = add_noise(jax.random.PRNGKey(1), records, level) - records
    ratio = jnp.std(noise, axis=1) / (level * jnp.std(records, axis=1))
    assert ratio.shape == (2, 2) and jnp.all(jnp.abs(ratio - 1.0) < 0.1)
    # One sensor per column: the same noise std in every record.
    noise = add_noise(jax.random.PRNGKey(1), records, level, per_record=False) - records
    ratio = jnp.std(noise, axis=1) / (level * jnp.std(records, axis=(0, 1)))
    assert ratio.shape == (2, 2) and jnp.all(jnp.abs(ratio - 1.0) < 0.1)

    assert add_noise(jax.random.PRNGKey(2), signal, 0.0) is signal
    with pytest.raises(DataError, match="noise level"):
        add_noise(jax.random.PRNGKey(2), signal, 1.5)


def test_measure_uses_independent_noise():
    t = jnp.arange(2000) * DT
    x = jnp.stack([jnp.sin(2 * np.pi * 5 * t)] * 2, 1)
    out = measure(jax.random.PRNGKey(0), t, x, xdot=x, u=x[:, :1], level=0.05)
    assert isinstance(out, Measurements)
    assert out.x.shape == x.shape and out.xdot.shape == x.shape and out.u.shape == (2000, 1)
    ex, exdot = out.x - x, out.xdot - x
    corr = float(jnp.corrcoef(ex[:, 0], exdot[:, 0])[0, 1])
    assert abs(corr) < 0.1 and abs(float(jnp.corrcoef(ex[:, 0], ex[:, 1])[0, 1])) < 0.1
    bare = measure(jax.random.PRNGKey(0), t, x, level=0.05)
    assert bare.xdot is None and bare.u is None


@pytest.mark.parametrize("half_width, order, deriv", [(5, 4, 0), (5, 4, 1), (10, 3, 1), (3, 2, 2), (7, 5, 0)])
def test_savgol_coefficients_match_scipy(half_width, order, deriv):
    ours = savgol_coefficients(half_width, order, deriv, dt=0.01)
    ref = scipy.signal.savgol_coeffs(2 * half_width + 1, order, deriv, delta=0.01, use="conv")
    np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-10 * np.abs(ref).max())


@pytest.mark.parametrize("half_width, order, deriv", [(5, 4, 0), (12, 4, 0), (5, 4, 1), (12, 3, 1)])
def test_smooth_matches_scipy_interp_mode(half_width, order, deriv):
    dt = 0.01
    rng = np.random.default_rng(0)
    t = np.arange(300) * dt
    x = np.stack([np.sin(3 * t) + 0.1 * rng.normal(size=t.size), rng.normal(size=t.size)], 1)
    ours = np.asarray(smooth(jnp.asarray(x), half_width, order, deriv, dt=dt))
    ref = scipy.signal.savgol_filter(x, 2 * half_width + 1, order, deriv, delta=dt, axis=0, mode="interp")
    scale = np.abs(ref).max()
    interior = slice(half_width, -half_width)
    np.testing.assert_allclose(ours[interior], ref[interior], rtol=0, atol=1e-10 * scale)
    np.testing.assert_allclose(ours[:half_width], ref[:half_width], rtol=0, atol=1e-10 * scale)
    np.testing.assert_allclose(ours[-half_width:], ref[-half_width:], rtol=0, atol=1e-10 * scale)

    # (R, N, c) is the per-record filter; (N,) the per-column one.
    stacked = smooth(jnp.stack([x, 2 * x]), half_width, order, deriv, dt=dt)
    np.testing.assert_allclose(stacked[1], 2 * ours, rtol=1e-12, atol=1e-12 * scale)
    np.testing.assert_allclose(smooth(x[:, 1], half_width, order, deriv, dt), ours[:, 1])


def test_smooth_is_jittable_and_validates_length():
    x = jnp.ones((30, 2))
    jitted = jax.jit(smooth, static_argnames=("half_width", "order", "deriv"))
    np.testing.assert_allclose(jitted(x, half_width=4, dt=0.5), x, rtol=1e-12)
    with pytest.raises(DataError, match="fewer than the window"):
        smooth(x, 20)
    with pytest.raises(DataError, match="order"):
        smooth(x, 1, order=4)


def test_smoothing_a_noisy_sine():
    t = jnp.arange(1000) * DT
    clean = jnp.sin(2 * np.pi * 5 * t)[:, None]
    noisy = add_noise(jax.random.PRNGKey(0), clean, 0.05)
    half_width = smoothing_half_width(DT, 5.0)
    smoothed = smooth(noisy, half_width)
    reduction = _rms(noisy - clean) / _rms(smoothed - clean)
    print(f"half width {half_width}: RMS error {_rms(noisy - clean):.4f} -> "
          f"{_rms(smoothed - clean):.4f} ({reduction:.2f}x)")
    assert reduction > 3.0


def test_smoothing_half_width_sets_the_cutoff():
    for f_signal in (5.0, 10.0):
        half_width = smoothing_half_width(DT, f_signal, order=4, factor=8.0)
        w, H = scipy.signal.freqz(savgol_coefficients(half_width, 4), worN=20000, fs=1 / DT)
        cutoff = w[np.argmax(np.abs(H) < 1 / np.sqrt(2))]
        print(f"f_signal {f_signal} Hz: half width {half_width}, -3 dB at {cutoff:.1f} Hz")
        assert abs(cutoff / (8.0 * f_signal) - 1.0) < 0.15
    assert smoothing_half_width(DT, 400.0) == 3  # clamped to order // 2 + 1
    assert smoothing_half_width(DT, 1e-4) == 500  # clamped to max_half_width
    with pytest.raises(DataError, match="dt"):
        smoothing_half_width(0.0, 5.0)


def test_highest_natural_frequency():
    assert abs(highest_natural_frequency_hz(example1().system.nominal)
               - np.sqrt(1000.0) / (2 * np.pi)) < 1e-12
    nominal = example2().system.nominal
    omega = np.sqrt(np.linalg.eigvalsh(np.asarray(nominal.K))).max()  # M = I
    assert abs(highest_natural_frequency_hz(nominal) - omega / (2 * np.pi)) < 1e-9


def test_estimate_rates_on_a_clean_sine():
    omega = 2 * np.pi * 5
    t = jnp.arange(1000) * DT
    x = jnp.stack([jnp.sin(omega * t), 3 * jnp.cos(omega * t)], 1)
    exact = jnp.stack([omega * jnp.cos(omega * t), -3 * omega * jnp.sin(omega * t)], 1)
    half_width = 10
    rates = estimate_rates(x, DT, half_width)
    interior = slice(half_width, -half_width)
    rel = jnp.max(jnp.abs(rates - exact)[interior], axis=0) / jnp.max(jnp.abs(exact), axis=0)
    print(f"estimate_rates interior max relative error: {np.asarray(rel)}")
    assert jnp.all(rel < 1e-4)
