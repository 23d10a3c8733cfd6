"""Fleet throughput (issue 28): structure-windows per second of
:func:`dtwin_jax.monitor.fleet.fleet_step`, one device (no mesh) against
:func:`~dtwin_jax.monitor.fleet.sharded_fleet_step` over 1, 2, 4 and 8 devices.

    python benchmarks/fleet.py --structures 1000            # the CPU: 8 virtual devices
    python benchmarks/fleet.py --structures 1000 --platform gpu
    python benchmarks/fleet.py --structures 1000 --processes 2   # two pinned processes, jax.distributed
    taskset -c 0 python benchmarks/fleet.py --structures 500 --host-devices 1 --devices ""  # one core

On the CPU the script asks XLA for 8 host devices before JAX starts
(``--xla_force_host_platform_device_count=8``); they share the machine's cores, so past the
core count more devices add no throughput. Each structure is a zoo SDOF member (seeds
0-7 in turn, 32 simulated lives repeated), 1 s windows at 1 kHz, 5% noise on every signal; the first window is the
baseline (compiles the program), the second is tested and absorbed and timed.
"""

import argparse
import json
import os
import socket
import subprocess
import sys
import time


def _host_devices() -> int:
    return int(sys.argv[sys.argv.index("--host-devices") + 1]) if "--host-devices" in sys.argv else 8


if ("--platform" not in sys.argv or "cpu" in sys.argv) and "--rank" not in sys.argv and _host_devices() > 1:
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") +
                               f" --xla_force_host_platform_device_count={_host_devices()}")

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
    fleet_put,
    fleet_sharding,
    fleet_step,
    sharded_fleet_step,
)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--structures", type=int, default=1000)
    ap.add_argument("--platform", default="cpu")
    ap.add_argument("--devices", default="1,2,4,8", help="sharded over these device counts ('' for none)")
    ap.add_argument("--skip-plain", action="store_true", help="leave out the one-device program without a mesh")
    ap.add_argument("--host-devices", type=int, default=8, help="CPU devices XLA declares (1: none virtual)")
    ap.add_argument("--processes", type=int, default=0,
                    help="instead: this many processes, one pinned core and one device each, joined by jax.distributed")
    ap.add_argument("--rank", type=int, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--port", type=int, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--simulate-on-cpu", action="store_true",
                    help="simulate the lives on the host's CPU (small sequential solves idle an accelerator)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    if a.processes and a.rank is None:
        return _launch(a)
    if a.rank is not None:
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[a.rank % len(os.sched_getaffinity(0))]})
        jax.distributed.initialize(f"127.0.0.1:{a.port}", num_processes=a.processes, process_id=a.rank)
    F = a.structures
    devices = jax.devices(a.platform)
    members = [zoo.draw_member(s).example for s in range(8)]
    # 32 simulated lives (4 per member) in turn: the simulations would take longer than the
    # fleet; each structure still draws with its own key.
    t0 = time.perf_counter()
    with jax.default_device(jax.devices("cpu")[0] if a.simulate_on_cpu else devices[0]):
        simulated = [simulate_life(members[i % 8], jax.random.key(i), scale=[1.0, 1.0]) for i in range(min(F, 32))]
        lives = [simulated[i % len(simulated)] for i in range(F)]
        data = [{k: jnp.stack([life[w][k] for life in lives]) for k in ("x", "u", "xdot")} for w in range(2)]
        nominal = jax.tree.map(lambda *x: jnp.stack(x), *[members[i % 8].system.nominal for i in range(F)])
    data, nominal = jax.device_put((data, nominal), devices[0])
    print(f"lives simulated in {time.perf_counter() - t0:.1f} s", flush=True)
    lib = parse_library("poly:3,sign,abs,xabs,input", 2, 1)
    static = dict(lib=lib, dt=1e-3, half_width=20, settings=MONITOR_SETTINGS)
    keys = [jax.vmap(lambda i: jax.random.fold_in(jax.random.key(w), i))(jnp.arange(F)) for w in range(2)]
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

    if a.rank is not None:  # every process's device in one mesh; each puts the rows it holds
        mesh = fleet_mesh()
        first, seconds = run(sharded_fleet_step(mesh, **static), lambda args: fleet_put(args, mesh))
        print(json.dumps({"rank": a.rank, "first": first, "seconds": seconds}), flush=True)
        jax.distributed.shutdown()
        return
    if not a.skip_plain:
        plain = jax.jit(lambda *args: fleet_step(*args, **static))
        # Every input committed to the device, as the step's outputs are: the tested window
        # then reuses the first window's program instead of compiling one for new placements.
        first, seconds = run(plain, lambda args: jax.device_put(args, devices[0]))
        rows.append(("one device, no mesh", first, seconds))
    for D in (int(d) for d in a.devices.split(",") if d):
        if D > len(devices) or F % D:
            continue
        mesh = fleet_mesh(devices[:D])
        first, seconds = run(sharded_fleet_step(mesh, **static), lambda args: jax.device_put(args, fleet_sharding(mesh)))
        rows.append((f"sharded over {D} device{'s' * (D > 1)}", first, seconds))
    _report(a, devices[0].device_kind, len(os.sched_getaffinity(0)), rows)


def _report(a, kind, cores, rows):
    F = a.structures
    lines = [f"## Fleet of {F} structures x 1 window ({a.platform}: {kind}, {cores} of "
             f"{os.cpu_count()} cores, host {os.uname().nodename})", "", "| program | first window (compile + run), s | "
             "tested window, s | structure-windows / s |", "|---|---|---|---|"]
    lines += [f"| {name} | {f:.1f} | {s:.1f} | {F / s:.1f} |" for name, f, s in rows]
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        with open(a.out, "a") as f:
            f.write(text + "\n")


def _launch(a):
    """``a.processes`` copies of this script joined by jax.distributed on localhost; the
    window's time is the slowest process's."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "XLA_FLAGS": ""}
    args = [sys.executable, __file__, "--structures", str(a.structures), "--platform", a.platform,
            "--processes", str(a.processes), "--port", str(port)]
    running = [subprocess.Popen(args + ["--rank", str(r)], env=env, stdout=subprocess.PIPE, text=True)
               for r in range(a.processes)]
    results = [json.loads(p.communicate()[0].strip().splitlines()[-1]) for p in running]
    P = a.processes
    _report(a, "one device per process", len(os.sched_getaffinity(0)),
            [(f"{P} processes (jax.distributed), one pinned core each", max(r["first"] for r in results),
              max(r["seconds"] for r in results))])


if __name__ == "__main__":
    main()
