"""Simulated service lives: one structure measured window after window while its physics
changes over service time, to judge the monitor (`dtwin_jax.monitor`).

A life is a `dtwin_jax.models.systems.Example` (a nominal model and a
perturbation) and two schedules over its windows: the perturbation's scale (0 before a term
appears, 1 after) and the stiffness factor (0.95 after a 5% drop, a slow decline for a
weakening spring). The state runs on from one window into the next; each window is measured
with noise on every signal.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax.models import systems
from dtwin_jax.preprocess.measurement import add_noise

__all__ = ["simulate_life"]


@dataclass(frozen=True)
class _Scaled:
    """The perturbation `inner` times `params["scale"]` (hashable: one program per `inner`)."""

    inner: Callable

    def __call__(self, x, u, params):
        return params["scale"] * self.inner(x, u, params["inner"])


def _nothing(x, u, params):
    """No perturbation (a linear example): one function, so one compiled simulation."""
    return jnp.zeros_like(x)


def _system(example: systems.Example, scale: float, stiffness: float) -> systems.PerturbedSystem:
    nominal = example.system.nominal
    nominal = eqx.tree_at(lambda n: n.K, nominal, stiffness * nominal.K)
    inner = example.system
    if isinstance(inner, systems.PerturbedSystem):
        return systems.PerturbedSystem(nominal, _Scaled(inner.perturbation),
                                       {"scale": jnp.asarray(scale, float), "inner": inner.params})
    return systems.PerturbedSystem(nominal, _Scaled(_nothing),
                                   {"scale": jnp.asarray(scale, float), "inner": {}})


def simulate_life(example: systems.Example, key: jax.Array, *, scale, stiffness=None, level: float = 0.05,
                  output_only: bool = False) -> list[dict]:
    """Simulate and measure one service life, window by window.

    The state runs on from one window into the next; in window `i` the true system is the
    example's nominal model with its stiffness matrix `K` times `stiffness[i]`, plus its
    perturbation times `scale[i]`.

    **Arguments:**

    - `example`: the structure, a `systems.Example` (its `dt` s, `duration` s per window,
      `x0` and `input_std`).
    - `key`: JAX PRNG key (the inputs or Brownian forcing, and the measurement noise).
    - `scale`: the perturbation's scale in each of the `W` windows, `(W,)` (0 before a term
      appears, 1 after).
    - `stiffness`: the factor on the nominal stiffness matrix `K` in each window, `(W,)`, or
      None (default) for 1 throughout.
    - `level`: measurement noise std as a fraction of each signal's std over the life (every
      signal).
    - `output_only`: drive the structure by Brownian forcing (`systems.simulate_sde`, the
      example's unit-intensity force through `B`) and measure no force; default False: a
      white input of std `input_std` held over each sample, measured.

    **Returns:** a list of `W` window dicts, each with `t (N,)` running on over the life (s)
    and the measured `x (N, m)`, `xdot` and `u (N, n)`: input-output, `xdot (N, m)` every
    state's rate; output-only (no `u`), `xdot (N, d)` what averaging accelerometers read
    (each velocity's change over the sample interval around the sample, over `dt`), named by
    `xdot_names` (the velocity states' names).
    """
    scale = np.asarray(scale, dtype=float)
    stiffness = np.ones_like(scale) if stiffness is None else np.asarray(stiffness, dtype=float)
    N = int(round(example.duration / example.dt))
    t = jnp.arange(N + 1) * example.dt
    x0 = jnp.asarray(example.x0, float)
    xs, xds, us = [], [], []
    for i, (s, k) in enumerate(zip(scale, stiffness)):
        system = _system(example, s, k)
        ki = jax.random.fold_in(key, i)
        if output_only:
            # Half steps: the samples at the odd points, the velocities' changes over a sample
            # interval at the even ones (what an averaging accelerometer reads).
            half = jnp.arange(2 * N + 3) * (example.dt / 2)
            xh = systems.simulate_sde(system, x0, half, ki, substeps=2)
            vel = np.asarray(system.nominal.velocity_index)
            xs.append(np.asarray(xh[1:2 * N:2]))
            xds.append(np.asarray((xh[2:2 * N + 1:2, vel] - xh[:2 * N - 1:2, vel]) / example.dt))
            x0 = xh[2 * N + 1]
        else:
            u = example.input_std * jax.random.normal(ki, (N + 1, system.nominal.n))
            x, xd = systems.simulate(system, x0, t, u)
            xs.append(np.asarray(x[:N])); xds.append(np.asarray(xd[:N])); us.append(np.asarray(u[:N])); x0 = x[N]
    signals = {"x": np.concatenate(xs), "xdot": np.concatenate(xds)} | ({"u": np.concatenate(us)} if us else {})
    names = ({"xdot_names": [example.system.nominal.state_names[i] for i in example.system.nominal.velocity_index]}
             if output_only else {})
    keys = jax.random.split(jax.random.fold_in(key, len(scale)), len(signals))
    noisy = {name: np.asarray(add_noise(k, a, level)) for k, (name, a) in zip(keys, signals.items())}
    times = np.arange(len(scale) * N) * example.dt
    return [{"t": times[i * N:(i + 1) * N], **{name: a[i * N:(i + 1) * N] for name, a in noisy.items()}, **names}
            for i in range(len(scale))]
