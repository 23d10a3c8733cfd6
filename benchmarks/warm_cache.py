"""What the persistent compilation cache saves on one pipeline, and what it cannot: input-output
examples 1 and 3 updated one after the other (5% noise, 2 chains of 200 draws after 100, XLA's
optimizing passes off as in the test suite), in a fresh process with an empty cache, then in a
second fresh process with every program in the cache. Each run's time is split by JAX's own
compile events into tracing, lowering to MLIR and XLA compilation (or loading from the cache).

    taskset -c 0 python benchmarks/warm_cache.py [--runs cold warm]

``XLA_FLAGS=... python benchmarks/warm_cache.py --runs cold`` compares XLA options on the cold run.
"""

import argparse
import json
import subprocess
import sys
import tempfile
import time

_CHILD = r"""
import collections, json, os, sys, time
os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] = "1"
import jax
jax.config.update("jax_compilation_cache_dir", sys.argv[1])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
seconds = collections.Counter()
events = {"/jax/core/compile/jaxpr_trace_duration": "tracing",
          "/jax/core/compile/jaxpr_to_mlir_module_duration": "lowering",
          "/jax/core/compile/backend_compile_duration": "compiling or loading"}
def listen(event, duration, **kwargs):
    if event in events:
        seconds[events[event]] += duration
jax.monitoring.register_event_duration_secs_listener(listen)
import dtwin_jax
from dtwin_jax.models import systems
from dtwin_jax.preprocess.measurement import measure
from dtwin_jax.update import SamplerSettings, update_input_output
settings = SamplerSettings(num_chains=2, num_draws=200, num_burnin=100)
t0 = time.perf_counter()
for name in ("example1", "example3"):
    ex = systems.EXAMPLES[name]()
    sim = systems.simulate_example(ex, jax.random.key(0))
    meas = measure(jax.random.key(1), sim["t"], sim["x"], sim["xdot"], sim["u"], level=0.05)
    update_input_output(ex.system.nominal, meas.t, meas.x, meas.u, meas.xdot, library=ex.library,
                        settings=settings, seed=0)
print(json.dumps({"total": time.perf_counter() - t0, **seconds}))
"""


def run(cache: str) -> dict:
    out = subprocess.run([sys.executable, "-c", _CHILD, cache], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", nargs="+", choices=("cold", "warm"), default=["cold", "warm"])
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as cache:
        filled = False
        for name in a.runs:
            if name == "cold" and not filled:  # runs with the shared cache empty and fills it
                r, filled = run(cache), True
            elif name == "cold":  # the shared cache is full: an empty one of its own
                with tempfile.TemporaryDirectory() as empty:
                    r = run(empty)
            else:
                if not filled:
                    run(cache)  # fill the shared cache once
                    filled = True
                r = run(cache)
            parts = ", ".join(f"{k} {v:.1f} s" for k, v in r.items() if k != "total")
            print(f"{name}: {r['total']:.1f} s ({parts}; the rest running and Python)")


if __name__ == "__main__":
    t = time.perf_counter()
    main()
    print(f"({time.perf_counter() - t:.0f} s in all)")
