"""Many chains and many noise levels in one call: the same benchmark on a CPU or an accelerator.

    python benchmarks/accelerator.py [--quick] [--out DIR] [--budget-s S] [--sections ...]

Runs on whatever device jax picks (``JAX_PLATFORMS=cpu`` forces the CPU) and writes
``accelerator-<platform>.md`` / ``.json`` into ``--out``. Sections (``--sections``, in the
order given; default ``chains agreement sweep``):

* ``chains``: one K-term problem (``algorithm1_numpy.make_problem(K, 1000)``), ``C`` chains
  of 5000 draws in one compiled call (``sampler.sample``, the device's default chain method:
  vectorized on accelerators, sequential on CPU). Compilation timed apart; the run is the
  best of two calls (one call from 8192 chains up); only per-chain PIPs and means leave the
  device (a 4096-chain trace is 6 GB). Each row checks the answer: the pooled PIPs of the
  three true terms and the largest PIP of the others.
* ``agreement`` (accelerators only): the same 4-chain call on the accelerator and on the host
  CPU backend; the largest differences of PIPs and posterior means (the backends round
  differently, so a chain may flip once differently and then wander apart).
* ``sweep``: :func:`dtwin_jax.studies.noise_sweep`, example 1, input-output, 14 levels x
  ``R`` replicates x 4 chains x 2000 draws (+1000 burn-in), one compiled program; first call
  (with compilation) and second call (cached), and the support recovery at 0 and 60% noise.
* ``updates``: example 1 at 5% noise, input-output (1 s) and output-only (300 x 1 s), each
  updated twice in the process (cold, warm).
* ``output-only-sweep``: framework 2's sweep, 14 levels x 4 replicates x 100 records, drift
  and diffusion, every (level, replicate) pair's statistics vmapped at once; one call.

``--budget-s``: stop starting new rows once this many seconds have passed (rows already
written stay), so the run fits a lease of device time. On a GPU machine without arviz-stats
(the updates' diagnostics need it), carry its wheels (arviz-stats, arviz-base,
xarray-einstats, xarray) and put them on ``PYTHONPATH``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import algorithm1_numpy  # noqa: E402

from dtwin_jax import sampler as S  # noqa: E402

DRAWS = 5000
N = 1000


def _chains_program(num_chains: int, draws: int, platform: str | None = None):
    """jit of: ``C`` chains on one problem -> per-chain PIPs and means ``(C, K)``, sigma2 ``(C,)``.
    It runs where its arguments are committed (``jax.device_put``)."""
    method = "sequential" if (platform or jax.default_backend()) == "cpu" else "vectorized"

    def run(key, stats):
        tr = S.sample(key, stats, num_draws=draws, num_burnin=0, num_chains=num_chains, chain_method=method)
        return tr.gamma.mean(1), tr.theta.mean(1), tr.sigma2.mean(1)

    return jax.jit(run), method


def _timed(fn, *args):
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - start


def chains_row(K: int, C: int, draws: int) -> dict:
    L, y = algorithm1_numpy.make_problem(K, N)
    stats = S.suff_stats(L, y)
    program, method = _chains_program(C, draws)
    start = time.perf_counter()
    compiled = program.lower(jax.random.key(0), stats).compile()
    compile_s = time.perf_counter() - start
    (pip, theta, _), run_s = _timed(compiled, jax.random.key(2), stats)
    if C < 8192:  # best of two, except where one call takes tens of seconds
        run_s = min(run_s, _timed(compiled, jax.random.key(2), stats)[1])
    pip = np.asarray(pip).mean(0)
    return {
        "K": K, "chains": C, "draws": draws, "method": method,
        "compile s": compile_s,
        "run s": run_s,
        "chain-sweeps/s": C * draws / run_s,
        f"s per {DRAWS}-draw chain (amortised)": run_s / C * DRAWS / draws,
        "min true PIP": float(pip[:3].min()),
        "max other PIP": float(pip[3:].max()),
        "theta[:3] mean": [round(float(v), 4) for v in np.asarray(theta).mean(0)[:3]],
    }


def agreement_row(K: int = 36, C: int = 4, draws: int = 2000) -> dict:
    """Posterior of the same call on the default device and on the host CPU."""
    L, y = algorithm1_numpy.make_problem(K, N)
    stats = S.suff_stats(L, y)
    out = []
    for device in (jax.devices()[0], jax.devices("cpu")[0]):
        program, _ = _chains_program(C, draws, device.platform)
        pip, theta, sigma2 = program(*jax.device_put((jax.random.key(3), stats), device))
        out.append((device.platform, np.asarray(pip), np.asarray(theta), np.asarray(sigma2)))
    (a, pa, ta, sa), (b, pb, tb, sb) = out
    return {
        "K": K, "chains": C, "draws": draws, "backends": f"{a} vs {b}",
        "largest PIP difference (pooled)": float(np.abs(pa.mean(0) - pb.mean(0)).max()),
        "largest theta-mean difference (pooled)": float(np.abs(ta.mean(0) - tb.mean(0)).max()),
        "sigma2 mean": [float(sa.mean()), float(sb.mean())],
        "chains with identical PIPs": int(np.sum(np.all(pa == pb, axis=1))),
    }


def sweep_row(replicates: int, quick: bool) -> dict:
    from dtwin_jax import studies
    from dtwin_jax.update import SamplerSettings

    settings = SamplerSettings(num_chains=2, num_draws=500, num_burnin=250) if quick else SamplerSettings()
    levels = np.linspace(0.0, 0.6, 14)
    sweep = lambda: studies.noise_sweep("example1", levels, replicates=replicates, framework="input-output",  # noqa: E731
                                        settings=settings, progress=False)
    _, first = _timed(sweep)
    res, second = _timed(sweep)
    table = res.table()
    chains = levels.size * replicates * len(res.states) * settings.num_chains
    return {
        "levels": levels.size, "replicates": replicates, "chains in the call": chains,
        "draws": f"{settings.num_chains} x {settings.num_draws} (+{settings.num_burnin})",
        "first call s (compiles)": first, "second call s": second,
        "chain-sweeps/s": chains * (settings.num_draws + settings.num_burnin) / second,
        "support recovery 0% / 60%": f"{table[0]['support_recovery_pct']:.0f} / {table[-1]['support_recovery_pct']:.0f}",
    }


def update_rows(quick: bool) -> list[dict]:
    """Example 1 at 5% noise, updated twice in this process (cold: tracing and compilation;
    warm: the programs cached): input-output (1 s at 1 kHz) and output-only (300 x 1 s)."""
    from dtwin_jax import SamplerSettings, update_input_output, update_output_only
    from dtwin_jax.models import systems
    from dtwin_jax.preprocess.measurement import add_noise, measure

    settings = SamplerSettings(num_chains=2, num_draws=500, num_burnin=250) if quick else SamplerSettings()
    ex = systems.example1()
    sim = systems.simulate_example(ex, jax.random.key(0))
    meas = measure(jax.random.key(1), sim["t"], sim["x"], sim["xdot"], sim["u"], level=0.05)
    io = lambda: update_input_output(ex.system.nominal, meas.t, meas.x, meas.u, meas.xdot,  # noqa: E731
                                     library=ex.library, settings=settings)
    records = 20 if quick else 300
    oo = ex.for_output_only()
    sde = systems.simulate_example_sde(oo, jax.random.key(0), num_records=records)
    x = np.asarray(add_noise(jax.random.key(1), sde["x"], 0.05))
    oo_run = lambda: update_output_only(oo.system.nominal, sde["t"], x, library=oo.library_output_only,  # noqa: E731
                                        settings=settings)
    draws = f"{settings.num_chains} x {settings.num_draws} (+{settings.num_burnin})"
    return [{"update": name, "draws": draws, "cold s": _timed(fn)[1], "warm s": _timed(fn)[1]}
            for name, fn in [("input-output, 1 s at 1 kHz", io), (f"output-only, {records} x 1 s", oo_run)]]


def output_only_sweep_row(replicates: int, quick: bool) -> dict:
    """Framework 2's sweep, drift and diffusion, every (level, replicate) pair's statistics
    vmapped at once (``batch_size`` = all pairs); one call, compilation included."""
    from dtwin_jax import studies
    from dtwin_jax.update import SamplerSettings

    settings = SamplerSettings(num_chains=2, num_draws=500, num_burnin=250) if quick else SamplerSettings()
    levels = np.linspace(0.0, 0.6, 3 if quick else 14)
    records = 20 if quick else 100
    res, seconds = _timed(lambda: studies.noise_sweep(
        "example1", levels, replicates=replicates, framework="output-only", settings=settings, records=records,
        progress=False, batch_size=levels.size * replicates))
    table = res.table()
    return {
        "levels": levels.size, "replicates": replicates, "records": records,
        "draws": f"{settings.num_chains} x {settings.num_draws} (+{settings.num_burnin})",
        "call s (compiles)": seconds, "drift s": res.timings["drift_seconds"],
        "diffusion s": res.timings.get("diffusion_seconds", float("nan")),
        "support recovery 0% / 60%": f"{table[0]['support_recovery_pct']:.0f} / {table[-1]['support_recovery_pct']:.0f}",
    }


def markdown(title: str, rows: list[dict]) -> str:
    if not rows:
        return f"### {title}\n\n(none run)\n"
    keys = list(dict.fromkeys(k for r in rows for k in r))
    fmt = lambda v: f"{v:.4g}" if isinstance(v, float) else str(v)  # noqa: E731
    lines = [f"### {title}", "", "| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    lines += ["| " + " | ".join(fmt(r.get(k, "")) for k in keys) + " |" for r in rows]
    return "\n".join(lines) + "\n"


SECTIONS = {"chains": "Chains in one call", "agreement": "Accelerator vs CPU",
            "sweep": "Noise sweep, example 1, input-output", "updates": "Full updates, example 1, 5% noise",
            "output-only-sweep": "Noise sweep, example 1, output-only"}


def write(results: dict, out: Path) -> str:
    """``accelerator-<platform>.md`` and ``.json`` into ``out``; returns the markdown."""
    info = results["info"]
    text = f"## {info['device']} ({info['platform']}), jax {info['jax']}\n\n"
    text += "".join(f"`{cmd}`\n\n" for cmd in results.get("commands", []))
    text += "\n".join(markdown(title, results[k]) for k, title in SECTIONS.items() if results.get(k))
    text += "".join(f"\nnot run: {s}\n" for s in results["skipped"])
    out.mkdir(parents=True, exist_ok=True)
    (out / f"accelerator-{info['platform']}.md").write_text(text)
    (out / f"accelerator-{info['platform']}.json").write_text(json.dumps(results, indent=1))
    return text


def merge(paths: list[str]) -> dict:
    """One result from several runs' JSON (a lease split into calls): rows concatenated."""
    runs = [json.loads(Path(p).read_text()) for p in paths]
    merged = {"info": runs[0]["info"], "commands": [c for r in runs for c in r.get("commands", [])],
              "skipped": [s for r in runs for s in r["skipped"]]}
    for k in SECTIONS:
        merged[k] = [row for r in runs for row in r.get(k, [])]
    merged["chains"].sort(key=lambda row: (row["K"], row["chains"]))
    return merged


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="fewer chains and draws (a smoke test)")
    p.add_argument("--out", default="benchmarks/results")
    p.add_argument("--budget-s", type=float, default=float("inf"))
    p.add_argument("--chains", type=int, nargs="+", help="chain counts of the K = 36 rows")
    p.add_argument("--replicates", type=int, nargs="+", help="replicate counts of the noise sweep")
    p.add_argument("--sections", nargs="+", default=["chains", "agreement", "sweep"], choices=list(SECTIONS))
    p.add_argument("--merge", nargs="+", metavar="JSON", help="only merge these runs' results into --out")
    args = p.parse_args(argv)
    out = Path(args.out)
    if args.merge:
        print(write(merge(args.merge), out))
        return
    start = time.perf_counter()
    platform = jax.default_backend()
    accel = platform != "cpu"
    device = jax.devices()[0]
    info = {"platform": platform, "device": getattr(device, "device_kind", str(device)), "jax": jax.__version__,
            "float64": bool(jax.config.jax_enable_x64)}
    print(info, flush=True)
    draws = 500 if args.quick else DRAWS
    chains = args.chains or ([1, 8] if args.quick else [1, 4096, 1024, 64] if accel else [1, 4, 16])
    replicates = args.replicates or ([1] if args.quick else [4, 64] if accel else [4])
    # Most telling rows first: a run cut short by --budget-s keeps them.
    plan = [("chains", (36, C, draws)) for C in chains[:2]]
    plan += [("agreement", ())] if accel else []
    plan += [("sweep", (R, args.quick)) for R in replicates]
    plan += [("chains", (36, C, draws)) for C in chains[2:]]
    if not args.chains:
        plan += [("chains", (256, C, draws)) for C in ([1] if args.quick else [1, 1024] if accel else [1])]
    plan += [("updates", (args.quick,)), ("output-only-sweep", (1 if args.quick else 4, args.quick))]
    plan = sorted([(kind, a) for kind, a in plan if kind in args.sections], key=lambda r: args.sections.index(r[0]))
    run = {"chains": chains_row, "agreement": agreement_row, "sweep": sweep_row, "updates": update_rows,
           "output-only-sweep": output_only_sweep_row}
    command = "python benchmarks/accelerator.py " + " ".join(argv if argv is not None else sys.argv[1:])
    results = {"info": info, "commands": [command.strip()], "skipped": [], **{kind: [] for kind in SECTIONS}}
    for kind, a in plan:
        if time.perf_counter() - start > args.budget_s:
            results["skipped"].append(f"{kind}{a}")
            continue
        try:
            row = run[kind](*a)
        except Exception as err:  # keep the other rows of a lease-bound run
            results["skipped"].append(f"{kind}{a}: {type(err).__name__}: {err}"[:500])
            print(results["skipped"][-1], flush=True)
            continue
        results[kind] += row if isinstance(row, list) else [row]
        print(kind, row, f"[{time.perf_counter() - start:.0f} s]", flush=True)
        write(results, out)
    print(write(results, out))


if __name__ == "__main__":
    main()
