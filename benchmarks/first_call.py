"""First calls from the shell, as ratios to the import floor of jax + diffrax + equinox.

    taskset -c 0 python benchmarks/first_call.py [--repeats 3] [--out benchmarks/results]

Each measurement is a fresh process: `dtwin-jax discover` on example 1 (1 s at 1 kHz, 5%
noise on every signal, `t,x1,x2,u1` without rates, the default library and route) with the
persistent caches (`DTWIN_JAX_CACHE`) in a new temporary folder:

- cold: the caches empty;
- warm: the same command again;
- new library: a library not run before (`poly:2,sign,input`), the caches filled by the runs above.

The floor is `python -c "import jax, diffrax, equinox"`. Medians of `--repeats` runs (cold:
each in its own empty folder). Writes `first_call-<host>.md` into `--out`.
"""

import argparse
import os
import statistics
import sys
import tempfile
from pathlib import Path

from shell_timing import example1_files, report, timed


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", default="benchmarks/results")
    a = p.parse_args()
    exe = str(Path(sys.executable).with_name("dtwin-jax"))
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        data = example1_files(tmp)

        def discover(cache, library=None):
            env = {**os.environ, "DTWIN_JAX_CACHE": str(cache)}
            cmd = [exe, "discover", str(data), "--nominal", str(tmp / "nominal.toml"), "--quiet",
                   "--out", str(tmp / "r.json")] + (["--library", library] if library else [])
            return timed(cmd, env)

        floor = statistics.median(timed([sys.executable, "-c", "import jax, diffrax, equinox"], dict(os.environ))
                                  for _ in range(a.repeats))
        cold, warm, new = [], [], []
        for r in range(a.repeats):
            cache = tmp / f"cache{r}"
            cold.append(discover(cache))
            warm.append(discover(cache))
            new.append(discover(cache, "poly:2,sign,input"))
    rows = [("import floor (jax, diffrax, equinox)", floor), ("cold: caches empty", statistics.median(cold)),
            ("a library not run before, caches filled", statistics.median(new)),
            ("warm: the same command again", statistics.median(warm))]
    print(report(a.out, "first_call", "First calls from the shell",
                 f"`python benchmarks/first_call.py --repeats {a.repeats}`: `dtwin-jax discover` on example 1 "
                 "(1 s, 5% noise, `t,x1,x2,u1`, default library and route); medians.",
                 ["call", "seconds", "ratio to the floor"], [(n, s, f"{s / floor:.1f}x") for n, s in rows]))

if __name__ == "__main__":
    main()
