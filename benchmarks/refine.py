"""Output-error refinement on random zoo members (`dtwin_jax.models.zoo`), input-output.

    python benchmarks/refine.py --members 20 --seed 0

Each member: 1 s measured at its own noise level (2-5%), `update_input_output` (2 chains x
1000 draws) with and without `refine=True`; then a new 10 s excitation, the normalised RMSE
of the posterior-mean twin (largest over states) before and after refinement, and for every
true term that the update selected, the refined coefficient's z-score `(mean - truth) / std`
(the share with |z| < 1.96 is the refined 95% interval's coverage).
"""

import argparse

import jax
import numpy as np

import dtwin_jax  # noqa: F401  (float64)
from dtwin_jax import SamplerSettings, simulate, simulation_error, update_input_output
from dtwin_jax.models import systems, zoo
from dtwin_jax.preprocess.measurement import measure


def run_member(member, settings):
    ex = member.example
    sim = systems.simulate_example(ex, jax.random.fold_in(jax.random.key(member.seed), 1))
    meas = measure(jax.random.fold_in(jax.random.key(member.seed), 2), sim["t"], sim["x"], sim["xdot"], sim["u"],
                   level=member.noise_level)
    res = update_input_output(ex.system.nominal, meas.t, meas.x, meas.u, meas.xdot, library=ex.library,
                              settings=settings, seed=member.seed, refine=True)
    if res.refinement is None:  # the free run failed: the check says why
        print(f"{ex.name}: not refined: {res.checks['refinement']['warnings'][0]}")
        return None
    try:
        new = systems.simulate_example(ex, jax.random.key(7), duration=10.0)
    except jax.errors.JaxRuntimeError:  # friction's tanh(v / w) outruns the step budget
        print(f"{ex.name}: the truth's 10 s simulation failed (solver steps); skipped")
        return None
    err = {}
    for label, twin in (("gibbs", _unrefined(res).twin), ("refined", res.twin)):
        x, _ = simulate(twin, ex.x0, new["t"], new["u"], rtol=1e-8, atol=1e-10)
        err[label] = float(np.max(simulation_error(x, new["x"])["nrmse"]))
    z = []
    for t in res.refinement_json()["terms"]:
        truth = ex.true_terms.get(t["state"], {}).get(t["expr"])
        if truth is not None:
            z.append((t["mean"] - truth) / t["std"])
    exact = all({e.names[k] for k in np.flatnonzero(e.selected)} == set(ex.true_terms.get(e.state, {}))
                for e in res.equations)
    return err, z, exact


def _unrefined(result):
    import dataclasses

    return dataclasses.replace(result, refinement=None)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--members", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    settings = SamplerSettings(num_chains=2, num_draws=1000, num_burnin=500)
    rows, zs = [], []
    print("| member | exact support | NRMSE Gibbs mean | NRMSE refined | refined z |")
    print("|---|---|---|---|---|")
    for i in range(args.members):
        m = zoo.draw_member(args.seed + i)
        out = run_member(m, settings)
        if out is None:
            continue
        err, z, exact = out
        rows.append((err["gibbs"], err["refined"]))
        zs += z
        print(f"| {m.example.name} | {exact} | {100 * err['gibbs']:.2f}% | {100 * err['refined']:.2f}% | "
              f"{', '.join(f'{v:+.2f}' for v in z)} |", flush=True)
    g, r = np.array(rows).T
    zs = np.array(zs)
    print(f"\nmedian NRMSE: Gibbs mean {100 * np.median(g):.2f}%, refined {100 * np.median(r):.2f}%; "
          f"refined better in {np.mean(r < g):.0%} of members; "
          f"95% interval coverage of true terms {np.mean(np.abs(zs) < 1.96):.0%} ({zs.size} terms)")


if __name__ == "__main__":
    main()
