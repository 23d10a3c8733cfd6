"""Side-by-side timings of the package's Gibbs kernel and its baselines (issue 10).

    taskset -c 1 python benchmarks/run.py [--quick] [--out benchmarks/results]

Writes ``results.md`` (markdown tables) and ``results.json`` (the same numbers) into ``--out``
and prints the markdown. Sections:

* the machine (CPU model, cores, jax version, device);
* the package's Gibbs kernel (``sampler.sample_jit``, one chain) for K in {8, 36, 100, 256} x
  N in {1e3, 1e4, 1e5}: compilation, sufficient statistics, sweeps per second, seconds per
  5000-draw chain, ESS per second;
* the paper's Algorithm 1 as written, in NumPy (benchmarks/algorithm1_numpy.py), at N = 1e3;
* NumPyro's DiscreteHMCGibbs(NUTS) on the same model (benchmarks/numpyro_model.py), K = 8 and
  36, N = 1e3;
* pysindy's SBR optimizer (a regularised-horseshoe NUTS regression) when pysindy is installed;
* ratios against Algorithm 1;
* end-to-end updates of example 1 (input-output, output-only with 300 records, and the
  command line from the shell) cold and warm, and the 14-level noise sweep.

Every problem is ``algorithm1_numpy.make_problem(K, N)``: standard-normal columns, three true
terms, noise 0.1. ``--quick`` runs fewer draws (per-chain times are then extrapolated to 5000
draws, which the kernel's cost per sweep allows: it does not change along a chain) and
Algorithm 1 at K = 8 and 36 only. Run it pinned to one core (``taskset -c 1``): XLA's CPU
thread pool and a second process slow each other down.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

# OpenBLAS starts a thread per core of the machine, not per core this process may use: under
# taskset -c 1 two threads share one core and Algorithm 1's sweeps ran 0-10% slower (K = 8-100,
# N = 1e3). Set before NumPy loads.
if hasattr(os, "sched_getaffinity"):
    os.environ.setdefault("OPENBLAS_NUM_THREADS", str(len(os.sched_getaffinity(0))))

import arviz as az  # noqa: E402
import jax  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import algorithm1_numpy  # noqa: E402
import numpyro_model  # noqa: E402

from dtwin_jax import sampler as S  # noqa: E402

KS = (8, 36, 100, 256)
NS = (1_000, 10_000, 100_000)
CHAIN = 5000  # draws per chain that the tables quote
COMPARE_N = 1_000  # the N at which the baselines run


@dataclass
class Section:
    """One table: ``rows`` are dicts with the same keys (the columns), ``notes`` free text."""

    title: str
    rows: list[dict] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def markdown(self) -> str:
        lines = [f"## {self.title}", ""]
        if self.rows:
            columns = list(self.rows[0])
            lines += ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
            lines += ["| " + " | ".join(_fmt(row[c]) for c in columns) + " |" for row in self.rows]
            lines.append("")
        lines += [f"- {note}" for note in self.notes]
        return "\n".join(lines).rstrip() + "\n"


def _fmt(value) -> str:
    if value is None:
        return "-"
    return f"{value:.3g}" if isinstance(value, float) else str(value)


def _progress(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


# --- the machine -----------------------------------------------------------------------------


def machine() -> dict:
    """CPU model, cores, library versions and the JAX device."""
    import numpyro

    model = platform.processor() or "unknown"
    try:
        with open("/proc/cpuinfo") as f:
            model = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), model)
    except OSError:
        pass
    return {
        "cpu": model,
        "cores": os.cpu_count(),
        "cores_usable": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "device": str(jax.devices()[0]),
        "platform": jax.default_backend(),
        "jax": jax.__version__,
        "numpy": np.__version__,
        "numpyro": numpyro.__version__,
        "python": platform.python_version(),
    }


def machine_section(info: dict) -> Section:
    return Section("Machine", [{"item": k, "value": v} for k, v in info.items()])


# --- effective sample size -----------------------------------------------------------------


def min_ess(theta: np.ndarray, sigma2: np.ndarray) -> float:
    """Smallest bulk ESS among the three true coefficients ``theta (C, D, K)[..., :3]`` and
    ``sigma2 (C, D)``: the quantities every benchmark problem estimates."""
    support = min(3, theta.shape[-1])
    ess = [np.asarray(az.ess(theta[..., k])) for k in range(support)]
    return float(np.min(ess + [np.asarray(az.ess(sigma2))]))


# --- the package's Gibbs kernel --------------------------------------------------------------


def _compile_gibbs(K: int, draws: int):
    """The one-chain ``sample_jit`` program for K terms (its shapes do not depend on N) and
    the seconds its compilation took."""
    L, y = algorithm1_numpy.make_problem(K, 10)
    start = time.perf_counter()
    compiled = S.sample_jit.lower(
        jax.random.key(0), S.suff_stats(L, y), num_draws=draws, num_burnin=0, num_chains=1
    ).compile()
    return compiled, time.perf_counter() - start


def gibbs_row(compiled, compile_s: float, K: int, N: int, draws: int) -> dict:
    """Time one ``draws``-sweep chain of the compiled kernel on the (K, N) problem."""
    L, y = algorithm1_numpy.make_problem(K, N)
    start = time.perf_counter()
    stats = jax.block_until_ready(S.suff_stats(L, y))
    stats_s = time.perf_counter() - start
    start = time.perf_counter()
    trace = jax.block_until_ready(compiled(jax.random.key(1), stats))
    run_s = time.perf_counter() - start
    ess = min_ess(np.asarray(trace.theta), np.asarray(trace.sigma2))
    return {
        "K": K,
        "N": N,
        "compile s": compile_s,
        "suff. stats s": stats_s,
        "sweeps/s": draws / run_s,
        f"s per {CHAIN}-draw chain": CHAIN * run_s / draws,
        "min ESS per 1000 draws": 1000 * ess / draws,
        "ESS/s": ess / run_s,
    }


def gibbs_section(quick: bool) -> Section:
    draws = 1000 if quick else CHAIN
    rows = []
    for K in KS:
        compiled, compile_s = _compile_gibbs(K, draws)
        for N in NS:
            _progress(f"Gibbs kernel K={K} N={N}")
            rows.append(gibbs_row(compiled, compile_s, K, N, draws))
    notes = [
        f"`sample_jit`, one chain, {draws} draws after no burn-in, greedy start; compiled once per K "
        "(`jit(...).lower(...).compile()`, not counted in the run times).",
        "A sweep works from L^T L and L^T y: its cost does not depend on N; 'suff. stats s' is the "
        "one O(N K^2) pass over the data.",
        "min ESS: smallest bulk ESS (arviz) of the three true coefficients and sigma2.",
    ]
    if quick:
        notes.append(f"--quick: per-chain times extrapolated from {draws} draws.")
    return Section("Gibbs kernel (dtwin_jax.sampler)", rows, notes)


# --- Algorithm 1 as written --------------------------------------------------------------------


def algorithm1_section(quick: bool) -> Section:
    Ks = KS[:2] if quick else KS
    sweeps = 2 if quick else 4
    rows = []
    for K in Ks:
        _progress(f"Algorithm 1 K={K} N={COMPARE_N}")
        per_sweep = algorithm1_numpy.time_per_sweep(K, COMPARE_N, sweeps)
        rows.append({
            "K": K,
            "N": COMPARE_N,
            "s per sweep": per_sweep,
            "sweeps/s": 1.0 / per_sweep,
            f"s per {CHAIN}-draw chain": CHAIN * per_sweep,
        })
    notes = [
        f"NumPy, mean of {sweeps} sweeps after one untimed sweep (the first starts from the full "
        "model); per-chain times extrapolated. glibc keeps freed memory for reuse "
        "(`reuse_freed_memory`); with its defaults every N x N matrix costs page faults and a sweep "
        "takes 4-6x longer.",
        "Each sweep forms 2K N x N matrices (Eq. 29b for both values of every indicator): "
        "O(K N^2) time and 8 N^2 bytes per matrix, so N = 1e4 (800 MB per matrix, 2K of them per "
        "sweep) and N = 1e5 (80 GB) are not run; the cost grows as N^2.",
    ]
    return Section("Algorithm 1 as written (benchmarks/algorithm1_numpy.py)", rows, notes)


# --- NumPyro -------------------------------------------------------------------------------


def numpyro_row(K: int, N: int, warmup: int, samples: int) -> dict:
    """Two runs of one DiscreteHMCGibbs chain: the first compiles, the second is timed."""
    L, y = algorithm1_numpy.make_problem(K, N)
    mcmc = numpyro_model.make_mcmc(warmup, samples, num_chains=1)
    start = time.perf_counter()
    numpyro_model.run_mcmc(mcmc, jax.random.key(0), L, y)
    cold_s = time.perf_counter() - start
    start = time.perf_counter()
    draws = numpyro_model.run_mcmc(mcmc, jax.random.key(1), L, y)
    warm_s = time.perf_counter() - start
    per_iteration = warm_s / (warmup + samples)
    ess = min_ess(draws["theta"], draws["sigma2"])
    return {
        "K": K,
        "N": N,
        "compile s": cold_s - warm_s,
        "ms per iteration": 1e3 * per_iteration,
        f"s per {CHAIN}-draw chain": CHAIN * per_iteration,
        "min ESS per 1000 draws": 1000 * ess / samples,
        "ESS/s": ess / (per_iteration * samples),
    }


def numpyro_section(quick: bool) -> Section:
    warmup, samples = (200, 300) if quick else (500, 2000)
    rows = []
    for K in KS[:2]:
        _progress(f"NumPyro K={K} N={COMPARE_N}")
        rows.append(numpyro_row(K, COMPARE_N, warmup, samples))
    notes = [
        f"DiscreteHMCGibbs(NUTS), non-centred, dense mass, one chain, {warmup} warmup + {samples} "
        "draws; 'compile s' is the first run's time less the second's (same shapes, cached); the "
        "first row's also holds one-time tracing that later rows reuse.",
        "An iteration is one Metropolised-Gibbs pass over the K indicators plus one NUTS step; "
        "warmup iterations count in 'ms per iteration'; ESS/s uses the draws' share of the run time.",
    ]
    return Section("NumPyro DiscreteHMCGibbs (benchmarks/numpyro_model.py)", rows, notes)


# --- pysindy ---------------------------------------------------------------------------------


def pysindy_section(quick: bool) -> Section:
    title = "pysindy SBR (regularised horseshoe, NUTS)"
    try:
        from pysindy.optimizers import SBR
    except ImportError as err:
        return Section(title, notes=[f"skipped: pysindy's SBR optimizer cannot be imported ({err})."])
    warmup, samples = (200, 300) if quick else (500, 2000)
    rows = []
    for K in KS[:2]:
        _progress(f"pysindy SBR K={K} N={COMPARE_N}")
        L, y = algorithm1_numpy.make_problem(K, COMPARE_N)
        start = time.perf_counter()
        SBR(num_warmup=warmup, num_samples=samples, mcmc_kwargs={"progress_bar": False}).fit(L, y[:, None])
        fit_s = time.perf_counter() - start
        rows.append({"K": K, "N": COMPARE_N, "s per fit incl. compile": fit_s,
                     "ms per iteration incl. compile": 1e3 * fit_s / (warmup + samples)})
    notes = [f"`SBR(num_warmup={warmup}, num_samples={samples}).fit`: a different prior (no indicators), "
             "timed for scale only; every fit builds a new model, so compilation is included."]
    return Section(title, rows, notes)


# --- ratios ----------------------------------------------------------------------------------


def _by_key(section: Section) -> dict:
    return {(row["K"], row["N"]): row for row in section.rows}


def ratio_section(gibbs: Section, alg1: Section, nuts: Section) -> Section:
    """Algorithm 1's time per sweep over the kernel's and over NumPyro's time per iteration,
    and the kernel's ESS/s over NumPyro's, at the (K, N) where the baselines ran."""
    g, n = _by_key(gibbs), _by_key(nuts)
    chain = f"s per {CHAIN}-draw chain"
    rows = []
    for key, a in _by_key(alg1).items():
        row = {"K": key[0], "N": key[1], "Algorithm 1 / Gibbs kernel (per sweep)": a[chain] / g[key][chain]}
        # None (shown as -) where NumPyro did not run.
        row["Algorithm 1 / NumPyro (per iteration)"] = a[chain] / n[key][chain] if key in n else None
        row["Gibbs ESS/s / NumPyro ESS/s"] = g[key]["ESS/s"] / n[key]["ESS/s"] if key in n else None
        rows.append(row)
    notes = ["Algorithm 1 and the kernel are both Gibbs samplers with theta and sigma2 integrated "
             "out of the indicator updates, and mix alike (min ESS per 1000 draws at K = 8, N = 1e3: "
             "964 for 1000 sweeps of Algorithm 1, 733-743 for the kernel), so time per sweep compares them."]
    return Section("Speed-ups against Algorithm 1", rows, notes)


# --- hooks for the end-to-end timings ---------------------------------------------------------


def _timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def full_update_section(quick: bool) -> Section:
    """End-to-end updates of example 1, each run twice in this process (cold: with tracing
    and compilation; warm: the programs cached), and the command line from the shell (a new
    process each time) with its persistent compilation cache filled by a first run."""
    import subprocess
    import tempfile

    from dtwin_jax import SamplerSettings, update_input_output, update_output_only
    from dtwin_jax.io import write_nominal
    from dtwin_jax.library import parse_library
    from dtwin_jax.models import systems
    from dtwin_jax.preprocess.measurement import add_noise, measure

    rows = []
    ex = systems.example1()
    sim = systems.simulate_example(ex, jax.random.key(0))
    meas = measure(jax.random.key(1), sim["t"], sim["x"], sim["xdot"], sim["u"], level=0.05)
    io_run = lambda: update_input_output(ex.system.nominal, meas.t, meas.x, meas.u, meas.xdot, library=ex.library,
                                         settings=SamplerSettings(num_chains=4, num_draws=2000, num_burnin=1000))
    rows.append({"update": "input-output, 1 s at 1 kHz, K = 31, 4 x 2000 draws",
                 "cold s": _timed(io_run), "warm s": _timed(io_run)})
    records = 100 if quick else 300
    oo = ex.for_output_only()
    sde = systems.simulate_example_sde(oo, jax.random.key(0), num_records=records)
    x = np.asarray(add_noise(jax.random.key(1), sde["x"], 0.05))
    oo_run = lambda: update_output_only(oo.system.nominal, sde["t"], x, library=oo.library_output_only)
    K = parse_library(oo.library_output_only, 2, 0).K
    rows.append({"update": f"output-only, {records} x 1 s, K = {K}, 4 x 2000 draws",
                 "cold s": _timed(oo_run), "warm s": _timed(oo_run)})
    with tempfile.TemporaryDirectory() as tmp:
        np.savez(f"{tmp}/m.npz", t=meas.t, x=meas.x, u=meas.u, xdot=meas.xdot)
        write_nominal(f"{tmp}/nominal.toml", ex.system.nominal)
        env = dict(os.environ, DTWIN_JAX_CACHE=f"{tmp}/cache")
        cmd = [sys.executable, "-m", "dtwin_jax.cli", "discover", f"{tmp}/m.npz", "--nominal", f"{tmp}/nominal.toml",
               "--library", ex.library, "--quiet"]
        shell = lambda: subprocess.run(cmd, env=env, check=True, capture_output=True)
        rows.append({"update": "dtwin-jax discover (same window, new process; warm: compilation cache filled)",
                     "cold s": _timed(shell), "warm s": _timed(shell)})
        np.savez(f"{tmp}/oo.npz", t=sde["t"], x=x)
        write_nominal(f"{tmp}/nominal_oo.toml", oo.system.nominal)
        cmd_oo = [sys.executable, "-m", "dtwin_jax.cli", "discover", f"{tmp}/oo.npz", "--nominal",
                  f"{tmp}/nominal_oo.toml", "--library", oo.library_output_only, "--quiet"]
        shell_oo = lambda: subprocess.run(cmd_oo, env=env, check=True, capture_output=True)
        rows.append({"update": f"dtwin-jax discover, output-only {records} x 1 s (new process; warm: caches filled)",
                     "cold s": _timed(shell_oo), "warm s": _timed(shell_oo)})
    return Section("Full updates (example 1, 5% noise)", rows,
                   ["cold: the first update in a process (tracing and XLA compilation); warm: the same "
                    "update again (a new window of the same shape costs the same)."])


def sweep_section(quick: bool) -> Section:
    """Fig. 10's noise sweep (input-output, example 1): one level against 14 levels, each a
    fresh compiled program, and the 14 levels again with the program cached."""
    from dtwin_jax import studies
    from dtwin_jax.update import SamplerSettings

    settings = SamplerSettings(num_chains=2, num_draws=500, num_burnin=250) if quick else SamplerSettings()
    replicates = 1 if quick else 4
    levels = np.linspace(0.0, 0.6, 14)
    sweep = lambda lv: studies.noise_sweep("example1", lv, replicates=replicates, framework="input-output",
                                           settings=settings, progress=False)
    rows = [{"levels": 1, "s": _timed(lambda: sweep(levels[[1]]))},
            {"levels": 14, "s": _timed(lambda: sweep(levels))},
            {"levels": "14 (cached program)", "s": _timed(lambda: sweep(levels))}]
    return Section(f"Noise sweep (example 1, input-output, {replicates} replicates, {settings.num_chains} x "
                   f"{settings.num_draws} draws)", rows, ["one compiled program per shape: levels x replicates x chains vmapped"])


# --- main ------------------------------------------------------------------------------------


def run(quick: bool) -> tuple[dict, list[Section]]:
    info = machine()
    gibbs = gibbs_section(quick)
    alg1 = algorithm1_section(quick)
    nuts = numpyro_section(quick)
    sections = [machine_section(info), gibbs, alg1, nuts, pysindy_section(quick), ratio_section(gibbs, alg1, nuts)]
    sections += [full_update_section(quick), sweep_section(quick)]
    return info, sections


def write(out: Path, quick: bool, info: dict, sections: list[Section]) -> str:
    """Write results.md and results.json into ``out``; return the markdown."""
    out.mkdir(parents=True, exist_ok=True)
    mode = "--quick" if quick else "full"
    md = f"# Sampler benchmarks ({mode})\n\n" + "\n".join(s.markdown() for s in sections)
    (out / "results.md").write_text(md)
    payload = {"quick": quick, "machine": info, "sections": [asdict(s) for s in sections]}
    (out / "results.json").write_text(json.dumps(payload, indent=1))
    return md


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer draws and sizes (a few minutes)")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    info, sections = run(args.quick)
    print(write(args.out, args.quick, info, sections))
    print(f"total {time.perf_counter() - start:.0f} s; written to {args.out}/results.md and results.json")


if __name__ == "__main__":
    main()
