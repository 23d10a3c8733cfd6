"""Command line (formats.md): `dtwin-jax discover`, `predict`, `update` and `monitor` (a
saved twin), `demo` and `sweep`."""

from __future__ import annotations

import _thread
import argparse
import contextlib
import os
import signal
import sys
import threading
from pathlib import Path

from dtwin_jax.errors import DataError
from dtwin_jax.runtime import configure_runtime

__all__ = ["main", "console_main", "configure_runtime"]

# The sampler's settings by their option names, for the resource checks' messages.
_OPTIONS = {"draws": "--draws", "chains": "--chains", "burn_in": "--burn-in", "library": "--library"}
INTERRUPTED = "dtwin-jax: interrupted; nothing was written"
# library.DEFAULT_LIBRARY, without importing SymPy for it (tests/test_resources.py checks they agree).
_DEFAULT_LIBRARY = "poly:6,sign,abs,xabs,exp,expxx,sin,cos,input"
# monitor.degradation.TRENDS, without importing SciPy for it (tests/test_degradation_trend.py checks).
_TRENDS = ("linear", "quadratic", "wiener")


class _Parser(argparse.ArgumentParser):
    """Usage errors as one line on standard error, exit status 2 (formats.md)."""

    def error(self, message):
        self.exit(2, f"dtwin-jax: error: {message}\n")


def _check_writable(path, *, folder: bool = False) -> None:
    """Refuse an output path that cannot be written, before any work is done: its nearest
    existing ancestor must be a writable folder, and the path itself not of the other kind."""
    path = Path(path)
    if path.exists() and path.is_dir() != folder:
        raise DataError(f"output '{path}' exists and is {'not ' if folder else ''}a folder")
    parent = path if folder else path.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise DataError(f"cannot write output '{path}': '{parent}' is not a writable folder")


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def _nonneg_int(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be a non-negative integer, got {text}")
    return value


def _smoothing(text: str):
    if text in ("auto", "none", "statespace", "savgol", "weak"):
        return None if text == "none" else text
    return _positive_int(text)


def _add_sampler_args(p: argparse.ArgumentParser, draws: int, burn_in: int, chains: int = 4) -> None:
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--chains", type=_positive_int, default=chains, help=f"Gibbs chains (default {chains})")
    p.add_argument("--draws", type=_positive_int, default=draws, help=f"kept draws per chain (default {draws})")
    p.add_argument("--burn-in", type=_nonneg_int, default=burn_in, help=f"discarded sweeps per chain (default {burn_in})")
    p.add_argument("--pip-threshold", type=float, default=0.5, help="select terms with PIP above this (default 0.5)")
    p.add_argument("--smoothing", type=_smoothing, default="auto",
                   help="state denoising: auto (kinematic smoother with measured rates; the weak form, nothing "
                        "differentiated, with every state measured and no rates; the state-space smoother when states "
                        "are missing or the sampling is too slow), weak, statespace, savgol, none, or a Savitzky-Golay "
                        "half width")
    p.add_argument("--quiet", action="store_true", help="no progress output")


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="dtwin-jax",
        description="Update a digital twin: discover interpretable perturbations of a nominal model.",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    d = sub.add_parser("discover", help="discover the perturbation from a measurement file")
    d.add_argument("data", help="measurement file (.npz or .csv, see formats.md)")
    d.add_argument("--nominal", required=True, help="nominal model (.toml)")
    d.add_argument("--mode", choices=("input-output", "output-only"), default=None,
                   help="default: input-output when the file has 'u', else output-only")
    d.add_argument("--library", default=None, help="comma-separated families (default: the paper's Eq. 24)")
    d.add_argument("--diffusion-library", default=None,
                   help="output-only: families for the diffusion (default poly:2)")
    d.add_argument("--out", default=None, help="result JSON path")
    d.add_argument("--plot", default=None, help="also write a PIP stem plot (PNG)")
    d.add_argument("--save-twin", default=None, metavar="TWIN_DIR",
                   help="also save the updated twin (posterior, nominal, library, history) to this folder")
    d.add_argument("--force", action="store_true",
                   help="with --save-twin: replace a twin already there (its history is discarded; other files stay)")
    d.add_argument("--refine", action="store_true",
                   help="input-output: refine the selected coefficients by output error (sharper long free runs)")
    _add_sampler_args(d, draws=2000, burn_in=1000)

    pr = sub.add_parser("predict", help="posterior-predictive simulation of a saved twin under a new input")
    pr.add_argument("twin", metavar="TWIN_DIR", help="a folder written by discover --save-twin")
    pr.add_argument("--input", required=True, help="NEW.npz: t (N,), x0 (m,), and u (N, n) for an input-output twin")
    pr.add_argument("--draws", type=_positive_int, default=100, help="posterior draws simulated (default 100)")
    pr.add_argument("--seed", type=int, default=0, help="random seed: draws and Brownian paths (default 0)")
    pr.add_argument("--out", required=True, help="PREDICTION.npz: t, mean, lower, upper")
    pr.add_argument("--quiet", action="store_true", help="no progress output")
    pr.add_argument("--no-model-error", action="store_true",
                    help="the band of the posterior draws alone, without the twin's model error (its free-run error "
                         "on its training data)")

    up = sub.add_parser("update", help="re-update a saved twin with a new measurement window")
    up.add_argument("twin", metavar="TWIN_DIR", help="a folder written by discover --save-twin")
    up.add_argument("data", help="the new measurement file (.npz or .csv)")
    up.add_argument("--forget", type=float, default=1.0,
                    help="weight of the previous data in the prior, in [0, 1] (default 1: all of it; 0: a fresh update)")
    up.add_argument("--out-twin", default=None, metavar="DIR", help="write the updated twin here (default: replace TWIN_DIR)")
    up.add_argument("--out", default=None, help="result JSON path")
    up.add_argument("--allow-repeat", action="store_true",
                    help="accept a window already in the twin's history (its data then count twice)")
    _add_sampler_args(up, draws=2000, burn_in=1000)

    mo = sub.add_parser("monitor", help="follow a saved twin window after window: test each window against it, "
                                        "then absorb it (formats.md)")
    mo.add_argument("twin", metavar="TWIN_DIR", help="a saved twin (the baseline); it keeps the timeline")
    mo.add_argument("windows", nargs="*", metavar="WINDOW", help="measurement files in time order, read as they come")
    mo.add_argument("--record", default=None, metavar="DATA", help="one long record, cut into windows of --window s")
    mo.add_argument("--window", type=float, default=None, metavar="SECONDS", help="the windows' length with --record")
    mo.add_argument("--out", required=True, help="MONITOR.json: the timeline (rewritten after every window)")
    mo.add_argument("--csv", default=None, help="also MONITOR.csv: one row per window")
    mo.add_argument("--plot", default=None, help="also a PNG of the test, the PIPs and the coefficients over service time")
    mo.add_argument("--false-alarm", type=float, default=None,
                    help="chance that a window that follows the twin raises an alarm (default 0.001 for an "
                         "input-output twin, 0.0005 for an output-only one)")
    mo.add_argument("--forget", type=float, default=0.9,
                    help="weight of the older windows' data at each update, in [0, 1] (default 0.9)")
    mo.add_argument("--track", default=None, metavar="STATE:TERM",
                    help="follow this coefficient's trend (for example x2:x1, an SDOF's stiffness) to --critical: "
                         "MONITOR.json gets its remaining life")
    mo.add_argument("--critical", type=float, default=None, help="the tracked coefficient's failure level")
    mo.add_argument("--trend", choices=_TRENDS, default="linear",
                    help="the tracked coefficient's trend: a straight line (default), a parabola, or a drift plus "
                         "a random walk (wiener: damage that grows with random loads, as a crack's)")
    _add_sampler_args(mo, draws=1000, burn_in=250, chains=2)  # monitor.MONITOR_SETTINGS

    demo = sub.add_parser("demo", help="simulate a paper example, update its twin, print and save results")
    demo.add_argument("--example", choices=("example1", "example2", "example3"), default="example1")
    demo.add_argument("--mode", choices=("input-output", "output-only"), default="input-output",
                      help="output-only: Brownian forcing, states measured, force not (default input-output)")
    demo.add_argument("--records", type=_positive_int, default=100,
                      help="output-only: ensemble size, records of 1 s each (default 100)")
    demo.add_argument("--noise", type=float, default=0.05, help="noise std as a fraction of each signal's std (default 0.05)")
    demo.add_argument("--out-dir", default="dtwin-demo", help="folder for the outputs (default ./dtwin-demo)")
    _add_sampler_args(demo, draws=2000, burn_in=1000)

    sw = sub.add_parser("sweep", help="noise-sensitivity study of a paper example (Fig. 10), one compiled run")
    sw.add_argument("--example", choices=("example1", "example2", "example3"), default="example1")
    sw.add_argument("--mode", choices=("input-output", "output-only"), default="input-output")
    sw.add_argument("--levels", default=None, help="comma-separated noise levels in [0, 1] (default: --num-levels from 0 to --max-level)")
    sw.add_argument("--num-levels", type=_positive_int, default=14, help="evenly spaced levels (default 14)")
    sw.add_argument("--max-level", type=float, default=0.6, help="largest level (default 0.6)")
    sw.add_argument("--replicates", type=int, default=4, help="independent data sets per level (default 4)")
    sw.add_argument("--records", type=int, default=100, help="output-only: records of 1 s per data set (default 100)")
    sw.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    sw.add_argument("--chains", type=_positive_int, default=4, help="Gibbs chains (default 4)")
    sw.add_argument("--draws", type=_positive_int, default=2000, help="kept draws per chain (default 2000)")
    sw.add_argument("--burn-in", type=_nonneg_int, default=1000, help="discarded sweeps per chain (default 1000)")
    sw.add_argument("--out-dir", default="dtwin-sweep", help="folder for sweep.csv, sweep.json, sweep.png (default ./dtwin-sweep)")
    sw.add_argument("--quiet", action="store_true", help="no progress output")
    return parser


def _settings(args):
    from dtwin_jax.update import SamplerSettings

    return SamplerSettings(num_chains=args.chains, num_draws=args.draws, num_burnin=args.burn_in)


def _check_threshold(value: float) -> None:
    if not 0.0 <= value < 1.0:
        raise DataError(f"--pip-threshold must be in [0, 1), got {value}")


def _discover(args) -> int:
    _check_threshold(args.pip_threshold)
    for out in (args.out, args.plot):
        if out:
            _check_writable(out)
    if args.save_twin:
        from dtwin_jax.io.twin_folder import check_target

        check_target(args.save_twin, force=args.force)  # before the long run: refuse a user's folder
    elif args.force:
        raise DataError("--force needs --save-twin")
    _check_early(args, _nominal_sizes(args.nominal), args.library)
    from dtwin_jax.io import load_measurements, load_nominal
    from dtwin_jax.io.twin_folder import locked

    data = load_measurements(args.data)  # first: a file's declared sizes are refused before any model is built
    nominal = load_nominal(args.nominal)
    mode = args.mode or ("input-output" if "u" in data else "output-only")
    # An existing twin (--force) is locked through the run; a new one only while it is written.
    existing = args.save_twin and (Path(args.save_twin) / "twin.json").is_file()
    with locked(args.save_twin, on_wait=_waiting(args.save_twin)) if existing else contextlib.nullcontext():
        result = _update(args, mode, nominal, data, library=args.library, diffusion_library=args.diffusion_library)
        _report(args, result)
        with _uninterrupted():
            _write_outputs(args, result)
            if args.save_twin:
                from dtwin_jax.io.store import save_twin

                save_twin(result, args.save_twin, replace=args.force)
                print(f"saved the twin to {args.save_twin}/")
    return 0


def _waiting(twin):
    """The one line a command prints when another process holds the twin's lock."""
    return lambda: print(f"dtwin-jax: waiting for twin '{twin}': another process is updating it", file=sys.stderr)


@contextlib.contextmanager
def _uninterrupted():
    """Ctrl-C is held while a run writes its outputs, and dropped once they are written:
    a run leaves all its files or none, so "nothing was written" stays true."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, lambda *_: None)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler if previous is None else previous)


def _nominal_sizes(path) -> tuple[int, int, int] | None:
    """`(d, E, n)` read off a nominal file's matrices (no validation: None when they are not
    plain lists; `io.load_nominal` later says what is wrong)."""
    import tomllib

    try:
        with open(path, "rb") as f:
            doc = tomllib.load(f)
        d, E, B = len(doc["M"]), doc.get("extra_states", 0), doc.get("B")
        n = len(B[0]) if B else d
    except Exception:  # noqa: BLE001 (any unreadable file: the loader reports it)
        return None
    return (d, E, n) if type(E) is int and E >= 0 and d > 0 else None


def _check_early(args, sizes, library) -> None:
    """The update's memory (`dtwin_jax.resources`) from the options and the nominal
    file's sizes, before the modules that load and fit the data are imported (they take
    seconds): an oversize request is refused in about a second. The update checks again,
    from the data (`dtwin_jax.update.update_input_output`)."""
    from dtwin_jax import resources

    if sizes is None:
        return
    d, E, n = sizes
    resources.check_nominal(d, E, n)
    spec = library or _DEFAULT_LIBRARY
    K = resources.count_terms(spec, 2 * d + E, n)
    resources.check_terms(K, spec)
    resources.check_sampler(d + E, K, args.chains, args.draws, args.burn_in, library=spec, names=_OPTIONS)


def _update(args, mode, nominal, data, *, library, diffusion_library=None, previous=None, forget=1.0):
    from dtwin_jax.update.from_data import update_from_data

    return update_from_data(mode, nominal, data, library=library, diffusion_library=diffusion_library,
                            smoothing=args.smoothing, refine=getattr(args, "refine", False), source=args.data,
                            pip_threshold=args.pip_threshold, settings=_settings(args), seed=args.seed,
                            progress=not args.quiet, previous=previous, forget=forget,
                            allow_repeat=getattr(args, "allow_repeat", False))


def _report(args, result) -> None:
    print(result.summary())
    _print_diagnostics(result)


def _write_outputs(args, result) -> None:
    """The result file and the PIP plot, where asked for."""
    from dtwin_jax.io import write_json

    if args.out:
        write_json(args.out, result.to_json())
    if getattr(args, "plot", None):
        from dtwin_jax.plots import plot_pip

        plot_pip(result, args.plot)


def _check_twin_early(twin) -> tuple[str | None, tuple | None]:
    """A saved twin's sizes checked before its modules are imported: its `num_inputs`
    (`resources.check_num_inputs`). Returns its library spec and its nominal
    `(d, E, n)`, each None when unreadable (`store.load_twin` says why)."""
    import json
    import re

    from dtwin_jax import resources

    folder, header = Path(twin), Path(twin) / "twin.json"
    try:
        head = json.loads(header.read_text())
        current = head.get("current") if head.get("version") == 2 else None
        if isinstance(current, str) and re.fullmatch(r"v\d{6}", current):  # format 2: a manifest
            folder, header = folder / current, folder / current / "header.json"
            head = json.loads(header.read_text())
    except Exception:  # noqa: BLE001 (any unreadable twin: load_twin reports it)
        return None, None
    sizes = _nominal_sizes(folder / "nominal.toml")
    if not isinstance(head, dict):
        return None, sizes
    if sizes:
        resources.check_num_inputs(head.get("num_inputs"), sizes[2], f"'{header}'")
    spec = head.get("library")
    return (spec if isinstance(spec, str) else None), sizes


def _update_saved(args) -> int:
    """Re-update a saved twin: its posterior (statistics times --forget) is the prior. The
    twin's lock is held from reading it to writing the update, so concurrent updates queue."""
    _check_threshold(args.pip_threshold)
    if not 0.0 <= args.forget <= 1.0:
        raise DataError(f"--forget must be in [0, 1], got {args.forget:g}")
    from dtwin_jax.io.twin_folder import check_target, locked

    target = args.out_twin or args.twin
    # In place, the twin is replaced by its continuation; --out-twin must not be another twin
    # (whose history the result does not continue): refused here, before the run.
    if Path(target).resolve() != Path(args.twin).resolve() and (Path(target) / "twin.json").is_file():
        raise DataError(f"--out-twin '{target}' already holds another twin; give a new or empty folder")
    check_target(target, force=True)  # a twin may be updated in place; a user's folder never
    if args.out:
        _check_writable(args.out)
    library, sizes = _check_twin_early(args.twin)
    _check_early(args, sizes, library)
    from dtwin_jax.io import load_measurements
    from dtwin_jax.io.store import load_twin, save_twin

    with locked(args.twin, on_wait=_waiting(args.twin)):
        previous = load_twin(args.twin)
        data = load_measurements(args.data)
        if previous.mode == "input-output" and "u" not in data:
            raise DataError(f"the twin is input-output; '{args.data}' has no key 'u'")
        result = _update(args, previous.mode, previous.nominal, data, library=previous.library,
                         diffusion_library=previous.preprocessing.get("diffusion_library"),
                         previous=previous, forget=args.forget)
        _report(args, result)
        with _uninterrupted():
            _write_outputs(args, result)
            save_twin(result, target)
    print(f"update {len(result.history)} of the twin saved to {target}/")
    return 0


def _monitor_windows(args):
    """`(source, data, t_start)` of each window, read when its turn comes."""
    from dtwin_jax.io import load_measurements

    if args.record is None:
        for path in args.windows:
            yield path, load_measurements(path), None
        return
    data = load_measurements(args.record)
    t = data["t"]
    if t.ndim != 1 or t.size < 2:
        raise DataError(f"'{args.record}': t must hold at least two sample times")
    n = int(round(args.window / (t[1] - t[0])))
    if not 3 <= n <= t.size:
        raise DataError(f"--window {args.window:g} s is {n} samples of '{args.record}', which holds {t.size}: "
                        "give at least 3 and at most the record")
    left = t.size % n
    if left:
        print(f"{args.record}: the last {left} samples are shorter than a window and are left out")
    for start in range(0, t.size - n + 1, n):
        sl = slice(start, start + n)
        window = {k: v[sl] if k == "t" or (k == "reference" and v.ndim == 1) else v[..., sl, :]
                  if k in ("x", "u", "xdot", "reference") else v for k, v in data.items()}
        yield f"{Path(args.record).name}[{start}:{start + n}]", window, float(t[start])


def _check_monitor_args(args) -> None:
    if (args.record is None) == (not args.windows):
        raise DataError("give the windows as files, or one --record with --window (not both)")
    if (args.window is None) != (args.record is None):
        raise DataError("--window goes with --record (the length of the windows cut from it)")
    if args.window is not None and not (args.window > 0 and args.window < float("inf")):
        raise DataError(f"--window must be a positive number of seconds, got {args.window:g}")
    if args.false_alarm is not None and not 0.0 < args.false_alarm < 1.0:
        raise DataError(f"--false-alarm must be in (0, 1), got {args.false_alarm:g}")
    if not 0.0 <= args.forget <= 1.0:
        raise DataError(f"--forget must be in [0, 1], got {args.forget:g}")
    if (args.track is None) != (args.critical is None):
        raise DataError("--track and --critical go together (a coefficient and its failure level)")
    if args.critical is not None and not abs(args.critical) < float("inf"):
        raise DataError(f"--critical must be a finite number, got {args.critical:g}")
    _check_threshold(args.pip_threshold)
    for out in (args.out, args.csv, args.plot):
        if out:
            _check_writable(out)
    if not (Path(args.twin) / "twin.json").is_file():
        raise DataError(f"'{args.twin}' is not a saved twin (no twin.json): save one with discover --save-twin")


def _monitor(args) -> int:
    """Follow a saved twin window after window (formats.md): each window tested against the
    twin as it stood, then absorbed; the twin (which keeps the timeline) and the timeline
    files are rewritten after every window, so a killed run resumes where it stopped."""
    _check_monitor_args(args)
    library, sizes = _check_twin_early(args.twin)
    _check_early(args, sizes, library)
    from dtwin_jax.io.store import load_twin, save_twin
    from dtwin_jax.io.twin_folder import locked
    from dtwin_jax.monitor import Monitor, first_alarm
    from dtwin_jax.monitor.timeline import write_timeline

    with locked(args.twin, on_wait=_waiting(args.twin)):
        mon = Monitor(load_twin(args.twin), settings=_settings(args), seed=args.seed, smoothing=args.smoothing,
                      false_alarm=args.false_alarm, forget=args.forget)
        settings = {"false_alarm": mon.false_alarm, "forget": mon.forget}
        for source, data, t_start in _monitor_windows(args):
            if mon.absorbed(data):
                print(f"{source}: already in the timeline; skipped")
                continue
            try:
                entry = mon.step(data, source=source, t_start=t_start)
            except DataError as e:  # which window: the earlier ones are absorbed and written
                raise DataError(f"window '{source}': {e}") from None
            reasons = [f"{k.split('_')[0]} {', '.join(entry[k])}" for k in ("new_terms", "dropped_terms",
                                                                              "changed_terms") if entry[k]]
            state = "ALARM" + (f" ({'; '.join(reasons)})" if reasons else "") if entry["alarm"] else "ok"
            print(f"window {entry['index']} ({source}): {state}, p = {entry['p_value']:.3g}, {entry['seconds']:.2f} s")
            with _uninterrupted():
                save_twin(mon.twin, args.twin)
                write_timeline(args.out, mon.timeline, csv_path=args.csv, **settings)
    timeline = mon.timeline
    remaining = None
    if args.track:
        from dtwin_jax.monitor.degradation import coefficient_track, remaining_life

        track = coefficient_track(timeline, args.track)
        rul = remaining_life(track["t"], track["mean"], track["sd"], args.critical, trend=args.trend)
        remaining = (args.track, track, rul)
        settings["remaining_life"] = {"term": args.track, **{k: v for k, v in rul.items() if k != "failure_time"},
                                      "windows": len(track["t"])}
        print(f"{args.track}: reaches {args.critical:g} at t = {rul['median']:.4g} s (90% interval {rul['lower']:.4g} "
              f"to {rul['upper']:.4g} s), {rul['rul_median']:.4g} s from now")
    with _uninterrupted():
        write_timeline(args.out, timeline, csv_path=args.csv, **settings)
        if args.plot:
            from dtwin_jax.plots import plot_monitor

            plot_monitor(timeline, args.plot, false_alarm=mon.false_alarm, remaining=remaining)
    first = first_alarm(timeline)
    print(f"{len(timeline)} windows in the timeline; first alarm: {'none' if first is None else f'window {first}'}")
    return 0


def _predict(args) -> int:
    """Posterior-predictive simulation of a saved twin: PREDICTION.npz with t, mean, lower, upper."""
    import warnings

    import jax
    import numpy as np

    from dtwin_jax import resources

    _check_writable(args.out)
    sizes = _check_twin_early(args.twin)[1]
    try:  # the paths' size from the input's times, before the twin's modules are imported
        with np.load(args.input) as z:
            samples = z["t"].size
    except Exception:  # noqa: BLE001 (load_prediction_input says what is wrong)
        samples = None
    if sizes and samples:
        resources.check_prediction(args.draws, samples, 2 * sizes[0] + sizes[1], option="--draws")
    from dtwin_jax.io import atomic_path, load_prediction_input
    from dtwin_jax.io.store import load_twin
    from dtwin_jax.models.prediction import PredictionWarning, posterior_twins, predict

    result = load_twin(args.twin)
    new = load_prediction_input(args.input, result.nominal, needs_input=result.mode == "input-output")
    resources.check_posterior_draws(args.draws, sum(e.theta.shape[-1] for e in result.equations), option="--draws")
    resources.check_prediction(args.draws, new["t"].size, result.nominal.m, option="--draws")
    key_draws, key_paths = jax.random.split(jax.random.key(args.seed))
    twins = posterior_twins(result, args.draws, key_draws)
    with warnings.catch_warnings():
        # PredictionWarning (a few draws dropped) is printed below as one line, as out["warnings"].
        warnings.simplefilter("ignore", PredictionWarning)
        try:
            out = predict(twins, new["x0"], new["t"], new.get("u"), key=key_paths, progress=not args.quiet,
                          model_error=not args.no_model_error)
        except (RuntimeError, jax.errors.JaxRuntimeError) as e:  # no traceback from a solver, whatever it hit
            raise DataError(f"the prediction failed ({type(e).__name__}): "
                            f"{(str(e).strip().splitlines() or [''])[0][:300]}") from None
    for w in out["warnings"]:
        print(f"dtwin-jax: warning: {w}", file=sys.stderr)
    arrays = {k: np.asarray(out[k]) for k in ("t", "mean", "lower", "upper")}
    if not all(np.all(np.isfinite(a)) for a in arrays.values()):
        raise DataError("the prediction diverged (non-finite states): the twin is unstable under this input")
    with _uninterrupted(), atomic_path(args.out) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
    print(f"predicted {arrays['t'].size} samples from {args.draws} posterior draws; wrote {args.out}")
    return 0


def _demo(args) -> int:
    import jax

    from dtwin_jax.models import systems
    from dtwin_jax.preprocess.measurement import measure
    from dtwin_jax.update import update_input_output

    _check_threshold(args.pip_threshold)
    if not 0.0 <= args.noise <= 1.0:
        raise DataError(f"--noise must be in [0, 1], got {args.noise}")
    say = (lambda *a: None) if args.quiet else (lambda *a: print(*a, file=sys.stderr))
    ex = systems.EXAMPLES[args.example]()
    if args.mode == "output-only":
        return _demo_output_only(args, ex, say)
    say(f"[1/3] simulating {ex.name}: {ex.duration:g} s at {1 / ex.dt:g} Hz (diffrax, Dopri8) ...")
    sim = systems.simulate_example(ex, jax.random.key(args.seed))
    meas = measure(jax.random.key(args.seed + 1), sim["t"], sim["x"], sim["xdot"], sim["u"], level=args.noise)
    nominal = ex.system.nominal
    say(f"[2/3] updating the twin: library '{ex.library}', {args.chains} chains x {args.draws} draws ...")
    result = update_input_output(
        nominal, meas.t, meas.x, meas.u, meas.xdot, library=ex.library, smoothing=args.smoothing,
        pip_threshold=args.pip_threshold, settings=_settings(args), seed=args.seed, progress=not args.quiet,
    )
    _finish_demo(
        ex, result, Path(args.out_dir), say, dict(t=meas.t, x=meas.x, u=meas.u, xdot=meas.xdot),
        [f"{ex.name}: {ex.description}",
         f"noise {100 * args.noise:g}% on every signal; {result.library.K} candidate terms per equation",
         "discovered perturbation (posterior mean ± std):"],
    )
    return 0


def _demo_output_only(args, ex, say) -> int:
    import jax
    import numpy as np

    from dtwin_jax.models import systems
    from dtwin_jax.preprocess.measurement import add_noise
    from dtwin_jax.update import update_output_only

    ex = ex.for_output_only()
    from dtwin_jax import resources

    resources.check_prediction(args.records, int(round(ex.duration / ex.dt)) + 1, ex.system.nominal.m,
                               option="--records", what="simulated records", unit="records")
    say(f"[1/3] simulating {ex.name} under Brownian forcing: {args.records} records of "
        f"{ex.duration:g} s at {1 / ex.dt:g} Hz (diffrax ShARK) ...")
    sim = systems.simulate_example_sde(ex, jax.random.key(args.seed), num_records=args.records)
    x = np.asarray(add_noise(jax.random.key(args.seed + 1), sim["x"], args.noise))
    nominal = ex.system.nominal
    say(f"[2/3] updating the twin from the states only: library '{ex.library_output_only}' ...")
    result = update_output_only(
        nominal, sim["t"], x, library=ex.library_output_only, pip_threshold=args.pip_threshold,
        settings=_settings(args), seed=args.seed, progress=not args.quiet,
    )
    _finish_demo(
        ex, result, Path(args.out_dir), say, dict(t=sim["t"], x=x),
        [f"{ex.name} (output-only): x0 = {np.asarray(ex.x0).tolist()}, {args.records} records",
         f"noise {100 * args.noise:g}% on every state; {result.library.K} drift terms per equation",
         "discovered drift perturbation and diffusion (posterior mean ± std):"],
        diffusion=ex.true_diffusion(),
    )
    return 0


def _print_diagnostics(result) -> None:
    """One line of convergence and posterior-predictive diagnostics on standard output, then
    each warning (residual and noise-correction checks, chain disagreement, R-hat) on standard error."""
    diag = result.diagnostics()
    failed = sum(not c.get("ok", True) for c in result.checks.values())
    rhat = "n/a" if diag["rhat_max"] is None else f"{diag['rhat_max']:.4f}"
    ess = "n/a" if diag["ess_bulk_min"] is None else f"{diag['ess_bulk_min']:.0f}"
    print(f"diagnostics: R-hat max {rhat}, bulk ESS min {ess}, "
          f"largest PIP disagreement between chains {diag['pip_chain_spread_max']:.3f}, "
          f"checks {'passed' if not failed else f'failed: {failed} of {len(result.checks)}'}, "
          f"{diag['seconds']:.1f} s")
    for w in result.warnings():
        print(f"dtwin-jax: warning: {w}", file=sys.stderr)


def _finish_demo(ex, result, out: Path, say, arrays: dict, header: list[str],
                 diffusion: dict | None = None) -> None:
    """Print the header, the discovered equations, the truth and diagnostics; write
    result.json, pip.png, measurements.npz and nominal.toml to `out`."""
    import numpy as np

    from dtwin_jax.io import atomic_path, write_json, write_nominal
    from dtwin_jax.plots import plot_pip

    say(f"[3/3] writing results to {out}/")
    print("\n".join(header))
    print(result.summary())
    print("truth:")
    for state, terms in ex.true_terms.items():
        print(f"{state}: " + " + ".join(f"{c:g} {t}" for t, c in terms.items()))
    for state, gamma in (diffusion or {}).items():
        print(f"{state} [diffusion]: {gamma:g}")
    _print_diagnostics(result)
    with _uninterrupted():
        write_json(out / "result.json", result.to_json())
        plot_pip(result, out / "pip.png")
        with atomic_path(out / "measurements.npz") as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, **{k: np.asarray(v) for k, v in arrays.items()})
        write_nominal(out / "nominal.toml", result.nominal)
    print(f"wrote {out}/result.json, {out}/pip.png, {out}/measurements.npz, {out}/nominal.toml")


def _sweep_levels(args) -> list[float]:
    import numpy as np

    if args.levels is None:
        if not 0.0 <= args.max_level <= 1.0:
            raise DataError(f"--max-level must be in [0, 1], got {args.max_level:g}")
        return np.linspace(0.0, args.max_level, args.num_levels).tolist()
    try:
        levels = [float(v) for v in args.levels.split(",") if v.strip()]
    except ValueError:
        raise DataError(f"--levels must be comma-separated numbers, got '{args.levels}'") from None
    if not levels:
        raise DataError("--levels is empty")
    return levels


def _sweep(args) -> int:
    """Run a noise sweep, print its table and wall time, write sweep.csv/json/png."""
    import time

    from dtwin_jax.io import write_json
    from dtwin_jax.plots import plot_noise_sweep
    from dtwin_jax.studies import noise_sweep

    levels = _sweep_levels(args)
    start = time.perf_counter()
    result = noise_sweep(
        args.example, levels, replicates=args.replicates, framework=args.mode, settings=_settings(args),
        seed=args.seed, records=args.records, progress=not args.quiet,
    )  # validates levels, replicates and records (DataError) before any work
    wall = time.perf_counter() - start
    table = result.table()
    errors = [k for k in table[0] if k.startswith("median_error_pct")]
    print(f"{result.example}, {result.framework}: {len(levels)} levels x {result.replicates} replicates x "
          f"{args.chains} chains x {args.draws} draws")
    print("level %  support %  " + "  ".join(k[len("median_error_pct"):] + " median err %" for k in errors))
    for row in table:
        print(f"{100 * row['level']:7.1f}  {row['support_recovery_pct']:9.0f}  "
              + "  ".join(f"{row[k]:>{len(k) - len('median_error_pct') + 13}.3f}" for k in errors))
    print(f"wall time {wall:.1f} s (one compiled program over all levels, compilation included)")
    out = Path(args.out_dir)
    with _uninterrupted():
        result.to_csv(out / "sweep.csv")
        write_json(out / "sweep.json", result.to_json())
        plot_noise_sweep(result, out / "sweep.png")
    print(f"wrote {out}/sweep.csv, {out}/sweep.json, {out}/sweep.png")
    return 0


def console_main(argv=None) -> int:
    """The `dtwin-jax` command: `configure_runtime` for this process, then `main`.

    (`main` called from Python leaves the caller's process as it is.) Single updates run on
    the CPU and `sweep` on an accelerator where there is one, unless `$DTWIN_JAX_PLATFORM`
    says otherwise (see `configure_runtime`). `--help` and usage errors exit before JAX starts.

    **Arguments:**

    - `argv`: the command line's arguments after the program name, or None (default) for
      `sys.argv[1:]`.

    **Returns:** the exit status, as `main` gives it (2 also for a bad `$DTWIN_JAX_PLATFORM` or
    `$DTWIN_JAX_CORES`, 130 when interrupted while the runtime is set up).
    """
    argv = sys.argv[1:] if argv is None else argv
    args = _parser().parse_args(argv)  # --help and usage errors exit here, before JAX starts
    sys.unraisablehook = _keep_interrupts(sys.unraisablehook)
    try:
        configure_runtime(platform=os.environ.get("DTWIN_JAX_PLATFORM") or
                          ("auto" if args.command == "sweep" else "cpu"))
    except DataError as e:
        return _error(str(e))
    except KeyboardInterrupt:
        return _interrupted()
    return main(argv)


def _keep_interrupts(hook):
    """`sys.unraisablehook` that raises a Ctrl-C again in the main thread: one that lands in a
    callback Python cannot raise from (jaxlib's garbage-collector callback) is otherwise
    printed and lost, and the run goes on. The new interrupt comes from another thread a
    moment later, once the main thread has left the callback (raised from this hook itself,
    it would be lost the same way); if it lands in such a callback again, so does the next."""

    def unraisable(info):
        if isinstance(info.exc_value, KeyboardInterrupt):
            threading.Timer(0.01, _thread.interrupt_main).start()
        else:
            hook(info)

    return unraisable


def main(argv=None) -> int:
    """Run one command and turn its errors into an exit status.

    Bad input and out of memory print one line on standard error; an internal error prints one
    line too, and `DTWIN_JAX_DEBUG=1` re-raises it with its traceback instead. The process
    itself is left as it is (`console_main` sets it up first).

    **Arguments:**

    - `argv`: the command line's arguments after the program name (e.g.
      `["discover", ...]`), or None (default) for `sys.argv[1:]`.

    **Returns:** the exit status: 0 on success, 2 for bad input or out of memory, 130 when
    interrupted, 1 for an internal error.
    """
    args = _parser().parse_args(argv)
    try:
        if getattr(args, "out_dir", None):
            _check_writable(args.out_dir, folder=True)
        commands = {"sweep": _sweep, "discover": _discover, "demo": _demo, "predict": _predict,
                    "update": _update_saved, "monitor": _monitor}
        return commands[args.command](args)
    except DataError as e:
        return _error(str(e))
    except KeyboardInterrupt:  # the writers are atomic and run last: no file is half-written
        return _interrupted()
    except Exception as e:
        if os.environ.get("DTWIN_JAX_DEBUG") == "1":
            raise
        if _out_of_memory(e):
            return _error(f"out of memory: {_first_line(e) or type(e).__name__}; "
                          "try fewer --draws/--chains or a smaller --library")
        _error(f"internal error: {type(e).__name__}: {_first_line(e)} (set DTWIN_JAX_DEBUG=1 for the traceback)")
        return 1


def _interrupted() -> int:
    """Print `INTERRUPTED`; returns 130. A Ctrl-C that ended inside a string `exec` or
    `eval` (namedtuple, dataclass and sympy code run some) sets a CPython 3.12 flag that, under
    `python -m`, turns the exit status into a death by SIGINT (-2) after the handler has run.
    The flag is cleared at the start of every string `exec`, so one empty one clears it."""
    print(INTERRUPTED, file=sys.stderr)
    exec("None")  # not outside input: a constant, run only to clear the flag
    return 130


def _first_line(e: BaseException) -> str:
    lines = str(e).strip().splitlines()
    return lines[0].strip() if lines else ""


def _error(message: str) -> int:
    """Print `dtwin-jax: error: <first line of message>`; returns 2."""
    lines = message.strip().splitlines()
    print(f"dtwin-jax: error: {lines[0].strip() if lines else message}", file=sys.stderr)
    return 2


def _out_of_memory(e: BaseException) -> bool:
    """numpy's `MemoryError`, or XLA's `RESOURCE_EXHAUSTED` (checked by name: no jax import)."""
    names = {c.__name__ for c in type(e).__mro__}
    return isinstance(e, MemoryError) or (
        bool(names & {"JaxRuntimeError", "XlaRuntimeError"}) and "RESOURCE_EXHAUSTED" in str(e))


if __name__ == "__main__":
    sys.exit(console_main())
