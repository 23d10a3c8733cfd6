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
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

NOMINAL = "M = [[1.0]]\nC = [[2.0]]\nK = [[1000.0]]\nB = [[1.0]]\n"


def _timed(cmd, env) -> float:
    start = time.perf_counter()
    subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - start


def _data(folder: Path) -> Path:
    import jax

    from dtwin_jax import measure
    from dtwin_jax.models import systems

    ex = systems.example1()
    sim = systems.simulate_example(ex, jax.random.key(0))
    meas = measure(jax.random.key(1), sim["t"], sim["x"], sim["xdot"], sim["u"], level=0.05)
    rows = np.column_stack([np.asarray(meas.t), np.asarray(meas.x), np.asarray(meas.u)])
    path = folder / "data.csv"
    path.write_text("t,x1,x2,u1\n" + "\n".join(",".join(f"{v:.10g}" for v in r) for r in rows) + "\n")
    (folder / "nominal.toml").write_text(NOMINAL)
    return path


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", default="benchmarks/results")
    a = p.parse_args()
    exe = str(Path(sys.executable).with_name("dtwin-jax"))
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        data = _data(tmp)

        def discover(cache, library=None):
            env = {**os.environ, "DTWIN_JAX_CACHE": str(cache)}
            cmd = [exe, "discover", str(data), "--nominal", str(tmp / "nominal.toml"), "--quiet",
                   "--out", str(tmp / "r.json")] + (["--library", library] if library else [])
            return _timed(cmd, env)

        floor = statistics.median(_timed([sys.executable, "-c", "import jax, diffrax, equinox"], dict(os.environ))
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
    host = platform.node() or "host"
    text = (f"# First calls from the shell ({host}, {os.cpu_count()} cores, "
            f"{'pinned' if len(os.sched_getaffinity(0)) == 1 else 'unpinned'})\n\n"
            f"`python benchmarks/first_call.py --repeats {a.repeats}`: `dtwin-jax discover` on example 1 "
            "(1 s, 5% noise, `t,x1,x2,u1`, default library and route); medians.\n\n"
            "| call | seconds | ratio to the floor |\n|---|---|---|\n"
            + "".join(f"| {name} | {s:.2f} | {s / floor:.1f}x |\n" for name, s in rows))
    print(text)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"first_call-{host}.md").write_text(text)


if __name__ == "__main__":
    main()
