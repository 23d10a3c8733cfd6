"""Where a cold output-only update's time goes: one example simulated (100 records x 1 s, 5%
noise), then updated twice in this process; prints the stages of each call and the XLA
compilation time of every compiled program (from JAX's compile log).

    taskset -c 0 python benchmarks/cold_update.py [example1|example2|example3] [--records R] [--default-settings]

``--records 300 --default-settings``: the issue's 300 x 1 s ensemble with the default 4 x 2000
draws (README, Performance: the cold first call); without ``taskset`` XLA compiles on both cores.

Run it in a fresh process with no persistent compilation cache (the default here: the
library sets none), pinned to one core. Each call prints its CPU time over all threads: on
n cores a call cannot take less than CPU / n, however its compilations were scheduled.
Last, the compilation time of one call site of ``jax.scipy.linalg.expm`` against
``dtwin_jax.linalg.expm`` (12 x 12) and of ``jnp.linalg.solve`` against
``dtwin_jax.linalg.mass_solve`` (1 x 1), each a fresh program.
"""

import argparse
import io
import logging
import re
import resource
import time

import jax
import numpy as np

from dtwin_jax import SamplerSettings, update_output_only
from dtwin_jax.models import systems
from dtwin_jax.preprocess.measurement import add_noise


def main(name: str = "example1", records: int = 100, default_settings: bool = False, library: str | None = None) -> None:
    jax.config.update("jax_log_compiles", True)
    log = io.StringIO()
    handler = logging.StreamHandler(log)
    logger = logging.getLogger("jax")
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    logger.propagate = False

    # tests/test_output_only.py's settings, or the package's defaults (4 x 2000 draws)
    settings = SamplerSettings() if default_settings else SamplerSettings(num_chains=2, num_draws=600, num_burnin=300)
    ex = systems.EXAMPLES[name]().for_output_only()
    start = time.perf_counter()
    sim = systems.simulate_example_sde(ex, jax.random.key(0), num_records=records)
    x = np.asarray(add_noise(jax.random.key(1), sim["x"], 0.05))
    print(f"{name}, {records} records: simulation, first call {time.perf_counter() - start:.2f} s")
    for call in ("first", "second"):
        start, cpu = time.perf_counter(), _cpu_seconds()
        result = update_output_only(ex.system.nominal, sim["t"], x, library=library or ex.library_output_only,
                                    settings=settings)
        print(f"update, {call} call {time.perf_counter() - start:.2f} s (CPU {_cpu_seconds() - cpu:.1f} s over all "
              f"threads): {result.preprocessing['stage_seconds']}")
    compiled: dict[str, float] = {}
    for line in log.getvalue().splitlines():
        found = re.search(r"Finished XLA compilation of (.*) in ([0-9.e-]+) sec", line)
        if found:
            compiled[found.group(1)] = compiled.get(found.group(1), 0.0) + float(found.group(2))
    print(f"XLA compilation {sum(compiled.values()):.1f} s in all; the largest:")
    for fn, seconds in sorted(compiled.items(), key=lambda kv: -kv[1])[:12]:
        print(f"  {seconds:6.2f} s  {fn}")
    _compile_times()


def _cpu_seconds() -> float:
    """User and system CPU time of this process, every thread (XLA compiles on all cores it may use)."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _compile_times() -> None:
    import jax.numpy as jnp
    import jax.scipy.linalg

    from dtwin_jax.linalg import expm, mass_solve

    A, M, b = 0.1 * jnp.eye(12) + 0.01, jnp.eye(1), jnp.ones((1, 3))
    cases = [("jax.scipy.linalg.expm", lambda a: jax.scipy.linalg.expm(a), (A,)), ("dtwin_jax.linalg.expm", expm, (A,)),
             ("jnp.linalg.solve, 1 x 1", lambda m, r: jnp.linalg.solve(m, r), (M, b)),
             ("dtwin_jax.linalg.mass_solve, 1 x 1", mass_solve, (M, b))]
    print("compilation of one call site (best of 3 fresh programs):")
    for name, fn, args in cases:
        best = float("inf")
        for i in range(3):
            start = time.perf_counter()
            jax.jit(lambda *a, i=i: fn(*a) * (1.0 + i)).lower(*args).compile()
            best = min(best, time.perf_counter() - start)
        print(f"  {best:6.3f} s  {name}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description="Where a cold output-only update's time goes.")
    parser.add_argument("example", nargs="?", default="example1", choices=sorted(systems.EXAMPLES))
    parser.add_argument("--records", type=int, default=100)
    parser.add_argument("--default-settings", action="store_true")
    parser.add_argument("--library", help="drift library spec (default: the example's, without inputs)")
    args = parser.parse_args()
    main(args.example, records=args.records, default_settings=args.default_settings, library=args.library)
