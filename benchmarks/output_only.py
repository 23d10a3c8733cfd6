"""Framework 2 on the paper's examples: drift and diffusion from noisy states only.

    python benchmarks/output_only.py [--examples example1 example3] [--noise 0.05] [--records 100]
    python benchmarks/output_only.py --diffusion-only --examples example1 example2 --noise 0 0.05 0.1 0.2

Prints the discovered equations, each true term's PIP and relative error, and sigma/m's error.
`--diffusion-only` runs the diffusion estimator alone with the true drift: the pre-averaged
pilot and the likelihood maximum with its standard error, per noise level.
"""

import argparse
import time

import jax
import numpy as np

from dtwin_jax import SamplerSettings, update_output_only
from dtwin_jax.models import systems
from dtwin_jax.output_only import kramers_moyal, statespace
from dtwin_jax.preprocess.measurement import add_noise


def run(name, level, records, duration, seed, settings):
    ex = systems.EXAMPLES[name]().for_output_only()
    sim = systems.simulate_example_sde(ex, jax.random.key(seed), num_records=records, duration=duration)
    x = np.asarray(add_noise(jax.random.key(seed + 1), sim["x"], level)) if level else np.asarray(sim["x"])
    start = time.perf_counter()
    res = update_output_only(ex.system.nominal, sim["t"], x, library=ex.library_output_only,
                             settings=settings, seed=seed)
    print(f"== {name}, {records} x {duration or ex.duration:g} s, noise {100 * level:g}%: "
          f"{time.perf_counter() - start:.1f} s")
    print(res.summary())
    for eq in res.equations:
        if eq.kind == "drift":
            for term, c in ex.true_terms.get(eq.state, {}).items():
                k = eq.names.index(term)
                print(f"   {eq.state} {term}: PIP {eq.pip[k]:.2f}, error {100 * (eq.mean[k] / c - 1):+.2f}%")
        else:
            k = eq.names.index("1")
            err = np.sqrt(max(eq.mean[k], 0) / ex.true_diffusion()[eq.state]) - 1
            print(f"   {eq.state} sigma/m: PIP {eq.pip[k]:.2f}, error {100 * err:+.2f}%")
    print("   ", res.diagnostics())


def diffusion_only(name, levels, records, duration, seed):
    ex = systems.EXAMPLES[name]().for_output_only()
    sim = systems.simulate_example_sde(ex, jax.random.key(seed), num_records=records, duration=duration)
    nominal, dt = ex.system.nominal, ex.dt
    step = statespace.DriftStep.true(ex)
    truth = np.array(list(ex.true_diffusion().values()))
    for level in levels:
        x = add_noise(jax.random.key(seed + 1), sim["x"], level) if level else sim["x"]
        start = time.perf_counter()
        s2 = kramers_moyal.noise_variance(x)
        pilot, _ = kramers_moyal.preaveraged_diffusion(nominal, x, dt, s2, step.perturbation)
        gamma, cov, _, _ = statespace.diffusion_mle(step, statespace.segments(x), s2, pilot)
        se = np.sqrt(np.diag(np.asarray(cov)))
        pct = lambda g: np.round(100 * (np.asarray(g) / truth - 1), 1).tolist()
        print(f"== {name}, noise {100 * level:g}%: Gamma error pilot {pct(pilot)}%, "
              f"likelihood {pct(gamma)}% (se {np.round(100 * se / truth, 1).tolist()}%), "
              f"{time.perf_counter() - start:.1f} s")


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--examples", nargs="+", default=["example1", "example3", "example2"])
    p.add_argument("--noise", type=float, nargs="+", default=[0.05])
    p.add_argument("--records", type=int, default=100)
    p.add_argument("--duration", type=float, default=None)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--draws", type=int, default=2000)
    p.add_argument("--diffusion-only", action="store_true")
    args = p.parse_args()
    if args.diffusion_only:
        for name in args.examples:
            diffusion_only(name, args.noise, args.records, args.duration, args.seed)
        return
    settings = SamplerSettings(num_draws=args.draws, num_burnin=args.draws // 2)
    for name in args.examples:
        for level in args.noise:
            run(name, level, args.records, args.duration, args.seed, settings)


if __name__ == "__main__":
    main()
