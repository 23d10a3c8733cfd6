"""Honest ambiguity (issue 26 item 2): the zoo members whose data nearly cannot tell the true
model from a rival, and the 95% HDI coverage of their true coefficients, with and without
the sampler's exchange move.

    python benchmarks/ambiguity.py --members 20 --combined 8 [--seed 0] [--duration 2]
        [--margin 5] [--json out.json]

Members: `zoo.draw_member(seed + i)` for `i < --members` (input-output, every state and rate
measured, as `benchmarks/zoo.py --layout accelerations`), then `--combined` SDOF members
with quadratic drag and Coulomb friction together (the issue's failure: a quadratic-drag
member, `zoo.draw_member(seed + i, "quadratic-drag")`, given Coulomb friction at 0.08 of the
per-sample force std, measured at 2% noise).

A member is **near-equivalent** when, on its regression statistics (standardised, as the
sampler sees them) and at the sampler's starting hyperparameters (`v_s = 10`, `p0 = 0.1`),
the best model found that leaves out one of the true terms has a log posterior within
`--margin` nats of the true model's. The rival is the best of a greedy forward selection
with that term forbidden and of every model the chains visited without it. The list is a
property of the data, the same for both samplers.

Each member is updated twice, `swap=True` (the default) and `swap=False`, with the same
seed; printed per member: the log-posterior gap to the rival, the rival, the PIPs of the true
terms and their HDI coverage. Then the table: exact support and coverage on every member and
on the near-equivalent ones.
"""

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import dtwin_jax  # noqa: F401  (float64)
from dtwin_jax import SamplerSettings, sampler, update_input_output
from dtwin_jax.models import systems, zoo
from dtwin_jax.preprocess.measurement import measure
from dtwin_jax.sampler.starts import greedy_indicators

sys.path.insert(0, str(Path(__file__).parent))
from zoo import score

P0, V_S = 0.1, 10.0  # the sampler's starting hyperparameters


drag_and_coulomb = zoo.drag_and_coulomb


def update(member: zoo.Member, duration: float, settings: SamplerSettings):
    """Simulate, measure (every state and rate) and update one member, as benchmarks/zoo.py."""
    ex = member.example
    sim = systems.simulate_example(ex, jax.random.fold_in(jax.random.key(member.seed), 1), duration=duration)
    meas = measure(jax.random.fold_in(jax.random.key(member.seed), 2), sim["t"], sim["x"], sim["xdot"], sim["u"],
                   level=member.noise_level)
    return update_input_output(ex.system.nominal, meas.t, meas.x, meas.u, meas.xdot, library=ex.library,
                               settings=settings, seed=member.seed)


def log_posterior(stats: sampler.SuffStats, gamma: np.ndarray) -> float:
    """``log p(y | gamma, v_s) + log p(gamma | p0)`` at ``V_S``, ``P0`` on standardised ``stats``."""
    G, b, yty, n = (np.asarray(a) for a in stats)
    prior = sampler.SpikeSlabPrior()
    r = int(gamma.sum())
    A = G[np.ix_(gamma, gamma)] + np.eye(r) / V_S
    quad = b[gamma] @ np.linalg.solve(A, b[gamma]) if r else 0.0
    logdet = np.linalg.slogdet(A)[1] if r else 0.0
    marginal = -0.5 * r * np.log(V_S) - 0.5 * logdet - (prior.a_sigma + 0.5 * n) * np.log(prior.b_sigma + 0.5 * (yty - quad))
    return float(marginal + r * np.log(P0) + (len(b) - r) * np.log1p(-P0))


def rival(stats: sampler.SuffStats, names, truth: dict, visited: np.ndarray) -> dict:
    """The true model's log posterior against the best model found without one of its terms.

    ``stats``: one equation's standardised statistics; ``visited``: ``(M, K)`` bool models
    the chains drew. Returns ``{"gap": log p(rival) - log p(true), "rival": [names]}``.
    """
    K = len(names)
    true = np.zeros(K, bool)
    true[[names.index(t) for t in truth]] = True
    base = log_posterior(stats, true)
    best, best_model = -np.inf, None
    jstats = sampler.SuffStats(*(jnp.asarray(a) for a in stats))
    for k in np.flatnonzero(true):
        allowed = np.ones(K, bool)
        allowed[k] = False
        greedy = np.asarray(greedy_indicators(jstats, sampler.SpikeSlabPrior(), jnp.asarray(P0), jnp.asarray(V_S),
                                                  min(K, 32), allowed=jnp.asarray(allowed)))
        candidates = [greedy] + [g for g in np.unique(visited[~visited[:, k]], axis=0)]
        for g in candidates:
            lp = log_posterior(stats, g)
            if lp > best:
                best, best_model = lp, g
    return {"gap": best - base, "rival": [names[k] for k in np.flatnonzero(best_model)]}


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--members", type=int, default=20)
    p.add_argument("--combined", type=int, default=8, help="drag + Coulomb members")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--duration", type=float, default=2.0)
    p.add_argument("--margin", type=float, default=5.0, help="nats: near-equivalent when the rival is this close")
    p.add_argument("--json", default=None)
    a = p.parse_args()
    members = [zoo.draw_member(a.seed + i) for i in range(a.members)]
    members += [drag_and_coulomb(a.seed + i) for i in range(a.combined)]
    print(f"{a.members} zoo members and {a.combined} drag+Coulomb from seed {a.seed}, {a.duration} s, every state "
          f"and rate measured; near-equivalent: a rival without a true term within {a.margin} nats", flush=True)
    rows = []
    for member in members:
        start = time.perf_counter()
        runs = {swap: update(member, a.duration, SamplerSettings(swap=swap)) for swap in (True, False)}
        result = runs[True]
        gaps = []
        for j, eq in enumerate(result.equations):
            truth = member.example.true_terms.get(eq.state, {})
            if not truth:
                continue
            st = sampler.standardize(sampler.SuffStats(*(jnp.asarray(s[j]) for s in result.statistics["drift"])))[0]
            visited = np.concatenate([r.equations[j].gamma.reshape(-1, len(eq.names)) for r in runs.values()])
            gaps.append({"state": eq.state} | rival(st, list(eq.names), truth, visited))
        near = any(g["gap"] > -a.margin for g in gaps)
        scores = {swap: score(member, r.equations) for swap, r in runs.items()}
        row = {"name": member.example.name, "family": member.family, "seed": member.seed, "near": near,
               "rivals": gaps, "after": scores[True], "before": scores[False], "seconds": time.perf_counter() - start}
        rows.append(row)

        def terms(s):
            return ", ".join(f"{t['term']} pip {t['pip']:.2f}{'' if t['covered'] else ' MISS'}" for t in s["terms"])

        rivals = "; ".join(f"{g['state']}: gap {g['gap']:+.1f} to {g['rival']}" for g in gaps)
        print(f"{row['name']}{' [near-equivalent]' if near else ''}: {rivals}\n    swap:    "
              f"support {'ok' if scores[True]['support_exact'] else 'WRONG'}; {terms(scores[True])}\n    no swap: "
              f"support {'ok' if scores[False]['support_exact'] else 'WRONG'}; {terms(scores[False])}  "
              f"({row['seconds']:.1f} s)", flush=True)
    print()
    print("| members | n | sampler | exact support % | true coefficients | HDI coverage % |")
    print("|---|---|---|---|---|---|")
    for label, group in (("all", rows), ("near-equivalent", [r for r in rows if r["near"]])):
        for key, name in (("before", "Gibbs sweep (before)"), ("after", "with exchange move (after)")):
            if not group:
                continue
            covered = [t["covered"] for r in group for t in r[key]["terms"]]
            exact = 100 * np.mean([r[key]["support_exact"] for r in group])
            print(f"| {label} | {len(group)} | {name} | {exact:.0f} | {len(covered)} | {100 * np.mean(covered):.0f} |")
    print("\nnear-equivalent:", ", ".join(r["name"] for r in rows if r["near"]) or "none")
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"args": vars(a), "rows": rows}, f, indent=1, default=float)


if __name__ == "__main__":
    main()
