"""The Silverbox benchmark (an electronic Duffing oscillator, measured): update on the
multisine part, simulate in free run on the "arrow" part, report the RMS error in mV.

    python examples/silverbox.py [--data data/silverbox/SNLS80mV.csv]
                                 [--draws 30] [--figure docs/silverbox.png] [--out result.json]

From V1 (input, V) and V2 (output, V) alone, on the default route: the output is the
displacement `x1` (the only measured state, `x_names = ["x1"]`), the input's interpolation
is chosen from its spectrum (band-limited), the nominal linear model is identified from the
same data (:func:`dtwin_jax.preprocess.estimate.identify_linear`), and the update takes the default
library and settings (the weak form, its velocity from the state-space smoother). The band
holds the posterior draws and the twin's model error (its free-run error on the training
data), as every prediction does by default. ``--library`` replaces the default library.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import numpy as np

from dtwin_jax import posterior_twins, predict, simulate, update_input_output
from dtwin_jax.preprocess.estimate import identify_linear

FS = 1e7 / 2**14  # Hz
DATA = Path(__file__).resolve().parents[1] / "data" / "silverbox" / "SNLS80mV.csv"  # provenance: its README
ESTIMATION = slice(40496, 127414)  # every multisine realization (pauses included)
ARROW = slice(0, 40000)  # the standard free-run test


def load(path):
    """`(u, y)` in V from the SNLS80mV csv (header `V1,V2`)."""
    table = np.loadtxt(path, delimiter=",", skiprows=1)
    return table[:, 0], table[:, 1]


LIBRARY = None  # the default library


def run(path, *, draws: int = 30, estimation=ESTIMATION, seed: int = 0, settings=None, library=LIBRARY) -> dict:
    """Identify, update and predict; returns the measured errors and the prediction.

    ``draws`` posterior twins give the mean prediction and its 95% band (0: the
    posterior-mean twin alone, no band); ``estimation`` the slice of samples to learn from."""
    u, y = load(path)
    dt = 1.0 / FS
    ue, ye = u[estimation, None], y[estimation, None]
    t = np.arange(ye.shape[0]) * dt
    start = time.perf_counter()
    nominal = identify_linear(t, ye, ue, ["x1"])
    identify_s = time.perf_counter() - start
    kwargs = {} if settings is None else {"settings": settings}
    result = update_input_output(nominal, t, ye, ue, x_names=["x1"], seed=seed, library=library, **kwargs)
    ta = np.arange(ARROW.stop - ARROW.start) * dt
    ua, ya = u[ARROW, None], y[ARROW]
    x0 = np.zeros(2)
    interpolation = result.preprocessing["input_interpolation"]
    linear = np.asarray(simulate(nominal, x0, ta, ua, interpolation=interpolation)[0][:, 0])
    twin_mean = np.asarray(simulate(result.twin, x0, ta, ua)[0][:, 0])
    if draws:
        pred = predict(posterior_twins(result, draws, jax.random.key(seed)), x0, ta, ua)
        mean, lower, upper = (np.asarray(pred[k][:, 0]) for k in ("mean", "lower", "upper"))
        bare = predict(posterior_twins(result, draws, jax.random.key(seed)), x0, ta, ua, model_error=False)
        lower_p, upper_p = (np.asarray(bare[k][:, 0]) for k in ("lower", "upper"))
    else:  # the posterior-mean twin alone, no band
        mean, lower, upper = twin_mean, None, None
    model_sd = result.preprocessing["model_error_sd"][0]
    inside_range = (ya >= ye.min()) & (ya <= ye.max())
    within = slice(0, int(np.flatnonzero(~inside_range)[0]) if not inside_range.all() else ya.size)

    def rms(a, part=slice(None)):
        return float(1e3 * np.sqrt(np.mean((a[part] - ya[part]) ** 2)))

    return {
        "result": result,
        "nominal": nominal,
        "t": ta,
        "measured": ya,
        "linear": linear,
        "mean": mean,
        "lower": lower,
        "upper": upper,
        "rms_mV": {"twin": rms(mean), "posterior_mean_twin": rms(twin_mean), "linear": rms(linear),
                   "twin_within_training_range": rms(mean, within),
                   "linear_within_training_range": rms(linear, within)},
        "within_training_range_samples": within.stop,
        "band_coverage": None if lower is None else {  # the default band: parameters and model error
            "arrow": float(np.mean((ya >= lower) & (ya <= upper))),
            "within_training_range": float(np.mean(((ya >= lower) & (ya <= upper))[within]))},
        "band_width_mV": None if lower is None else float(1e3 * np.mean(upper - lower)),
        "model_error_sd_mV": 1e3 * model_sd,
        "parameter_band_coverage": None if lower is None else float(np.mean((ya >= lower_p) & (ya <= upper_p))),
        "selected_terms": sum(int(e.selected.sum()) for e in result.equations),
        "seconds": {"identify": identify_s, "update": result.seconds},
    }


def figure(out: dict, path) -> None:
    """Measured against predicted on the last 0.1 s of the arrow, and the errors over all of it."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 5.5), layout="constrained")
    ax1, ax2 = fig.subplots(2, 1)
    t, y = out["t"], out["measured"]
    # A 0.1 s window near the end: over the whole arrow the two curves cannot be told apart.
    zoom = (t >= t[-1] - 0.1)
    ax1.plot(t[zoom], y[zoom], color="k", lw=1.2, label="measured V2")
    ax1.plot(t[zoom], out["mean"][zoom], color="C0", lw=1.0, ls="--", label="updated twin (mean)")
    ax1.plot(t[zoom], out["linear"][zoom], color="C3", lw=0.8, label="linear model")
    ax1.set_ylabel("V2 (V)")
    ax1.set_xlabel("time (s), the last 0.1 s of the arrow")
    ax1.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    ax1.set_title(f"Silverbox arrow, free run: twin {out['rms_mV']['twin']:.2f} mV RMS, "
                  f"identified linear model {out['rms_mV']['linear']:.1f} mV")
    ax2.plot(t, 1e3 * (out["linear"] - y), color="C3", lw=0.4, label="linear model error")
    ax2.fill_between(t, 1e3 * (out["lower"] - y), 1e3 * (out["upper"] - y), color="C1", alpha=0.45,
                     lw=0, label="twin 95% band - measured", zorder=3)  # over the twin's error
    ax2.plot(t, 1e3 * (out["mean"] - y), color="C0", lw=0.4, label="twin error")
    ax2.axvline(t[out["within_training_range_samples"] - 1], color="k", lw=0.6, ls="--")
    ax2.set_ylim(-12, 12)
    ax2.set_xlabel("time (s)")
    ax2.set_ylabel("error (mV)")
    ax2.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    fig.savefig(path, dpi=130)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default=str(DATA))
    p.add_argument("--draws", type=int, default=30, help="posterior twins in the band")
    p.add_argument("--figure", default="docs/silverbox.png")
    p.add_argument("--library", default=LIBRARY, help="library spec (default: the default library)")
    p.add_argument("--out", default=None, help="write the result JSON here")
    args = p.parse_args()
    out = run(args.data, draws=args.draws, library=args.library)
    result = out["result"]
    print(result.summary())
    for w in result.warnings():
        print("warning:", w)
    print("nominal (identified): K", float(out["nominal"].K[0, 0]), "C", float(out["nominal"].C[0, 0]),
          "B", float(out["nominal"].B[0, 0]), "F0", float(out["nominal"].F0[0]))
    print(json.dumps({k: out[k] for k in ("rms_mV", "within_training_range_samples", "band_coverage",
                                          "band_width_mV", "model_error_sd_mV", "parameter_band_coverage",
                                          "selected_terms", "seconds")}, indent=1))
    figure(out, args.figure)
    if args.out:
        from dtwin_jax.io import write_json

        write_json(args.out, result.to_json())


if __name__ == "__main__":
    main()
