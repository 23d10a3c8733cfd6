"""The updates on the zoo of random perturbed systems (`dtwin_jax.models.zoo`), scored by family.

    python benchmarks/zoo.py --framework input-output|output-only --members 40 --seed 0
        [--layout accelerations|states|displacement|accelerometers] [--duration 2]
        [--records 200] [--chains 4 --draws 2000 --burn-in 1000] [--json out.json]

Member `i` is `zoo.draw_member(seed + i)` (the families cycle), measured at its own noise
level (2-5% on every signal). Input-output: `simulate_example`, then `measure` on states,
accelerations and inputs, then `update_input_output` with the measured accelerations.
Output-only: `simulate_example_sde` with `--records` records, `add_noise` on the states
(one sensor per state: the noise std is the level times the ensemble's std, the same in
every record), then `update_output_only`; with `--layout accelerometers`, the records'
accelerations alone (an accelerometer's average over each sample's interval, the same
noise), as ambient vibration is measured. Scores: exact support (every regressed equation's selected terms
are exactly its true terms), 95% HDI coverage of every true coefficient, and its relative
error `|mean / truth - 1|` (mean given inclusion; a never-included term counts 100%).
Prints one progress line per member and a markdown table by family; `--json` writes every
member's row.
"""

import argparse
import json
import time

import jax
import numpy as np

import dtwin_jax  # noqa: F401  (float64)
from dtwin_jax import SamplerSettings, update_input_output, update_output_only
from dtwin_jax.models import systems, zoo
from dtwin_jax.preprocess.measurement import add_noise, measure

LAYOUTS = ("accelerations", "states", "displacement", "accelerometers")


def _layout(nominal, layout: str, meas):
    """The measured columns of a sensor layout: ``(x, x_names, xdot, xdot_names)``.

    ``accelerations``: every state and every rate; ``states``: every state, no rates;
    ``displacement``: the displacements only; ``accelerometers``: the accelerations (the
    rates of the velocities) only, with the force."""
    names = nominal.state_names
    pos = [i for i in range(nominal.m) if i not in nominal.velocity_index]
    vel = list(nominal.velocity_index)
    if layout == "accelerations":
        return meas.x, None, meas.xdot, None
    if layout == "states":
        return meas.x, None, None, None
    if layout == "displacement":
        return meas.x[..., pos], [names[i] for i in pos], None, None
    return None, [], meas.xdot[..., vel], [names[i] for i in vel]


def _update(member: zoo.Member, framework: str, records: int, settings: SamplerSettings,
            layout: str = "accelerations", duration: float | None = None):
    """Simulate and measure one member, update its twin; returns the update's result."""
    ex, level = member.example, member.noise_level
    sim_key = jax.random.fold_in(jax.random.key(member.seed), 1)  # not the pilot's key
    noise_key = jax.random.fold_in(jax.random.key(member.seed), 2)
    nominal = ex.system.nominal
    if framework == "input-output":
        sim = systems.simulate_example(ex, sim_key, duration=duration)
        meas = measure(noise_key, sim["t"], sim["x"], sim["xdot"], sim["u"], level=level)
        x, x_names, xdot, xdot_names = _layout(nominal, layout, meas)
        result = update_input_output(nominal, meas.t, x, meas.u, xdot, x_names=x_names, xdot_names=xdot_names,
                                     library=ex.library, settings=settings, seed=member.seed)
    elif layout == "accelerometers":  # ambient vibration: accelerometers alone, the force white and unknown
        sim = systems.simulate_example_sde(ex, sim_key, num_records=records, duration=duration, accelerations=True)
        xdot = add_noise(noise_key, sim["xdot"], level, per_record=False)
        result = update_output_only(nominal, sim["t"], None, xdot=xdot,
                                    xdot_names=[nominal.state_names[i] for i in nominal.velocity_index],
                                    library=ex.library_output_only, settings=settings, seed=member.seed)
    else:
        sim = systems.simulate_example_sde(ex, sim_key, num_records=records, duration=duration)
        x = add_noise(noise_key, sim["x"], level, per_record=False)  # one sensor per state
        result = update_output_only(nominal, sim["t"], x, library=ex.library_output_only,
                                    settings=settings, seed=member.seed)
    return result


def score(member: zoo.Member, equations) -> dict:
    """Support, HDI coverage and relative error of every true coefficient of one member."""
    terms, support, diffusion = [], {}, []
    for eq in equations:
        if eq.kind == "diffusion":  # constant diffusion: exactly the term `1`, and its error
            k = eq.names.index("1")
            truth = member.example.true_diffusion()[eq.state]
            selected = sorted(eq.names[j] for j in np.flatnonzero(eq.selected))
            diffusion.append({"state": eq.state, "selected": selected, "exact": selected == ["1"],
                              "error": float(abs(eq.mean[k] / truth - 1))})
            continue
        truth = member.example.true_terms.get(eq.state, {})
        selected = sorted(eq.names[k] for k in np.flatnonzero(eq.selected))
        support[eq.state] = {"selected": selected, "true": sorted(truth),
                             "exact": set(selected) == set(truth)}
        for term, coef in truth.items():
            k = eq.names.index(term)
            lo, hi = eq.hdi_95[k]
            terms.append({
                "state": eq.state, "term": term, "truth": coef, "mean": float(eq.mean[k]),
                "std": float(eq.std[k]), "pip": float(eq.pip[k]), "hdi_95": [float(lo), float(hi)],
                "covered": bool(lo <= coef <= hi),  # NaN HDI (never included): False
                "error": float(abs(eq.mean[k] / coef - 1)),
            })
    return {"support_exact": all(s["exact"] for s in support.values()),
            "support": support, "terms": terms, "diffusion": diffusion}


def _stats(rows) -> tuple:
    errors = np.array([t["error"] for r in rows for t in r["terms"]])
    covered = [t["covered"] for r in rows for t in r["terms"]]
    return (
        len(rows),
        100 * np.mean([r["support_exact"] for r in rows]),
        100 * np.mean(covered) if covered else float("nan"),
        100 * np.median(errors) if errors.size else float("nan"),
        100 * np.percentile(errors, 90) if errors.size else float("nan"),
    )


def _diffusion_stats(rows) -> str:
    """` | constant diffusion exact % | median Gamma error %` (output-only), else empty."""
    found = [d for r in rows for d in r.get("diffusion", [])]
    if not found:
        return ""
    exact = 100 * np.mean([d["exact"] for d in found])
    return f" {exact:.0f} | {100 * np.median([d['error'] for d in found]):.2f} |"


def table(rows) -> str:
    """Markdown table by family, then the overall row."""
    extra = any(r.get("diffusion") for r in rows)
    head = "| family | members | exact support % | HDI coverage % | median error % | p90 error % |"
    lines = [head + (" diffusion `1` only % | median Gamma error % |" if extra else ""),
             "|---|---|---|---|---|---|" + ("---|---|" if extra else "")]
    groups = [(f, [r for r in rows if r["family"] == f]) for f in zoo.FAMILIES]
    for name, group in [*groups, ("**all**", rows)]:
        if group:
            n, exact, cover, med, p90 = _stats(group)
            lines.append(f"| {name} | {n} | {exact:.0f} | {cover:.0f} | {med:.2f} | {p90:.2f} |" + _diffusion_stats(group))
    return "\n".join(lines)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--framework", choices=["input-output", "output-only"], default="input-output")
    p.add_argument("--layout", choices=LAYOUTS, default="accelerations",
                   help="input-output: the sensors (every state and rate; states; displacements; accelerometers)")
    p.add_argument("--duration", type=float, default=None, help="window length in s (default: the member's, 1 s)")
    p.add_argument("--members", type=int, default=40)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--records", type=int, default=200, help="output-only: records per member")
    p.add_argument("--chains", type=int, default=4)
    p.add_argument("--draws", type=int, default=2000)
    p.add_argument("--burn-in", type=int, default=1000)
    p.add_argument("--json", default=None)
    a = p.parse_args()
    settings = SamplerSettings(num_chains=a.chains, num_draws=a.draws, num_burnin=a.burn_in)
    print(f"{a.framework} ({a.layout})" + f", {a.members} members from seed {a.seed}; {a.chains} chains x "
          f"{a.draws} draws, {a.burn_in} burn-in" + (f"; {a.records} records" if a.framework == "output-only" else ""),
          flush=True)
    rows = []
    for i in range(a.members):
        start = time.perf_counter()
        member = zoo.draw_member(a.seed + i)
        try:
            result = _update(member, a.framework, a.records, settings, a.layout, a.duration)
            row = score(member, result.equations)
            row["unsettled"] = any("did not settle" in w for w in result.checks.get("preprocessing", {}).get("warnings", []))
            failure = None
        except Exception as e:  # a failed update is a result too: scored as wrong
            row = {"support_exact": False, "support": {}, "terms": [
                {"state": s, "term": t, "truth": c, "covered": False, "error": 1.0}
                for s, terms in member.example.true_terms.items() for t, c in terms.items()]}
            failure = f"{type(e).__name__}: {e}"
        seconds = time.perf_counter() - start
        row = {"name": member.example.name, "family": member.family, "seed": member.seed,
               "noise_level": member.noise_level, "ratio": member.ratio, "z_min": member.z_min,
               "z_full": member.z_full, "description": member.example.description,
               "seconds": seconds, "failure": failure} | row
        rows.append(row)
        errors = ", ".join(f"{t['term']} {100 * t['error']:.2f}%{'' if t['covered'] else ' (HDI miss)'}"
                           for t in row["terms"])
        extra = {s: v["selected"] for s, v in row["support"].items() if not v["exact"]}
        print(f"{member.example.name}: support {'ok' if row['support_exact'] else 'WRONG ' + str(extra)}; "
              f"{errors}; " + "".join(f"diffusion {d['state']} {d['selected']} {100 * d['error']:.1f}%; "
                                      for d in row.get("diffusion", []))
              + f"{seconds:.1f} s" + ("; warned: states did not settle" if row.get("unsettled") else "")
              + (f"; FAILED {failure}" if failure else ""), flush=True)
    print()
    print(table(rows), flush=True)
    warned = [r["name"] for r in rows if r.get("unsettled")]
    print(f"warned that the accelerometers' states did not settle: {', '.join(warned) or 'none'}", flush=True)
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"framework": a.framework, "layout": a.layout, "duration": a.duration, "members": a.members, "seed": a.seed,
                       "records": a.records if a.framework == "output-only" else None,
                       "settings": {"chains": a.chains, "draws": a.draws, "burn_in": a.burn_in},
                       "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
