"""Denoising the measured states before they enter the library.

Noise in the states is an errors-in-variables error: it sits inside the library columns and
inside the nominal rates removed from the target, and biases the coefficients (plain least
squares on example 1's `x1**3` with a few percent noise comes out low). Two estimators:

* `kinematic_smoother` (used when rates are measured): a Rauch-Tung-Striebel smoother on
  the exact kinematic chains `dq/dt = v`, `dv/dt = a` (and `de/dt = edot` for extra
  states) driven by the measured rates. It fuses displacement, velocity and acceleration
  sensors: at low frequency it trusts the states, at high frequency the integrated rates.
  No model of the (unknown) perturbed dynamics enters, only kinematics.
* `savgol_states` (when rates are not measured): a Savitzky-Golay filter whose cutoff is
  matched to the sampling rate and to the nominal model's highest natural frequency.

Sensor noise levels are estimated from the data: white noise is what a Savitzky-Golay
projection leaves behind, `var(s - SG(s)) = sigma^2 (1 - h_0)` with `h_0` the filter's centre
tap, because the signal lives well below the filter's cutoff.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp

from dtwin_jax._compile import aot
from dtwin_jax.linalg import mass_solve
from dtwin_jax.models.systems import LinearSecondOrder
from dtwin_jax.preprocess.kalman import (
    kalman_filter,
    newton_log_variances,
    rts_smoother,
)
from dtwin_jax.preprocess.measurement import (
    highest_natural_frequency_hz,
    savgol_coefficients,
    smooth,
    smoothing_half_width,
)

__all__ = ["savgol_design_ok", "auto_half_width", "noise_std", "savgol_states", "kinematic_smoother", "input_noise_variance"]

_ORDER = 4


def savgol_design_ok(nominal: LinearSecondOrder, dt: float) -> bool:
    """Whether the Savitzky-Golay filters can put their cutoff at 8x the highest nominal natural frequency.

    Not when that is above the Nyquist frequency (a few samples per period), where the
    shortest window's derivative gain already falls well below 1 and biases the stiffness.

    **Arguments:**

    - `nominal`: the nominal model (its highest natural frequency).
    - `dt`: sample step, s.

    **Returns:** True when 8 times the highest natural frequency is below the Nyquist
    frequency `0.5 / dt`.
    """
    return 8.0 * highest_natural_frequency_hz(nominal) < 0.5 / dt


def auto_half_width(nominal: LinearSecondOrder, dt: float, num_samples: int) -> int:
    """Savitzky-Golay half width (order 4) matched to `dt` and the nominal band.

    **Arguments:**

    - `nominal`: the nominal model (its highest natural frequency sets the cutoff,
      `measurement.smoothing_half_width`).
    - `dt`: sample step, s.
    - `num_samples`: samples per record `N`.

    **Returns:** the half width, samples, at most `(N - 1) // 2`; without stiffness, a window
    of about 1% of the record (at least 3).
    """
    f_hz = highest_natural_frequency_hz(nominal)
    if f_hz <= 0:  # no stiffness: a window of 1% of the record
        half_width = max(3, num_samples // 200)
    else:
        half_width = smoothing_half_width(dt, f_hz, order=_ORDER)
    return int(min(half_width, (num_samples - 1) // 2))


@functools.partial(jax.jit, static_argnums=1)  # one program (eagerly, each operation was one)
def noise_std(signal, half_width: int) -> jax.Array:
    """Std of white noise on each column of a signal, from the Savitzky-Golay residual.

    The residual's variance is `sigma^2 (1 - h_0)` with `h_0` the filter's centre tap (order
    4); the edges, fitted one-sided, are left out. Jitted (`half_width` static).

    **Arguments:**

    - `signal`: `(..., N, c)` the signal, samples along the second-to-last axis.
    - `half_width`: the filter's half width, samples (static).

    **Returns:** the noise std `(..., c)`, in the signal's units.
    """
    h0 = float(savgol_coefficients(half_width, _ORDER)[half_width])
    resid = signal - smooth(signal, half_width, _ORDER)
    core = resid[..., half_width:-half_width, :]  # the edges use one-sided fits
    return jnp.sqrt(jnp.mean(core**2, axis=-2) / (1.0 - h0))


def savgol_states(x, half_width: int):
    """Savitzky-Golay smoothing (order 4) of states.

    **Arguments:**

    - `x`: `(..., N, m)` states.
    - `half_width`: the filter's half width, samples.

    **Returns:** the smoothed states, `(..., N, m)`.
    """
    return smooth(x, half_width, _ORDER)


def _filter(z, w, F, G, Q, r_diag):
    """Kalman filter (`kalman.kalman_filter`) of the kinematic chain
    `s_{k+1} = F s_k + G w_k + noise(Q)`, `z_k = s_k + noise(r_diag)`: `z (N, p)`
    measured states, `w (N-1, p)` known inputs, `r_diag (p,)` measurement variances.

    The first sample under a prior of the measurement itself with `1e6` times its noise,
    updated by it in closed form (`s_0 = z_0`, `P_0 = R 1e6 / (1e6 + 1)`), and left out of
    the likelihood, which is that of `z_1..z_{N-1}` given `z_0`.
    """
    P0 = jnp.diag(r_diag * (1e6 / (1e6 + 1.0)))
    return kalman_filter(F, w @ G.T, Q, None, None, r_diag, z, z[0], P0, update_first=False)


def _rts(z, w, F, G, Q, r_diag):
    """RTS smoother of the model of `_filter`: smoothed states `(N, p)`."""
    return rts_smoother(_filter(z, w, F, G, Q, r_diag), F)[0]


def _fit_noise(z, w, F, G, Q_unit, r0, q0, iterations: int = 10):
    """Maximum-likelihood measurement variances `(p,)` and process-noise scale `()` of
    the model of `_filter` with `Q = q Q_unit`, from first guesses `r0`, `q0`.

    Newton steps in the log-variances (`kalman.newton_log_variances`); fixed
    iterations, so it jits and vmaps. Floors at 1e-10 of the guesses keep a noise-free
    signal finite.
    """
    floor = jnp.log(jnp.concatenate([r0, q0[None]]) * 1e-10 + 1e-300)

    def loglik(params):
        return _filter(z, w, F, G, jnp.exp(params[-1]) * Q_unit, jnp.exp(params[:-1])).loglik

    params = jnp.log(jnp.maximum(jnp.concatenate([r0, q0[None]]), 1e-300))
    params = newton_log_variances(loglik, params, floor, iterations)
    return jnp.exp(params[:-1]), jnp.exp(params[-1])


def kinematic_smoother(
    nominal: LinearSecondOrder, dt: float, x, xdot, u=None, half_width: int | None = None
):
    """Fuse measured states with measured rates by RTS smoothing.

    Each degree of freedom is the chain `(q, v)` driven by the measured acceleration; each
    extra state `e` is driven by its measured rate. Within a sample interval the input is
    held (piecewise constant), so the acceleration jumps by `M^-1 B du` at sample times; the
    known jump is taken out before the trapezoidal integration. The noise variances of the
    states and rates are fitted by maximum likelihood of each chain (Newton steps from the
    first guesses of `noise_std`): the filter-residual guesses assume a band-limited signal,
    which a velocity under white-noise force (rough at the sample scale) or an acceleration
    that jumps (friction) is not; on such data they were several times too large.

    **Arguments:**

    - `nominal`: the nominal model (`d` degrees of freedom, extra states, `M`, `B`).
    - `dt`: sample step, s.
    - `x`: `(N, m)` measured states.
    - `xdot`: `(N, m)` measured rates.
    - `u`: `(N, n)` measured inputs, held over each step, or None (no input jump taken out).
    - `half_width`: half width, samples, of the noise levels' first guesses, or None (default:
      `auto_half_width`).

    **Returns:** the smoothed states, `(N, m)`.
    """
    x = jnp.asarray(x)
    xdot = jnp.asarray(xdot)
    if half_width is None:
        half_width = auto_half_width(nominal, dt, x.shape[0])
    u = None if u is None else jnp.asarray(u)
    # The noise fit's first guesses in a program of their own: the smoother's program is then
    # keyed by the record's shape, not by the width (each structure's nominal model gives its
    # own width, and compiled the whole smoother again, 2-3 s, for every structure monitored).
    sig_x, sig_r = _first_guesses(nominal, x, xdot, u, int(half_width))
    # dt traced, not static: windows cut at other offsets have dt's that differ in the last
    # bits, and each new value compiled the program again (2.9 s) in a monitor's life.
    return _kinematic_smoother(nominal, jnp.asarray(dt, dtype=jnp.float64), x, xdot, u, sig_x, sig_r)


def _smooth_part(nominal: LinearSecondOrder, xdot, u):
    """The measured rates `xdot (N, m)` split into the jump of the held input's force,
    `(N, m)` (zero off the velocity rows), and the smooth rest `xdot - jump`."""
    d = nominal.d
    jump = jnp.zeros_like(xdot)
    if u is not None:
        force = mass_solve(nominal.M, nominal.B @ jnp.asarray(u).T).T  # (N, d)
        jump = jump.at[:, d : 2 * d].set(force)
    return jump, xdot - jump


@eqx.filter_jit  # half_width (a Python int) static
def _first_guesses(nominal: LinearSecondOrder, x, xdot, u, half_width: int):
    """Std of the states' and the smooth rates' noise `((m,), (m,))` (`noise_std`)."""
    return noise_std(x, half_width), noise_std(_smooth_part(nominal, xdot, u)[1], half_width)


# A new process (the command line) reuses the traced program (dtwin_jax._compile.aot).
@aot.exported("kinematic_smoother")
@eqx.filter_jit
def _kinematic_smoother(nominal: LinearSecondOrder, dt, x, xdot, u, sig_x, sig_r):
    # Compiled as a whole: run eagerly, the noise fit's loop compiled anew on every call
    # (6 s per 1000-sample record).
    N, m = x.shape
    d, E = nominal.d, nominal.extra_states
    jump, smooth_part = _smooth_part(nominal, xdot, u)
    # a(t) on [t_k, t_k+1) = held part + smooth part s(t); s is integrated by trapezoid.
    held = jump[:-1]
    s0, s1 = smooth_part[:-1], smooth_part[1:]
    mean_rate = held + 0.5 * (s0 + s1)  # average rate over the step
    pos_rate = held / 2 + (2 * s0 + s1) / 6  # double integral / dt^2
    out = x
    if d:
        F = jnp.array([[1.0, dt], [0.0, 1.0]])
        G = jnp.array([[dt**2, 0.0], [0.0, dt]])
        q_idx = jnp.arange(d)
        v_idx = d + q_idx

        Q_unit = jnp.array([[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt**2]])

        def chain(j_q, j_v):
            z = jnp.stack([x[:, j_q], x[:, j_v]], axis=1)
            w = jnp.stack([pos_rate[:, j_v], mean_rate[:, j_v]], axis=1)
            sa = sig_r[j_v] ** 2 / 2  # trapezoid averages two noisy samples
            r = jnp.maximum(jnp.stack([sig_x[j_q], sig_x[j_v]]) ** 2, 1e-300)
            r, sa = _fit_noise(z, w, F, G, Q_unit, r, sa)
            return _rts(z, w, F, G, sa * Q_unit, r)

        sm = jax.vmap(chain)(q_idx, v_idx)  # (d, N, 2)
        out = out.at[:, :d].set(sm[:, :, 0].T).at[:, d : 2 * d].set(sm[:, :, 1].T)
    if E:
        F1 = jnp.eye(1)
        G1 = jnp.eye(1) * dt

        def chain1(j):
            z = x[:, j][:, None]
            w = mean_rate[:, j][:, None]
            r = jnp.maximum(sig_x[j] ** 2, 1e-300)[None]
            r, sa = _fit_noise(z, w, F1, G1, jnp.eye(1) * dt**2, r, sig_r[j] ** 2 / 2)
            return _rts(z, w, F1, G1, sa * jnp.eye(1) * dt**2, r)[:, 0]

        e_idx = jnp.arange(2 * d, 2 * d + E)
        out = out.at[:, 2 * d :].set(jax.vmap(chain1)(e_idx).T)
    return out


def input_noise_variance(nominal: LinearSecondOrder, xs, u, rates, half_width: int) -> jax.Array:
    """Variance of white noise on the measured inputs, from the measured rates.

    A white input cannot be told from white noise on its own, but the accelerations see only
    the true input: the high-frequency parts of `r = xdot - f(x, 0)` and `u` covary through
    `M^-1 B` times the true input's variance, while `u` alone carries true + noise. Jittable.

    **Arguments:**

    - `nominal`: the nominal model.
    - `xs`: `(R, N, m)` denoised states.
    - `u`: `(R, N, n)` measured inputs.
    - `rates`: `(R, N, m)` measured rates.
    - `half_width`: half width of the high-pass Savitzky-Golay filter, samples (static).

    **Returns:** the noise variance of each input, `(n,)`, in input units squared (at least 0).
    """
    xs, u, rates = (jnp.asarray(a) for a in (xs, u, rates))
    d = nominal.d
    vel = jnp.asarray(nominal.velocity_index)
    gain = mass_solve(nominal.M, nominal.B)  # (d, n)
    zero = jnp.zeros(u.shape[-1], u.dtype)
    f0 = jax.vmap(lambda x: nominal.rate_batch(x, jnp.broadcast_to(zero, (x.shape[0], zero.size))))(xs)
    r = rates[..., vel] - f0[..., vel]
    core = slice(half_width, -half_width)
    hp_r = (r - smooth(r, half_width, _ORDER))[:, core].reshape(-1, d)
    hp_u = (u - smooth(u, half_width, _ORDER))[:, core].reshape(-1, u.shape[-1])
    cov_ru = hp_r.T @ hp_u / hp_r.shape[0]  # (d, n) = gain @ cov(u_true)
    var_true = jnp.diag(jnp.linalg.pinv(gain) @ cov_ru)  # least squares, as lstsq
    var_meas = jnp.mean(hp_u**2, axis=0)
    h0 = float(savgol_coefficients(half_width, _ORDER)[half_width])
    return jnp.maximum(var_meas - var_true, 0.0) / (1.0 - h0)
