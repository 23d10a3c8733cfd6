"""The paper's Fig. 10: example 1 against 14 noise levels (0..60%), both frameworks.

    python benchmarks/sweep.py                                   # full: 4 replicates, 4 x 2000 draws
    python benchmarks/sweep.py --modes input-output --replicates 2 --chains 2 --draws 500 --burn-in 250

Prints each framework's table (support recovery and median coefficient error per level) and
the wall time of a 1-level sweep against the 14-level sweep (each in a fresh compiled program,
so both include compilation; the 14-level one is one program, not 14 runs). Writes
sweep-<mode>.{csv,json,png} into --out-dir.
"""

import argparse
import time
from pathlib import Path

import numpy as np

from dtwin_jax import SamplerSettings, studies
from dtwin_jax.io import write_json
from dtwin_jax.plots import plot_noise_sweep


def timed(example, levels, mode, args, settings):
    start = time.perf_counter()
    res = studies.noise_sweep(example, levels, replicates=args.replicates, framework=mode, settings=settings,
                              seed=args.seed, records=args.records, progress=not args.quiet)
    return res, time.perf_counter() - start


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--example", default="example1")
    p.add_argument("--modes", nargs="+", default=["input-output", "output-only"])
    p.add_argument("--num-levels", type=int, default=14)
    p.add_argument("--max-level", type=float, default=0.6)
    p.add_argument("--replicates", type=int, default=4)
    p.add_argument("--records", type=int, default=100)
    p.add_argument("--chains", type=int, default=4)
    p.add_argument("--draws", type=int, default=2000)
    p.add_argument("--burn-in", type=int, default=1000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out-dir", default="sweep-results")
    p.add_argument("--quiet", action="store_true")
    p.add_argument("--no-repeat", action="store_true", help="skip the third (cached-program) timing run")
    args = p.parse_args()
    settings = SamplerSettings(num_chains=args.chains, num_draws=args.draws, num_burnin=args.burn_in)
    levels = np.linspace(0.0, args.max_level, args.num_levels)
    out = Path(args.out_dir)
    for mode in args.modes:
        # One level first (its own compilation), then all levels (another shape: compiled again).
        _, t_one = timed(args.example, levels[[1]], mode, args, settings)
        res, t_all = timed(args.example, levels, mode, args, settings)
        t_again = float("nan") if args.no_repeat else timed(args.example, levels, mode, args, settings)[1]
        print(f"== {args.example}, {mode}: {levels.size} levels x {args.replicates} replicates x "
              f"{args.chains} chains x {args.draws} draws (+{args.burn_in} burn-in)"
              + (f", {args.records} records" if mode == "output-only" else ""))
        for row in res.table():
            errs = "  ".join(f"{k[len('median_error_pct'):]} {v:7.3f}%" for k, v in row.items()
                             if k.startswith("median_error_pct"))
            print(f"  level {100 * row['level']:5.1f}%  support {row['support_recovery_pct']:5.0f}%  {errs}")
        print(f"  wall time: 1 level {t_one:.1f} s, {levels.size} levels {t_all:.1f} s "
              f"(compiled again: {t_again:.1f} s); timings {res.timings}")
        res.to_csv(out / f"sweep-{mode}.csv")
        write_json(out / f"sweep-{mode}.json", res.to_json())
        plot_noise_sweep(res, out / f"sweep-{mode}.png")


if __name__ == "__main__":
    main()
