"""The largest resident size of an output-only update from accelerometers alone, by window
length (docs/performance.md, "The weak form from accelerometers").

    taskset -c 0 python benchmarks/accelerometer_memory.py --member 5 --seconds 40 80

Each window is one record of a zoo member's ambient vibration (the monitor's lives: white force,
5% noise, averaging accelerometers) updated with the monitor's settings, each in a fresh
process. Prints the seconds and the process's peak resident size (``VmHWM``) of each update.
"""

import argparse
import json
import subprocess
import sys


def one(member: int, seconds: float) -> dict:
    """Update one window in this process and return its time and peak resident size."""
    import time

    import jax
    import numpy as np

    import dtwin_jax  # noqa: F401  (float64)
    from dtwin_jax.models import zoo
    from dtwin_jax.models.lives import simulate_life
    from dtwin_jax.monitor import MONITOR_SETTINGS
    from dtwin_jax.update.from_data import update_from_data

    m = zoo.draw_member(member)
    ex = m.example._replace(duration=seconds)
    w = simulate_life(ex, jax.random.key(member), scale=np.ones(1), stiffness=np.ones(1), level=0.05,
                      output_only=True)[0]
    start = time.perf_counter()
    res = update_from_data("output-only", ex.system.nominal,
                           {"t": w["t"], "xdot": w["xdot"], "xdot_names": w["xdot_names"]},
                           library=ex.library_output_only, settings=MONITOR_SETTINGS)
    seconds_taken = time.perf_counter() - start
    peak = next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("VmHWM"))
    return {"member": member, "family": m.family, "seconds": seconds, "update_s": round(seconds_taken, 1),
            "peak_mb": peak // 1024, "drift": [e.state for e in res.equations if e.kind == "drift"]}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--member", type=int, default=5)
    ap.add_argument("--seconds", type=float, nargs="+", default=[40.0, 80.0])
    ap.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(args.member, args.seconds[0])))
        return
    for s in args.seconds:
        out = subprocess.run([sys.executable, __file__, "--one", "--member", str(args.member), "--seconds", str(s)],
                             capture_output=True, text=True)
        line = out.stdout.strip().splitlines()[-1] if out.returncode == 0 else f"failed ({out.returncode})"
        print(f"{s:g} s: {line}", flush=True)


if __name__ == "__main__":
    main()
