"""Run by tests/test_fleet.py in a process of its own, with 8 virtual CPU devices
(``XLA_FLAGS=--xla_force_host_platform_device_count=8``, set before JAX starts): the fleet's
windows of ``IN.npz`` through :func:`dtwin_jax.monitor.fleet.sharded_fleet_step`, every
leaf of the states and reports saved to ``OUT.npz``."""

import sys

import jax
import jax.numpy as jnp
import numpy as np
from fleet_settings import STATIC

import dtwin_jax  # noqa: F401  (float64)
from dtwin_jax.models.systems import LinearSecondOrder
from dtwin_jax.monitor.fleet import (
    fleet_init,
    fleet_mesh,
    fleet_sharding,
    sharded_fleet_step,
)


def main(src, out):
    data = np.load(src)
    assert len(jax.devices()) == 8, jax.devices()
    nominal = LinearSecondOrder(*(jnp.asarray(data[k]) for k in ("M", "C", "K", "B", "F0")))
    mesh = fleet_mesh()
    step = sharded_fleet_step(mesh, **STATIC)
    F, W = data["x"].shape[:2]
    state = fleet_init(F, 1, STATIC["lib"].K)
    leaves = []
    for w in range(W):
        args = (state, data["x"][:, w], data["u"][:, w], data["xdot"][:, w], nominal, jax.random.wrap_key_data(data["keys"][w]))
        state, report = step(*jax.device_put(args, fleet_sharding(mesh)))
        assert report.alarm.sharding.num_devices == 8
        leaves.append([np.asarray(a) for a in jax.tree.leaves((state, report))])
    np.savez(out, **{f"w{w}_{i}": a for w, ls in enumerate(leaves) for i, a in enumerate(ls)})


if __name__ == "__main__":
    main(*sys.argv[1:])
