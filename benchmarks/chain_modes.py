"""Where many chains end: the fraction of chains in the true model after an update's run.

    taskset -c 0 python benchmarks/chain_modes.py [--example example2] [--chains 32] [--repeats 4]

Runs the output-only update of a paper example (100 records x 1 s, 5% noise, seed 0, the
tests' settings: 2 chains, 300 + 600 sweeps) for its drift statistics, then samples every
drift equation's statistics again with ``--chains`` chains ``--repeats`` times (new keys
each time) and counts the chains whose last draw is exactly the true support. A chain
elsewhere is stuck in another model: its mean log marginal likelihood over the last 100
draws (``log p(y | gamma, v_s)``, the prior of the indicators left out) is printed beside
the true model's, so a worse model (poor mixing) shows apart from an equally good or a
better one (an ambiguity the data cannot settle, or a likelihood that favours too many
terms). With two chains a stuck one shows as PIPs of 0.5 and a "chains disagree" warning.
Writes ``results/chain_modes-<example>.txt``.
"""

import argparse
from collections import Counter
from pathlib import Path

import jax
import numpy as np

from dtwin_jax import SamplerSettings, sampler, update_output_only
from dtwin_jax.models import systems
from dtwin_jax.preprocess.measurement import add_noise

TEST_SETTINGS = SamplerSettings(num_chains=2, num_draws=600, num_burnin=300)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--example", default="example2")
    p.add_argument("--chains", type=int, default=32)
    p.add_argument("--repeats", type=int, default=4)
    p.add_argument("--out", default="benchmarks/results")
    a = p.parse_args()
    ex = systems.EXAMPLES[a.example]().for_output_only()
    sim = systems.simulate_example_sde(ex, jax.random.key(0), num_records=100)
    x = np.asarray(add_noise(jax.random.key(1), sim["x"], 0.05))
    res = update_output_only(ex.system.nominal, sim["t"], x, library=ex.library_output_only,
                             settings=TEST_SETTINGS, seed=0)
    stats = res.statistics["drift"]
    truth = ex.identifiable()
    settings = SamplerSettings(num_chains=a.chains, num_draws=TEST_SETTINGS.num_draws,
                               num_burnin=TEST_SETTINGS.num_burnin)
    drift = [eq for eq in res.equations if eq.kind == "drift"]
    lines = [f"python benchmarks/chain_modes.py --example {a.example} --chains {a.chains} --repeats {a.repeats}"]
    for q, eq in enumerate(drift):
        support = set(truth.get(eq.state, {}))
        st = sampler.SuffStats(*(np.asarray(s)[q] for s in stats))
        ends, margins = Counter(), {}
        for r in range(a.repeats):
            trace = sampler.sample(jax.random.key(100 + r), st, settings)
            gamma, log_ml = np.asarray(trace.gamma), np.asarray(trace.log_marginal)
            for c in range(a.chains):
                model = tuple(sorted(eq.names[k] for k in np.flatnonzero(gamma[c, -1])))
                ends[model] += 1
                margins.setdefault(model, []).append(log_ml[c, -100:].mean())
        total = a.chains * a.repeats
        right = ends.get(tuple(sorted(support)), 0)
        lines.append(f"{eq.state}: {right} of {total} chains end in the true model {sorted(support)}")
        for model, n in ends.most_common():
            names = ", ".join(model[:6]) + (f", ... ({len(model)} terms)" if len(model) > 6 else "")
            lines.append(f"   {n:4d} chains, log marginal {np.mean(margins[model]):.1f}: {names}")
    text = "\n".join(lines) + "\n"
    print(text, end="")
    Path(a.out).mkdir(parents=True, exist_ok=True)
    (Path(a.out) / f"chain_modes-{a.example}.txt").write_text(text)


if __name__ == "__main__":
    main()
