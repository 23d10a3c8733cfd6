"""Fleets: many structures' windows tested and absorbed by one compiled program, sharded
over the devices (and hosts) that JAX sees.

Each structure of a fleet is monitored as :class:`~dtwin_jax.monitor.Monitor` monitors one
(the same score tests, Fisher's combination over the last windows, the discounted update or
the restart), on input-output windows with every state, its rate and the force measured: the
jittable chain of :func:`dtwin_jax.input_output.targets.input_output_stats` (kinematic
smoother, targets, statistics with the input-noise correction), then the Gibbs sampler on
every equation. :func:`fleet_step` is a pure function of arrays, vmapped over the structures;
:func:`sharded_fleet_step` runs it under ``jax.shard_map`` with the fleet axis split over a
``Mesh`` (one structure's numbers never leave its device: no communication). Across hosts,
:func:`jax.distributed.initialize` first, then the same mesh over ``jax.devices()``.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from dtwin_jax.input_output.targets import input_output_stats
from dtwin_jax.library import Library
from dtwin_jax.monitor.change import Belief, window_test
from dtwin_jax.monitor.service import LOOKBACK
from dtwin_jax.sampler import SamplerSettings, SuffStats, sample

__all__ = ["FleetState", "FleetReport", "fleet_init", "fleet_step", "fleet_mesh", "sharded_fleet_step"]

FLEET_AXIS = "fleet"


class FleetState(NamedTuple):
    """What a fleet of ``F`` structures carries from one window to the next."""

    belief: Belief  # (F, q, K), (F, q, K, K), (F, q): each twin's drift coefficients
    stats: SuffStats  # (F, q, K, K), (F, q, K), (F, q), (F, q): the statistics they were sampled from
    recent: jax.Array  # (F, LOOKBACK - 1) window p-values since the last restart, newest first (NaN: none)
    fresh: jax.Array  # (F,) bool: no twin yet (the next window is its baseline, untested)


class FleetReport(NamedTuple):
    """One window of every structure."""

    alarm: jax.Array  # (F,) bool
    p_value: jax.Array  # (F,) the alarm's (combined) p-value; 1 for a baseline window
    p_window: jax.Array  # (F,) the window's alone
    pip: jax.Array  # (F, q, K) inclusion probabilities after the window
    mean: jax.Array  # (F, q, K) posterior mean coefficients (zero where excluded), acceleration units


def fleet_init(num_structures: int, num_equations: int, num_terms: int) -> FleetState:
    """A fleet with no twins yet: each structure's first window is its baseline."""
    F, q, K = num_structures, num_equations, num_terms
    zeros = functools.partial(jnp.zeros, dtype=jnp.float64)
    return FleetState(Belief(zeros((F, q, K)), zeros((F, q, K, K)), jnp.ones((F, q))),
                      SuffStats(zeros((F, q, K, K)), zeros((F, q, K)), zeros((F, q)), zeros((F, q))),
                      jnp.full((F, LOOKBACK - 1), jnp.nan, dtype=jnp.float64), jnp.ones((F,), bool))


def _combined(p_window, recent):
    """:func:`~dtwin_jax.monitor.service.combined_p_value` of one structure, jittable."""
    p = jnp.clip(jnp.concatenate([p_window[None], recent]), 1e-300, 1.0)
    valid = jnp.cumprod(jnp.isfinite(jnp.concatenate([jnp.ones(1), recent]))).astype(bool)
    s = jnp.cumsum(jnp.where(valid, -jnp.log(jnp.where(valid, p, 1.0)), 0.0))  # -sum log p over the first L
    L = jnp.arange(1, p.size + 1)
    terms = jnp.stack([s**j / math.factorial(j) for j in range(p.size)], axis=-1)  # (L, j)
    sf = jnp.exp(-s) * jnp.sum(jnp.where(jnp.arange(p.size)[None, :] < L[:, None], terms, 0.0), axis=-1)
    tried = jnp.sum(valid)
    return jnp.minimum(1.0, jnp.min(jnp.where(valid, sf, jnp.inf)) * tried)


def _belief(trace) -> Belief:
    """Belief of one equation from its draws ``(C, D, K)``."""
    theta = trace.theta.reshape(-1, trace.theta.shape[-1])
    mean = theta.mean(axis=0)
    d = theta - mean
    return mean, d.T @ d / (theta.shape[0] - 1), trace.sigma2.mean()


def fleet_step(state: FleetState, x, u, xdot, nominal, keys, *, lib: Library, dt: float, half_width: int,
               settings: SamplerSettings, forget: float = 0.9, false_alarm: float = 1e-3):
    """Test and absorb one window of every structure.

    **Arguments:**

    - ``state``: the :class:`FleetState` before the window.
    - ``x``, ``xdot``: ``(F, N, m)`` measured states and rates; ``u``: ``(F, N, n)`` forces.
    - ``nominal``: the structures' nominal models, a
      :class:`~dtwin_jax.models.systems.LinearSecondOrder` whose arrays have a leading ``F``
      axis (``jax.tree.map(lambda *a: jnp.stack(a), *models)``).
    - ``keys``: ``(F,)`` PRNG keys (a structure's draws depend on its key only).
    - ``lib``, ``dt`` (s), ``half_width``, ``settings``: static: the library, the sample
      interval, the smoother's half width (:func:`~dtwin_jax.preprocess.denoise.auto_half_width`)
      and the sampler's settings.
    - ``forget``, ``false_alarm``: as :class:`~dtwin_jax.monitor.Monitor`'s.

    **Returns:** ``(state after the window, FleetReport)``. Pure and jittable.
    """

    def one(st: FleetState, x, u, xdot, nominal, key):
        window = input_output_stats(nominal, lib, dt, x, u, xdot, half_width)
        test = window_test(st.belief, window)
        q = test.p_value.shape[0]
        p_window = jnp.minimum(1.0, jnp.min(test.p_value) * q)
        p_value = jnp.where(st.fresh, 1.0, _combined(p_window, st.recent))
        alarm = (p_value < false_alarm) & ~st.fresh
        restart = alarm | st.fresh
        stats = jax.tree.map(lambda w, old: jnp.where(restart, w, w + forget * old), window, st.stats)
        trace = jax.vmap(lambda k, s: sample(k, s, settings))(jax.random.split(key, q), stats)
        belief = Belief(*jax.vmap(_belief)(trace))
        recent = jnp.where(restart, jnp.nan, jnp.concatenate([jnp.where(st.fresh, jnp.nan, p_window)[None],
                                                               st.recent[:-1]]))
        pip = trace.gamma.mean(axis=(1, 2))
        return (FleetState(belief, stats, recent, jnp.zeros((), bool)),
                FleetReport(alarm, p_value, p_window, pip, belief.mean))

    return jax.vmap(one)(state, x, u, xdot, nominal, keys)


def fleet_mesh(devices=None) -> Mesh:
    """A one-axis mesh (axis ``"fleet"``) over ``devices`` (default: every device JAX sees,
    on every host after :func:`jax.distributed.initialize`)."""
    return Mesh(np.asarray(jax.devices() if devices is None else devices), (FLEET_AXIS,))


def sharded_fleet_step(mesh: Mesh, **static):
    """:func:`fleet_step` with the fleet axis split over ``mesh`` (``jax.shard_map``), jitted;
    ``static`` are its keyword arguments (``lib``, ``dt``, ``half_width``, ``settings``,
    ``forget``, ``false_alarm``). The fleet's size must be a multiple of the mesh's. Returns
    ``step(state, x, u, xdot, nominal, keys) -> (state, report)``; put the inputs on the mesh
    with :func:`fleet_sharding` to avoid a transfer."""
    spec = PartitionSpec(FLEET_AXIS)
    body = functools.partial(fleet_step, **static)
    # check_vma off: the sampler's loops start from constants that the fleet axis never touches.
    return jax.jit(jax.shard_map(body, mesh=mesh, in_specs=spec, out_specs=spec, check_vma=False))


def fleet_sharding(mesh: Mesh) -> NamedSharding:
    """The sharding of an array whose leading axis is the fleet's."""
    return NamedSharding(mesh, PartitionSpec(FLEET_AXIS))
