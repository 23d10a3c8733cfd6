"""Run by tests/test_fleet.py in processes of their own: the fleet's windows of ``IN.npz``
through :func:`dtwin_jax.monitor.fleet.sharded_fleet_step` over 8 CPU devices.

    python fleet_sharded.py IN.npz OUT.npz                      # one process, 8 devices
    python fleet_sharded.py IN.npz OUT.npz RANK PROCESSES PORT  # jax.distributed on localhost

Devices come from ``XLA_FLAGS=--xla_force_host_platform_device_count`` (set before JAX
starts: 8 for one process, 8 / PROCESSES each otherwise). Each process saves the shards it
holds of every leaf of the states and reports (``w{window}_{leaf}_{first structure}``)."""

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
    fleet_put,
    sharded_fleet_step,
)


def main(src, out, rank=None, processes=None, port=None):
    if rank is not None:
        jax.distributed.initialize(f"127.0.0.1:{port}", num_processes=int(processes), process_id=int(rank))
    data = np.load(src)
    assert len(jax.devices()) == 8, jax.devices()
    nominal = LinearSecondOrder(*(jnp.asarray(data[k]) for k in ("M", "C", "K", "B", "F0")))
    mesh = fleet_mesh()  # every device of every process
    step = sharded_fleet_step(mesh, **STATIC)
    F, W = data["x"].shape[:2]

    state = fleet_init(F, 1, STATIC["lib"].K)
    saved = {}
    for w in range(W):
        keys = jax.random.wrap_key_data(data["keys"][w])
        args = (state, *(data[k][:, w] for k in ("x", "u", "xdot")), nominal, keys)
        state, report = step(*fleet_put(args, mesh))
        assert report.alarm.sharding.num_devices == 8
        for i, leaf in enumerate(jax.tree.leaves((state, report))):
            for shard in leaf.addressable_shards:
                saved[f"w{w}_{i}_{shard.index[0].start or 0}"] = np.asarray(shard.data)
    np.savez(out, **saved)
    if rank is not None:
        jax.distributed.shutdown()


if __name__ == "__main__":
    main(*sys.argv[1:])
