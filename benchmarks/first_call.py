"""First calls from the shell, as ratios to the import floor of jax + diffrax + equinox.

    taskset -c 0 python benchmarks/first_call.py [--repeats 3] [--out benchmarks/results] [--baseline DIR]

Each measurement is a fresh process: `dtwin-jax discover` on example 1 (1 s at 1 kHz, 5%
noise on every signal, `t,x1,x2,u1` without rates, the default library and route) with the
persistent caches (`DTWIN_JAX_CACHE`) in a new temporary folder:

- cold: the caches empty;
- warm: the same command again;
- a new library of a size class compiled before: `poly:6,sign,abs,input` (33 terms, padded to
  64 columns as the default library's 46 are), the caches filled by the runs above;
- a new library of a new size class: `poly:2,sign,input` (9 terms, class 16), after those.

The floor is `python -c "import jax, diffrax, equinox"`. Medians of `--repeats` runs (cold:
each in its own empty folder). Writes `first_call-<host>.md` into `--out`.

`--baseline DIR`: also the same calls with another checkout's package (`PYTHONPATH=DIR`, for
example a `git worktree` of an earlier commit), each run right after this checkout's in
its own cache folders, so that both see the same load: a column each, and their ratio.
"""

import argparse
import os
import statistics
import sys
import tempfile
from pathlib import Path

from shell_timing import example1_files, report, timed


# In the order they run: each after the ones above it, in the same cache folder.
STEPS = (("cold", None), ("warm", None), ("same", "poly:6,sign,abs,input"), ("new", "poly:2,sign,input"))


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", default="benchmarks/results")
    p.add_argument("--baseline", default=None, help="another checkout's root, run interleaved (PYTHONPATH)")
    a = p.parse_args()
    exe = str(Path(sys.executable).with_name("dtwin-jax"))
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        data = example1_files(tmp)

        def discover(cache, library=None, path=None):
            env = {**os.environ, "DTWIN_JAX_CACHE": str(cache), **({"PYTHONPATH": path} if path else {})}
            cmd = [exe, "discover", str(data), "--nominal", str(tmp / "nominal.toml"), "--quiet",
                   "--out", str(tmp / "r.json")] + (["--library", library] if library else [])
            return timed(cmd, env)

        floor = statistics.median(timed([sys.executable, "-c", "import jax, diffrax, equinox"], dict(os.environ))
                                  for _ in range(a.repeats))
        paths = [None] + ([a.baseline] if a.baseline else [])
        times = {path: {step: [] for step, _ in STEPS} for path in paths}
        for r in range(a.repeats):
            for step, library in STEPS:
                for i, path in enumerate(paths):
                    times[path][step].append(discover(tmp / f"cache{r}-{i}", library, path))
    names = {"cold": "cold: caches empty", "warm": "warm: the same command again",
             "same": "a new library, its size class compiled before (`poly:6,sign,abs,input`)",
             "new": "a new library of a new size class (`poly:2,sign,input`)"}
    order = ("cold", "same", "new", "warm")
    med = {path: {k: statistics.median(v) for k, v in t.items()} for path, t in times.items()}
    rows = [("import floor (jax, diffrax, equinox)", floor, "1.0x")]
    rows += [(names[k], med[None][k], f"{med[None][k] / floor:.1f}x") for k in order]
    columns = ["call", "seconds", "ratio to the floor"]
    if a.baseline:
        columns += ["baseline seconds", "this / baseline"]
        rows = [rows[0] + ("", "")] + [row + (med[a.baseline][k], f"{row[1] / med[a.baseline][k]:.2f}")
                                       for row, k in zip(rows[1:], order)]
    print(report(a.out, "first_call", "First calls from the shell",
                 f"`python benchmarks/first_call.py --repeats {a.repeats}"
                 + (" --baseline DIR" if a.baseline else "") + "`: `dtwin-jax discover` on example 1 "
                 "(1 s, 5% noise, `t,x1,x2,u1`, default library and route); medians"
                 + (" (the baseline: another checkout, each call right after this one's)." if a.baseline else "."),
                 columns, rows))

if __name__ == "__main__":
    main()
