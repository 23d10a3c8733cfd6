"""Fleet throughput (issue 28): structure-windows per second of
:func:`dtwin_jax.monitor.fleet.fleet_step`, one device (vmapped) against
:func:`~dtwin_jax.monitor.fleet.sharded_fleet_step` over 1, 2, 4 and 8 devices.

    python benchmarks/fleet.py --structures 1000            # the CPU: 8 virtual devices
    python benchmarks/fleet.py --structures 1000 --platform gpu

On the CPU the script asks XLA for 8 host devices before JAX starts
(``--xla_force_host_platform_device_count=8``); they share the machine's cores, so past the
core count more devices add no throughput. Each structure is a zoo SDOF member (seeds
0-7 in turn), 1 s windows at 1 kHz, 5% noise on every signal; the first window is the
baseline (compiles the program), the second is tested and absorbed and timed.
"""

import argparse
import os
import sys
import time

if "--platform" not in sys.argv or "cpu" in sys.argv:
    os.environ["XLA_FLAGS"] = os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=8"

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

import dtwin_jax  # noqa: E402,F401
from dtwin_jax.library import parse_library  # noqa: E402
from dtwin_jax.models import zoo  # noqa: E402
from dtwin_jax.models.lives import simulate_life  # noqa: E402
from dtwin_jax.monitor import MONITOR_SETTINGS  # noqa: E402
from dtwin_jax.monitor.fleet import (  # noqa: E402
    fleet_init,
    fleet_mesh,
    fleet_sharding,
    fleet_step,
    sharded_fleet_step,
)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--structures", type=int, default=1000)
    ap.add_argument("--platform", default="cpu")
    ap.add_argument("--devices", default="1,2,4,8", help="sharded over these device counts ('' for none)")
    ap.add_argument("--skip-plain", action="store_true", help="leave out the one-device vmapped program")
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    F = a.structures
    members = [zoo.draw_member(s).example for s in range(8)]
    lives = [simulate_life(members[i % 8], jax.random.key(i), scale=[1.0, 1.0]) for i in range(F)]
    data = [{k: jnp.stack([life[w][k] for life in lives]) for k in ("x", "u", "xdot")} for w in range(2)]
    nominal = jax.tree.map(lambda *x: jnp.stack(x), *[members[i % 8].system.nominal for i in range(F)])
    lib = parse_library("poly:3,sign,abs,xabs,input", 2, 1)
    static = dict(lib=lib, dt=1e-3, half_width=20, settings=MONITOR_SETTINGS)
    keys = [jax.vmap(lambda i: jax.random.fold_in(jax.random.key(w), i))(jnp.arange(F)) for w in range(2)]
    devices = jax.devices(a.platform)
    rows = []

    def run(step, put):
        state = fleet_init(F, 1, lib.K)
        t0 = time.perf_counter()
        state, _ = jax.block_until_ready(step(*put((state, data[0]["x"], data[0]["u"], data[0]["xdot"], nominal,
                                                    keys[0]))))
        first = time.perf_counter() - t0
        t0 = time.perf_counter()
        jax.block_until_ready(step(*put((state, data[1]["x"], data[1]["u"], data[1]["xdot"], nominal, keys[1]))))
        return first, time.perf_counter() - t0

    if not a.skip_plain:
        plain = jax.jit(lambda *args: fleet_step(*args, **static))
        with jax.default_device(devices[0]):
            first, seconds = run(plain, lambda args: args)
        rows.append(("one device, vmapped", first, seconds))
    for D in (int(d) for d in a.devices.split(",") if d):
        if D > len(devices) or F % D:
            continue
        mesh = fleet_mesh(devices[:D])
        first, seconds = run(sharded_fleet_step(mesh, **static), lambda args: jax.device_put(args, fleet_sharding(mesh)))
        rows.append((f"sharded over {D} device{'s' * (D > 1)}", first, seconds))
    host = os.uname().nodename
    cores = len(os.sched_getaffinity(0))
    lines = [f"## Fleet of {F} structures x 1 window ({a.platform}: {devices[0].device_kind}, {cores} of "
             f"{os.cpu_count()} cores, host {host})", "", "| program | first window (compile + run), s | tested window, s | "
             "structure-windows / s |", "|---|---|---|---|"]
    lines += [f"| {name} | {f:.1f} | {s:.1f} | {F / s:.1f} |" for name, f, s in rows]
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        with open(a.out, "a") as f:
            f.write(text + "\n")


if __name__ == "__main__":
    main()
