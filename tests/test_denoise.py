"""Denoising the states removes the errors-in-variables bias of the library."""

import jax
import numpy as np

import dtwin_jax  # noqa: F401
from dtwin_jax.data import check_records
from dtwin_jax.input_output.targets import input_output_targets
from dtwin_jax.models import systems
from dtwin_jax.preprocess.denoise import kinematic_smoother, noise_std
from dtwin_jax.preprocess.measurement import measure
from dtwin_jax.update import denoise_states


def _ls_cubic(seed, smoothing):
    ex = systems.example1()
    nominal = ex.system.nominal
    sim = systems.simulate_example(ex, jax.random.key(seed))
    meas = measure(jax.random.key(100 + seed), sim["t"], sim["x"], sim["xdot"], sim["u"], level=0.05)
    rec = check_records(meas.t, meas.x, meas.u, meas.xdot, nominal)
    xs, _ = denoise_states(rec, nominal, smoothing)
    y = np.asarray(input_output_targets(nominal, xs[0], meas.u, meas.xdot))[:, 0]
    col = xs[0][:, :1] ** 3
    return float(np.linalg.lstsq(col, y, rcond=None)[0][0]) / -1e5 - 1.0


def test_denoising_removes_the_bias_of_plain_least_squares():
    raw = np.array([_ls_cubic(s, None) for s in range(6)])
    sg = np.array([_ls_cubic(s, "savgol") for s in range(6)])
    rts = np.array([_ls_cubic(s, "auto") for s in range(6)])
    print("x1**3 relative error, raw", raw.mean(), "savgol", sg.mean(), "kinematic", rts.mean(), "spread", rts.std())
    assert raw.mean() < -0.012  # about 2% low: attenuation by noise in the columns
    assert abs(sg.mean()) < 0.006
    assert abs(rts.mean()) < 0.003 and rts.std() < 0.005


def test_kinematic_smoother_beats_savgol_and_estimates_noise():
    ex = systems.example2()
    nominal = ex.system.nominal
    sim = systems.simulate_example(ex, jax.random.key(0))
    meas = measure(jax.random.key(1), sim["t"], sim["x"], sim["xdot"], sim["u"], level=0.05)
    truth = np.asarray(sim["x"])
    est_noise = np.asarray(noise_std(meas.x, 10))
    np.testing.assert_allclose(est_noise, 0.05 * truth.std(axis=0), rtol=0.15)
    rec = check_records(meas.t, meas.x, meas.u, meas.xdot, nominal)
    sg, _ = denoise_states(rec, nominal, "savgol")
    ks = np.asarray(kinematic_smoother(nominal, 1e-3, meas.x, meas.xdot, meas.u))
    err_raw = np.sqrt(np.mean((np.asarray(meas.x) - truth) ** 2, axis=0))
    err_sg = np.sqrt(np.mean((sg[0] - truth) ** 2, axis=0))
    err_ks = np.sqrt(np.mean((ks - truth) ** 2, axis=0))
    print("rms state error raw", err_raw, "savgol", err_sg, "kinematic", err_ks)
    assert np.all(err_ks < 0.5 * err_sg) and np.all(err_sg < 0.6 * err_raw)


def test_kinematic_smoother_noise_by_likelihood_on_friction():
    """Coulomb friction and white-noise force: the velocity is rough at the sample scale and
    the acceleration jumps, where a filter-residual noise estimate (4.7x too high on the
    velocity) left the smoothed velocity 0.23x the sensor noise off on a similar case; the
    likelihood fit leaves 0.17x here (measured)."""
    import jax.numpy as jnp

    from dtwin_jax.models.systems import Example, LinearSecondOrder, PerturbedSystem

    def friction_and_drag(x, u, p):
        v = x[1]
        return jnp.stack([jnp.zeros_like(v), -(3.0 * jnp.sign(v) + 5.0 * v * jnp.abs(v)) / 2.0])

    nominal = LinearSecondOrder.create([[2.0]], [[3.0]], [[800.0]], [[2.0]])
    ex = Example("friction", PerturbedSystem(nominal, friction_and_drag, {}), jnp.zeros(2), 1e-3, 1.0,
                 1e3**0.5, {}, "poly:1", "")
    sim = systems.simulate_example(ex, jax.random.key(0))
    meas = measure(jax.random.key(1), sim["t"], sim["x"], sim["xdot"], sim["u"], level=0.02)
    xs = np.asarray(kinematic_smoother(nominal, 1e-3, meas.x, meas.xdot, meas.u))
    raw = np.sqrt(np.mean((np.asarray(meas.x) - np.asarray(sim["x"])) ** 2, axis=0))
    err = np.sqrt(np.mean((xs - np.asarray(sim["x"])) ** 2, axis=0))
    print("raw", raw, "smoothed", err, "ratio", err / raw)
    assert np.all(err / raw < 0.19), err / raw


def test_a_window_whose_step_differs_in_the_last_bits_reuses_the_compiled_smoother(lowered_programs):
    # A monitor's windows cut at other offsets: (t[-1] - t[0]) / (N - 1) takes several values a
    # few ulps apart (6 over 200 one-second windows at 1 kHz); each once compiled the
    # smoother again (2.9 s against 0.17 s for the whole window).
    ex = systems.example1()
    sim = systems.simulate_example(ex, jax.random.key(0), duration=1.0)
    meas = measure(jax.random.key(1), sim["t"], sim["x"], sim["xdot"], sim["u"], level=0.05)
    first = kinematic_smoother(ex.system.nominal, 1e-3, meas.x, meas.xdot, meas.u, half_width=20)
    lowered_programs.clear()
    again = kinematic_smoother(ex.system.nominal, np.nextafter(1e-3, 1.0), meas.x, meas.xdot, meas.u, half_width=20)
    assert not [p for p in lowered_programs if "kinematic" in p[1]], lowered_programs
    np.testing.assert_allclose(np.asarray(again), np.asarray(first), rtol=1e-9, atol=1e-12)


def test_structures_whose_widths_differ_share_the_compiled_smoother(lowered_programs):
    """Another structure's nominal model gives another Savitzky-Golay width for the noise
    fit's first guesses (here 13 and 20 samples); the smoother's program is keyed by the
    record's shape, so monitoring structures one by one compiles it once, not once each."""
    ex = systems.example1()
    sim = systems.simulate_example(ex, jax.random.key(0), duration=1.0)
    meas = measure(jax.random.key(1), sim["t"], sim["x"], sim["xdot"], sim["u"], level=0.05)
    first = kinematic_smoother(ex.system.nominal, 1e-3, meas.x, meas.xdot, meas.u, half_width=20)
    lowered_programs.clear()
    other = kinematic_smoother(ex.system.nominal, 1e-3, meas.x, meas.xdot, meas.u, half_width=13)
    assert not [p for p in lowered_programs if p[1] == "jit(_kinematic_smoother)"], lowered_programs
    # The width only sets the first guesses: the maximum-likelihood fit ends at the same noise.
    np.testing.assert_allclose(np.asarray(other), np.asarray(first), rtol=1e-6, atol=1e-9)
