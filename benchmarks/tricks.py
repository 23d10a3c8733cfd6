"""Does each compile-speed trick (dtwin_jax/_compile) beat plain `jit` with the persistent cache?

    taskset -c 0 python benchmarks/tricks.py [--repeats 1] [--out benchmarks/results]

`dtwin-jax discover` from the shell, each call a fresh process with its own cache folder,
cold (caches empty) then warm (the same command again), with every trick on and with one
turned off:

- exports: `dtwin_jax._compile.aot` (traced programs kept on disk for new processes);
- quick: `dtwin_jax._compile.quick_compile` (short-running programs compiled without
  LLVM's optimizations);
- level 2: `quick_compile.prefer_level_2` (the other programs at LLVM's level 2, not 3),
  turned off by naming XLA's default level in `XLA_FLAGS`.

Two commands: input-output on example 1 (1 s at 1 kHz, 5% noise, `t,x1,x2,u1`) and
output-only on example 1's ensemble (20 records of 1 s, 5% noise, `.npz`). Writes
`tricks-<host>.md` into `--out`.
"""

import argparse
import os
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np
from shell_timing import example1_files, report, timed

# Each variant's launcher turns one trick off before the command runs.
OFF = {
    "all on": "",
    "exports off": "from dtwin_jax._compile import aot; aot.enable = lambda folder: None",
    "quick off": "from dtwin_jax._compile import quick_compile; quick_compile.QUICK_COMPILE.clear()",
    "level 2 off": "import os; os.environ['XLA_FLAGS'] = os.environ.get('XLA_FLAGS', '') + ' --xla_backend_optimization_level=3'",
}


def _data(folder: Path) -> tuple[Path, Path]:
    import jax

    from dtwin_jax.models import systems
    from dtwin_jax.preprocess.measurement import add_noise

    io = example1_files(folder)
    oo_ex = systems.example1().for_output_only()
    sde = systems.simulate_example_sde(oo_ex, jax.random.key(0), num_records=20)
    oo = folder / "oo.npz"
    np.savez(oo, t=np.asarray(sde["t"]), x=np.asarray(add_noise(jax.random.key(1), sde["x"], 0.05)))
    return io, oo


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--repeats", type=int, default=1)
    p.add_argument("--out", default="benchmarks/results")
    a = p.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        io, oo = _data(tmp)
        for label, data in (("io", io), ("oo", oo)):
            for variant, off in OFF.items():
                launch = f"{off}\nfrom dtwin_jax.cli import console_main; raise SystemExit(console_main())"
                cold, warm = [], []
                for r in range(a.repeats):
                    cache = tmp / f"cache-{label}-{variant.replace(' ', '')}-{r}"
                    env = {**os.environ, "DTWIN_JAX_CACHE": str(cache)}
                    cmd = [sys.executable, "-c", launch, "discover", str(data), "--nominal", str(tmp / "nominal.toml"),
                           "--quiet", "--out", str(tmp / "r.json")]
                    cold.append(timed(cmd, env))
                    warm.append(timed(cmd, env))
                rows.append((label, variant, statistics.median(cold), statistics.median(warm)))
                print(rows[-1], flush=True)
    print(report(a.out, "tricks", "Compile-speed tricks against plain `jit` with the persistent cache",
                 f"`python benchmarks/tricks.py --repeats {a.repeats}`: `dtwin-jax discover`, a fresh process per "
                 "call; io = example 1 input-output (1 s), oo = example 1 output-only (20 records x 1 s); medians.",
                 ["data", "variant", "cold (s)", "warm (s)"], rows))

if __name__ == "__main__":
    main()
