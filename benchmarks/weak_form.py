"""Framework 1 without measured rates: today's default route against the weak form.

    python benchmarks/weak_form.py [--seeds 8] [--noise 0.05 0.2]

Today's route is ``smoothing="savgol"`` (the default before the weak form). Duffing
(``systems.example1``), 1 s at 1 kHz, ``jax.random.key(seed)`` for the simulation and ``seed + 1`` for 5 % / 20 % noise on states and input, no rates; 2 chains x 1000 draws, 500
burn-in. Prints, per library, noise and route: exact supports, the median and max error of the
``x1**3`` coefficient and the share of seeds whose 95 % HDI covers the truth.
"""

import argparse
import time

import jax
import numpy as np

import dtwin_jax  # noqa: F401
from dtwin_jax import SamplerSettings, update_input_output
from dtwin_jax.models import systems
from dtwin_jax.preprocess.measurement import measure


def run(ex, library, level, seed, smoothing, settings):
    sim = systems.simulate_example(ex, jax.random.key(seed))
    meas = measure(jax.random.key(seed + 1), sim["t"], sim["x"], None, sim["u"], level=level)
    res = update_input_output(ex.system.nominal, meas.t, meas.x, meas.u, library=library, smoothing=smoothing,
                              settings=settings, seed=seed)
    eq = res.equations[0]
    k, truth = eq.names.index("x1**3"), ex.true_terms["x2"]["x1**3"]
    selected = {eq.names[i] for i in np.flatnonzero(eq.selected)}
    lo, hi = eq.hdi_95[k]
    return selected == {"x1**3"}, 100 * abs(eq.mean[k] - truth) / abs(truth), lo <= truth <= hi


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--seeds", type=int, default=8)
    p.add_argument("--noise", nargs="+", type=float, default=[0.05, 0.2])
    p.add_argument("--libraries", nargs="+", default=["paper", "poly:3,input"])
    p.add_argument("--routes", nargs="+", default=["savgol", "weak"])
    a = p.parse_args()
    ex = systems.example1()
    settings = SamplerSettings(num_chains=2, num_draws=1000, num_burnin=500)
    print(f"{jax.devices()[0].platform}; example1, {a.seeds} seeds, 2 chains x 1000 draws, 500 burn-in, no rates")
    print("| library | noise | route | support exact | median error % | max error % | 95% HDI covers | s/run |")
    print("|---|---|---|---|---|---|---|---|")
    for library in a.libraries:
        spec = ex.library if library == "paper" else library
        for level in a.noise:
            for route in a.routes:
                t0 = time.perf_counter()
                rows = [run(ex, spec, level, seed, route, settings) for seed in range(a.seeds)]
                sec = (time.perf_counter() - t0) / a.seeds
                exact, err, cover = (np.array(c) for c in zip(*rows))
                print(f"| `{library}` | {level:.0%} | {route} | {exact.sum()}/{a.seeds} | {np.median(err):.2f} | "
                      f"{err.max():.2f} | {cover.sum()}/{a.seeds} | {sec:.1f} |", flush=True)


if __name__ == "__main__":
    main()
