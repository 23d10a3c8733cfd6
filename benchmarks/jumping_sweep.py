"""The indicator sweep that jumps between flips, against another checkout's sampler.

    taskset -c 1 python benchmarks/jumping_sweep.py [--baseline PATH]

For this checkout's package (and, with ``--baseline``, the ``dtwin_jax`` of another checkout
at PATH, e.g. ``git worktree add /tmp/old d32c4da``, the last commit with the one-at-a-time
sweep), each in a fresh process: compilation and best-of-5 time of a one-chain, 5000-draw
``sample_jit`` chain at K = 8, 36, 100, 256 (benchmarks/algorithm1_numpy.py's problem,
N = 1000); the same on two collinear problems built to flip many indicators per sweep; and
the warm input-output update of example 2 (K = 258, two equations, 2 x 1000 draws after 500)
with the flips per sweep of its chains. Both sweeps give the same draws, so the flips agree.
"""

import os
import subprocess
import sys
from pathlib import Path

CHILD = r"""
import sys, time
sys.path.insert(0, sys.argv[1])
import jax, numpy as np
import algorithm1_numpy
import dtwin_jax
from dtwin_jax import sampler as S, systems, update_input_output
from dtwin_jax.measurement import measure
from dtwin_jax.update import SamplerSettings

def chain(L, y):
    st = S.suff_stats(L, y)
    start = time.perf_counter()
    c = S.sample_jit.lower(jax.random.key(0), st, num_draws=5000, num_burnin=0, num_chains=1).compile()
    compile_s = time.perf_counter() - start
    best = float("inf")
    for r in range(5):
        start = time.perf_counter(); trace = jax.block_until_ready(c(jax.random.key(r + 1), st))
        best = min(best, time.perf_counter() - start)
    g = np.asarray(trace.gamma)[0].astype(int)
    return compile_s, best, np.abs(np.diff(g, axis=0)).sum(1).mean()

print("package", dtwin_jax.__file__)
for K in (8, 36, 100, 256):
    print("chain", K, *chain(*algorithm1_numpy.make_problem(K, 1000)))
for K, N, noise in ((36, 60, 1.0), (100, 120, 2.0)):
    rng = np.random.default_rng(0)
    L = rng.normal(size=(N, 3)) @ rng.normal(size=(3, K)) + 0.3 * rng.normal(size=(N, K))
    y = L[:, :3] @ np.array([1.0, -1.0, 0.5]) + noise * rng.normal(size=N)
    print("collinear", f"{K}x{N}", *chain(L, y))
ex = systems.example2()
sim = systems.simulate_example(ex, jax.random.key(0))
meas = measure(jax.random.key(1), sim["t"], sim["x"], sim["xdot"], sim["u"], level=0.05)
settings = SamplerSettings(num_chains=2, num_draws=1000, num_burnin=500)
run = lambda: update_input_output(ex.system.nominal, meas.t, meas.x, meas.u, meas.xdot, library=ex.library, settings=settings)
run()
start = time.perf_counter(); res = run(); warm = time.perf_counter() - start
flips = [float(np.abs(np.diff(np.asarray(e.gamma).astype(int), axis=1)).sum(-1).mean()) for e in res.equations]
print("example2", warm, *flips)
"""


def measure(package: str) -> dict:
    here = Path(__file__).resolve().parent
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([package, str(here)])}
    out = subprocess.run([sys.executable, "-c", CHILD, package], capture_output=True, text=True, env=env, check=True)
    rows = {}
    for line in out.stdout.splitlines():
        key, *values = line.split()
        rows.setdefault(key, []).append(values)
    return rows


def main(argv: list[str]) -> None:
    packages = {"this checkout": str(Path(__file__).resolve().parent.parent)}
    if "--baseline" in argv:
        packages["baseline"] = argv[argv.index("--baseline") + 1]
    results = {name: measure(path) for name, path in packages.items()}
    for name, rows in results.items():
        print(f"\n{name}: {rows['package'][0][0]}\n")
        print("| problem | compile s | s per 5000-draw chain | flips per sweep |\n|---|---|---|---|")
        for kind in ("chain", "collinear"):
            for label, compile_s, run_s, flips in rows[kind]:
                problem = f"K = {label}" if kind == "chain" else f"collinear K x N = {label}"
                compiled = f"{float(compile_s):.2f}" if kind == "chain" else "(K = 36 / 100's)"
                print(f"| {problem} | {compiled} | {float(run_s):.4f} | {float(flips):.2f} |")
        warm, *flips = rows["example2"][0]
        print(f"\nexample 2 input-output update, warm: {float(warm):.2f} s; flips per sweep by equation: "
              + ", ".join(f"{float(f):.2f}" for f in flips))


if __name__ == "__main__":
    main(sys.argv[1:])
