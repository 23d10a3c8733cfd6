"""Fleets: many structures' windows tested and absorbed by one compiled program, sharded
over the devices (and hosts) that JAX sees.

Each structure of a fleet is monitored as `monitor.Monitor` monitors one
(the same score tests, the window alone and pooled with the last ones, the discounted update
or the restart), on input-output windows with every state, its rate and the force measured: the
jittable chain of `dtwin_jax.input_output.targets.input_output_stats` (kinematic
smoother, targets, statistics with the input-noise correction), then the Gibbs sampler on
every equation. `fleet_step` is a pure function of arrays, mapped over the structures
(`jax.vmap` on accelerators, `lax.map` on the CPU, as the sampler maps its chains);
`sharded_fleet_step` runs it under `jax.shard_map` with the fleet axis split over a
`Mesh` (one structure's numbers never leave its device: no communication). Across hosts,
`jax.distributed.initialize` first, then the same mesh over `jax.devices()`.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from dtwin_jax.input_output.targets import input_output_stats
from dtwin_jax.library import Library
from dtwin_jax.monitor.change import linear_columns, overdispersion, window_test
from dtwin_jax.monitor.service import LOOKBACK
from dtwin_jax.sampler import SamplerSettings, SuffStats, sample
from dtwin_jax.sampler.driver import batch_map, default_batch_method

__all__ = ["FleetState", "FleetReport", "fleet_init", "fleet_step", "fleet_mesh", "fleet_put", "sharded_fleet_step"]

FLEET_AXIS = "fleet"


class FleetState(NamedTuple):
    """What a fleet of `F` structures carries from one window to the next (`P = LOOKBACK - 1`)."""

    stats: SuffStats  # (F, q, K, K), (F, q, K), (F, q), (F, q): each twin's drift statistics
    recent_windows: SuffStats  # (F, P, q, ...): the last windows' statistics, newest first
    recent_twins: SuffStats  # (F, P, q, ...): the twin's statistics before each of them
    recent_count: jax.Array  # (F,) int: how many of them count (since the last restart)
    ratio_sum: jax.Array  # (F, q) sum of T over the windows without an alarm (overdispersion)
    ratio_count: jax.Array  # (F, q) their number
    fresh: jax.Array  # (F,) bool: no twin yet (the next window is its baseline, untested)


class FleetReport(NamedTuple):
    """One window of every structure."""

    alarm: jax.Array  # (F,) bool
    p_value: jax.Array  # (F,) the alarm's (combined) p-value; 1 for a baseline window
    p_window: jax.Array  # (F,) the window's alone
    pip: jax.Array  # (F, q, K) inclusion probabilities after the window
    mean: jax.Array  # (F, q, K) posterior mean coefficients (zero where excluded), acceleration units


def fleet_init(num_structures: int, num_equations: int, num_terms: int) -> FleetState:
    """A fleet with no twins yet: each structure's first window is its baseline.

    **Arguments:**

    - `num_structures`: the fleet's size `F`.
    - `num_equations`: the drift equations of each structure, `q`.
    - `num_terms`: the library's terms per equation, `K`.

    **Returns:** a `FleetState` of zero statistics (float64, with `P = LOOKBACK - 1` recent windows'
    slots) and zero counts, every structure `fresh`.
    """
    F, q, K, P = num_structures, num_equations, num_terms, LOOKBACK - 1

    def stats(*lead):
        return SuffStats(*(jnp.zeros(lead + s, jnp.float64) for s in ((q, K, K), (q, K), (q,), (q,))))

    return FleetState(stats(F), stats(F, P), stats(F, P), jnp.zeros((F,), jnp.int32),
                      jnp.zeros((F, q), jnp.float64), jnp.zeros((F, q), jnp.float64), jnp.ones((F,), bool))


def _alarm_p(st: FleetState, window: SuffStats, dispersion, linear):
    """`service.combined_p_value` of the pooled tests of one
    structure (`service.pooled_tests`), jittable: `(p, p_window,
    the window's own unscaled T (q,))`."""
    cums = jax.tree.map(lambda w, r: jnp.concatenate([w[None], w[None] + jnp.cumsum(r, axis=0)]), window,
                        st.recent_windows)
    twins = jax.tree.map(lambda b, r: jnp.concatenate([b[None], r]), st.stats, st.recent_twins)
    tests = jax.vmap(window_test, in_axes=(0, 0, None, None, None))(twins, cums, dispersion, 0.0, linear)
    q = tests.p_value.shape[-1]
    p = jnp.minimum(1.0, jnp.min(tests.p_value, axis=-1) * q)  # (P + 1,)
    valid = jnp.arange(p.size) <= st.recent_count
    ratio = tests.statistic[0] * dispersion
    return jnp.minimum(1.0, jnp.min(jnp.where(valid, p, jnp.inf)) * jnp.sum(valid)), p[0], ratio


def fleet_step(state: FleetState, x, u, xdot, nominal, keys, *, lib: Library, dt: float, half_width: int,
               settings: SamplerSettings, forget: float = 0.9, false_alarm: float = 1e-3):
    """Test and absorb one window of every structure.

    **Arguments:**

    - `state`: the `FleetState` before the window.
    - `x`: `(F, N, m)` measured states.
    - `u`: `(F, N, n)` measured forces.
    - `xdot`: `(F, N, m)` measured rates of the states.
    - `nominal`: the structures' nominal models, a
      `models.systems.LinearSecondOrder` whose arrays have a leading `F`
      axis (`jax.tree.map(lambda *a: jnp.stack(a), *models)`).
    - `keys`: `(F,)` PRNG keys (a structure's draws depend on its key only).
    - `lib`: static: the `Library` of the drift equations' terms.
    - `dt`: static: the sample interval, s.
    - `half_width`: static: the kinematic smoother's half width, in samples
      (`preprocess.denoise.auto_half_width`).
    - `settings`: static: the sampler's `SamplerSettings`.
    - `forget`: the weight, in [0, 1], of the older windows' data at each update (default 0.9), as
      `monitor.Monitor`'s.
    - `false_alarm`: the false-alarm rate per window (default 1e-3), as `monitor.Monitor`'s.

    **Returns:** `(state, report)`: the `FleetState` after the window and the window's
    `FleetReport`. Pure and jittable.
    """

    linear = linear_columns(lib.names, nominal)  # static: the same columns for every structure

    def one(st: FleetState, x, u, xdot, nominal, key):
        window = input_output_stats(nominal, lib, dt, x, u, xdot, half_width)
        q = window.n.shape[0]
        p_value, p_window, ratio = _alarm_p(st, window, overdispersion(st.ratio_sum, st.ratio_count), linear)
        p_value, p_window = jnp.where(st.fresh, 1.0, p_value), jnp.where(st.fresh, 1.0, p_window)
        alarm = (p_value < false_alarm) & ~st.fresh
        restart = alarm | st.fresh
        stats = jax.tree.map(lambda w, old: jnp.where(restart, w, w + forget * old), window, st.stats)
        trace = jax.vmap(lambda k, s: sample(k, s, settings))(jax.random.split(key, q), stats)
        windows = jax.tree.map(lambda w, r: jnp.concatenate([w[None], r[:-1]]), window, st.recent_windows)
        twins = jax.tree.map(lambda b, r: jnp.concatenate([b[None], r[:-1]]), st.stats, st.recent_twins)
        count = jnp.where(restart, 0, jnp.minimum(st.recent_count + 1, LOOKBACK - 1))
        calm = ~restart  # a tested window without an alarm: its T / df joins the dispersion's
        pip = trace.gamma.mean(axis=(1, 2))
        return (FleetState(stats, windows, twins, count, st.ratio_sum + jnp.where(calm, ratio, 0.0),
                           st.ratio_count + calm, jnp.zeros((), bool)),
                FleetReport(alarm, p_value, p_window, pip, trace.theta.mean(axis=(1, 2))))

    # On the CPU one structure after another: a vmapped batch runs every structure's sampler
    # loops as long as its slowest one's (512 structures on one core: 0.30 s per structure-window
    # vmapped, 0.265 s looped; benchmarks/fleet.py).
    return batch_map(one, default_batch_method(), state, x, u, xdot, nominal, keys)


def fleet_mesh(devices=None) -> Mesh:
    """A one-axis mesh (axis `"fleet"`) over the devices.

    **Arguments:**

    - `devices`: the devices, or None (default) for every device JAX sees (`jax.devices()`),
      on every host after `jax.distributed.initialize`.

    **Returns:** the `Mesh`, its one axis `"fleet"`.
    """
    return Mesh(np.asarray(jax.devices() if devices is None else devices), (FLEET_AXIS,))


def sharded_fleet_step(mesh: Mesh, **static):
    """`fleet_step` with the fleet axis split over `mesh` (`jax.shard_map`), jitted.

    The fleet's size must be a multiple of the mesh's.

    **Arguments:**

    - `mesh`: the `Mesh` (`fleet_mesh`) whose axis `"fleet"` splits the fleet.
    - `**static`: `fleet_step`'s keyword arguments (`lib`, `dt`, `half_width`, `settings`,
      `forget`, `false_alarm`).

    **Returns:** the jitted `step(state, x, u, xdot, nominal, keys) -> (state, report)`; put the
    inputs on the mesh with `fleet_sharding` (or `fleet_put`) to avoid a transfer.
    """
    spec = PartitionSpec(FLEET_AXIS)
    body = functools.partial(fleet_step, **static)
    # check_vma off: the sampler's loops start from constants that the fleet axis never touches.
    return jax.jit(jax.shard_map(body, mesh=mesh, in_specs=spec, out_specs=spec, check_vma=False))


def fleet_sharding(mesh: Mesh) -> NamedSharding:
    """The sharding of an array whose leading axis is the fleet's.

    **Arguments:**

    - `mesh`: the fleet's `Mesh` (`fleet_mesh`).

    **Returns:** the `NamedSharding` that splits the leading axis over the mesh's `"fleet"` axis.
    """
    return NamedSharding(mesh, PartitionSpec(FLEET_AXIS))


def fleet_put(tree, mesh: Mesh):
    """Every array of `tree` (leading axis the fleet's) as a global array on `mesh`.

    Each global array is built from the rows this process's devices hold: the same call on every
    process after `jax.distributed.initialize` (each holds the whole input, or at least its rows).
    PRNG keys stay keys; arrays already spread over the mesh (a step's output) pass as they are.

    **Arguments:**

    - `tree`: a pytree of arrays (NumPy or JAX, PRNG keys included) whose leading axis is the fleet's.
    - `mesh`: the fleet's `Mesh` (`fleet_mesh`).

    **Returns:** the same tree of global `jax.Array`s, sharded by `fleet_sharding(mesh)`.
    """
    sharding = fleet_sharding(mesh)

    def one(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            return x
        key = isinstance(x, jax.Array) and jnp.issubdtype(x.dtype, jax.dtypes.prng_key)
        a = np.asarray(jax.random.key_data(x) if key else x)
        out = jax.make_array_from_callback(a.shape, sharding, lambda index: a[index])
        return jax.random.wrap_key_data(out) if key else out

    return jax.tree.map(one, tree)
