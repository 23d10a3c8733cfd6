"""Realistic simulated plants for tests and examples, beyond the paper's open-loop oscillators.

`positioning_stage`: a linear stage of about 100 kg with viscous and Coulomb friction
and a constant offset force, under a digital PD position controller following a smooth
reference, as measured in service: the encoder position, quantized, and the motor force the
controller commanded, both at 1 kHz. The controller closes the loop on the quantized position
(and its backward difference), so the force is correlated with the measurement errors, as on
a real machine; the force is held over each sample (a digital drive).

The plant is `m q'' = u - c v - Fc sign(v) - F0` (states `x1 = q` m, `x2 = v` m/s; input `u`
N). Integrated with diffrax: fixed Bosh3 steps, 16 per sample, on which the held force is
constant (`sign(v)` chatters an adaptive solver).
"""

from __future__ import annotations

from typing import NamedTuple

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax.errors import DataError
from dtwin_jax.models.systems import LinearSecondOrder

__all__ = ["StageParams", "positioning_stage", "stage_nominal", "STAGE_TERMS"]

# The discovered perturbation of the stage against `stage_nominal` (mass and viscous
# friction known): acceleration units, in `library.parse_library`'s names.
STAGE_TERMS = ("sign(x2)", "1")


class StageParams(NamedTuple):
    """A positioning stage and its controller (SI units).

    `mass` kg, `viscous` N s/m, `coulomb` N, `offset` N (a constant force: a cable chain, a
    tilt); `kp` N/m and `kd` N s/m of the PD controller; `resolution` m of the encoder;
    `force_noise` N (std of the measured motor force around the commanded one);
    `amplitude` m and `bandwidth` Hz of the smooth random reference around `centre` m (where
    the stage starts, at rest: the position never changes sign, as on a real axis);
    `substeps` solver steps per sample; `disturbance` N, the std of an unmeasured force on
    the stage (a random load, cogging), band-limited to `disturbance_bandwidth` Hz, which the
    controller fights: the input is then correlated with the equation error."""

    mass: float = 100.0
    viscous: float = 50.0
    coulomb: float = 20.0
    offset: float = 5.0
    kp: float = 4.0e5
    kd: float = 4.0e3
    resolution: float = 1e-6
    force_noise: float = 0.5
    amplitude: float = 0.02
    bandwidth: float = 2.0
    centre: float = 0.05
    substeps: int = 16
    disturbance: float = 0.0
    disturbance_bandwidth: float = 5.0


def stage_nominal(params: StageParams = StageParams()) -> LinearSecondOrder:
    """The nominal model a user would write: mass and viscous friction, no spring, no Coulomb
    friction, no offset (`M q'' + C q' = u`).

    **Arguments:**

    - `params`: the stage, `StageParams` (its `mass` kg and `viscous` N s/m are used).

    **Returns:** the `LinearSecondOrder` with `M = [[mass]]`, `C = [[viscous]]`, `K = [[0]]`,
    `B = [[1]]` (states `x1 = q` m, `x2 = v` m/s; input `u` N).
    """
    return LinearSecondOrder.create([[params.mass]], [[params.viscous]], [[0.0]], [[1.0]])


def _sines(key, freqs, t):
    """Sinusoids at `freqs (F,)` Hz on `t (N,)`: random phases, amplitudes in [1/2, 1).
    Returns `(waves (N, F), phases (F,), amplitudes (F,))`."""
    k1, k2 = jax.random.split(key)
    phases = jax.random.uniform(k1, freqs.shape, maxval=2 * jnp.pi)
    amplitudes = jax.random.uniform(k2, freqs.shape, minval=0.5, maxval=1.0)
    return jnp.sin(2 * jnp.pi * freqs * t[:, None] + phases), phases, amplitudes


def _reference(key, t, params: StageParams):
    """A smooth random reference: `centre` plus a sum of 8 sinusoids up to `bandwidth` Hz
    with random phases, scaled to `amplitude` peak, faded in over 1 s (a raised cosine)."""
    freqs = params.bandwidth * jnp.linspace(0.1, 1.0, 8)
    waves, phases, amplitudes = _sines(key, freqs, t)
    r = jnp.sum(amplitudes / freqs * (waves - jnp.sin(phases)), axis=1)  # smoother at high f
    ramp = jnp.where(t < 1.0, 0.5 - 0.5 * jnp.cos(jnp.pi * jnp.minimum(t, 1.0)), 1.0)
    return params.centre + params.amplitude * ramp * r / jnp.max(jnp.abs(r))


def _disturbance(key, t, params: StageParams):
    """A random force of std `disturbance` N: 16 sinusoids up to `disturbance_bandwidth` Hz
    with random phases and amplitudes."""
    waves, _, amplitudes = _sines(key, params.disturbance_bandwidth * jnp.linspace(1.0 / 16, 1.0, 16), t)
    d = jnp.sum(amplitudes * waves, axis=1)
    return params.disturbance * d / jnp.std(d)


def _plant_rate(s, y, args):
    u, d, p = args
    q, v = y
    force = u + d - p.viscous * v - p.coulomb * jnp.sign(v) - p.offset
    return jnp.stack([v, force / p.mass])


def positioning_stage(key, duration: float = 25.0, dt: float = 1e-3, params: StageParams = StageParams()) -> dict:
    """Simulate the stage under closed-loop PD control and measure it.

    **Arguments:**

    - `key`: a JAX PRNG key (the reference, the disturbance and the force sensor's noise).
    - `duration`: the record's length, s (at least 16 samples).
    - `dt`: the sample interval, s (1 kHz by default).
    - `params`: the stage and its controller, `StageParams`.

    **Returns:** a dict with `t (N,)` s; `x (N, 1)` the measured (quantized) position m and
    `x_names = ["x1"]`; `u (N, 1)` the measured motor force N; `reference (N,)` m; and the
    truth `q (N,)`, `v (N,)`, `force (N,)` (commanded, N), `disturbance (N,)` N (held over each
    sample, like the force).
    """
    if duration <= 0 or dt <= 0 or duration / dt < 16:
        raise DataError(f"positioning_stage needs at least 16 samples, got duration {duration} s at dt {dt} s")
    N = int(round(duration / dt)) + 1
    t = jnp.arange(N) * dt
    k_ref, k_noise = jax.random.split(key)
    r = _reference(k_ref, t, params)
    rdot = jnp.gradient(r, dt)
    dist = _disturbance(jax.random.fold_in(key, 7), t, params) if params.disturbance else jnp.zeros(N)
    term, solver = diffrax.ODETerm(_plant_rate), diffrax.Bosh3()
    h = dt / params.substeps

    def sample(carry, k):
        y, q_prev = carry
        q_meas = jnp.round(y[0] / params.resolution) * params.resolution
        v_est = (q_meas - q_prev) / dt  # the drive's backward difference of the encoder
        u = params.kp * (r[k] - q_meas) + params.kd * (rdot[k] - v_est)  # no integral action: an offset error
        sol = diffrax.diffeqsolve(term, solver, t0=0.0, t1=dt, dt0=h, y0=y, args=(u, dist[k], params),
                                  stepsize_controller=diffrax.ConstantStepSize(),
                                  saveat=diffrax.SaveAt(t1=True), max_steps=params.substeps + 1)
        return (sol.ys[-1], q_meas), (y, q_meas, u)

    start = jnp.array([params.centre, 0.0])
    _, (states, q_meas, force) = jax.lax.scan(sample, (start, params.centre), jnp.arange(N))
    noise = params.force_noise * jax.random.normal(k_noise, (N,))
    return {
        "t": np.asarray(t), "x": np.asarray(q_meas)[:, None], "x_names": ["x1"],
        "u": np.asarray(force + noise)[:, None], "reference": np.asarray(r),
        "q": np.asarray(states[:, 0]), "v": np.asarray(states[:, 1]), "force": np.asarray(force), "disturbance": np.asarray(dist),
    }
