"""One sampler chain (K = 36, N = 1000, 5000 draws, after compilation) under the threading
choices a user has, each in a fresh process (XLA sizes its CPU thread pool at start).

    python benchmarks/thread_pinning.py

Configurations: the process free to use every core; pinned to one core from the start
(`taskset -c 0`); XLA's single-thread flags; async dispatch off; and every thread pinned
after XLA has started (what a library could do from inside an already running process).
Prints the best of three runs per configuration.
"""

import os
import subprocess
import sys

CHILD = r"""
import os, sys, time
import jax
if "noasync" in sys.argv: jax.config.update("jax_cpu_enable_async_dispatch", False)
import numpy as np
import dtwin_jax
from dtwin_jax import sampler as S
rng = np.random.default_rng(0)
L = rng.normal(size=(1000, 36)); y = L[:, :3] @ np.array([1.0, -2.0, 0.5]) + 0.1 * rng.normal(size=1000)
st = S.suff_stats(L, y)
run = lambda k: S.sample_jit(k, st, num_draws=5000, num_burnin=0, num_chains=1).gamma.block_until_ready()
run(jax.random.key(0))
if "pin-after" in sys.argv:
    for task in os.listdir("/proc/self/task"):
        os.sched_setaffinity(int(task), {sorted(os.sched_getaffinity(0))[0]})
times = []
for i in range(1 if "pin-after" in sys.argv else 3):
    start = time.perf_counter(); run(jax.random.key(i + 1)); times.append(time.perf_counter() - start)
print(min(times))
"""


def measure(label, prefix=(), env=None, args=()):
    out = subprocess.run([*prefix, sys.executable, "-c", CHILD, *args], capture_output=True, text=True,
                         env={**os.environ, **(env or {})}, check=True).stdout.split()[-1]
    print(f"| {label} | {float(out):.3f} |", flush=True)


def main():
    core = str(sorted(os.sched_getaffinity(0))[0])
    print(f"{os.cpu_count()} cores\n\n| threading | s per 5000-draw chain |\n|---|---|")
    measure("free (every core)")
    measure("pinned to one core from the start (taskset)", prefix=("taskset", "-c", core))
    measure("XLA single-thread flags", env={"XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false "
                                                         "intra_op_parallelism_threads=1"})
    measure("async dispatch off", args=("noasync",))
    measure("every thread pinned after XLA started (one run)", args=("pin-after",))


if __name__ == "__main__":
    main()
