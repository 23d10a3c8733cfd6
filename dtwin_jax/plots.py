"""Figures: posterior inclusion probabilities as stem plots; noise sweeps (Fig. 10);
predictions with their 95% band (Figs. 7-9); degradation forecasts."""

from __future__ import annotations

import numpy as np

__all__ = ["plot_pip", "plot_noise_sweep", "plot_prediction", "plot_degradation"]


def _figure(size):
    """A figure outside pyplot: no backend is selected or changed (an interactive session
    keeps its own), and Jupyter still displays the returned figure."""
    from matplotlib.figure import Figure

    return Figure(figsize=size)


def _save(fig, path):
    if path is not None:
        from dtwin_jax.io import atomic_path

        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=110, format="png", bbox_inches="tight")  # legends sit outside the axes
    return fig


# Terms whose inclusion probability reaches this are named on PIP plots.
PIP_LABEL = 0.1


def plot_pip(result, path=None):
    """Stem plot of every equation's PIPs with the selection threshold; returns the figure.

    ``result`` is an :class:`~dtwin_jax.update.UpdateResult`; every term with PIP of at least
    :data:`PIP_LABEL` is named (the selected ones in bold). Written to ``path`` (PNG) when given.
    """
    eqs = result.equations
    fig = _figure((10, 2.6 * len(eqs)))
    axes = fig.subplots(len(eqs), 1, squeeze=False)
    for ax, eq in zip(axes[:, 0], eqs):
        pip = eq.pip
        k = np.arange(pip.size)
        ax.stem(k, pip, basefmt="k-")
        ax.axhline(result.pip_threshold, color="r", ls="-.", lw=1)
        for i in np.flatnonzero(pip >= PIP_LABEL):
            ax.annotate(eq.names[i], (i, pip[i]), textcoords="offset points", xytext=(4, 2), fontsize=8,
                        rotation=30, fontweight="bold" if eq.selected[i] else "normal")
        ax.set_ylim(0, 1.25)
        ax.set_xlim(-1, pip.size)
        ax.set_ylabel("PIP (-)")
        ax.set_title(f"{eq.state} ({eq.kind}): {int(eq.selected.sum())} of {pip.size} terms selected", fontsize=10)
    axes[-1, 0].set_xlabel("library term (index)")
    fig.tight_layout()
    return _save(fig, path)


def plot_noise_sweep(sweep, path=None):
    """The paper's Fig. 10 for a :class:`~dtwin_jax.studies.SweepResult`: against the noise
    level (% of each signal's std), (a) the relative error (%) of every true term's posterior
    mean, median over replicates with the min-max band, and (b) the support recovery rate
    (% of replicates whose every equation has exactly the true support). Framework 2's
    diffusion terms are drawn dashed. Written to ``path`` (PNG) when given; returns the figure.
    """
    level = 100 * np.asarray(sweep.levels)
    fig = _figure((11, 4))
    ax_err, ax_sup = fig.subplots(1, 2)
    parts = [(sweep, "-", "")] + ([(sweep.diffusion, "--", "diffusion ")] if sweep.diffusion is not None else [])
    for part, ls, prefix in parts:
        for name, err in part.term_errors().items():
            err = 100 * err  # (L, Rp)
            line, = ax_err.plot(level, np.median(err, axis=1), ls, marker="o", ms=3, label=prefix + name)
            ax_err.fill_between(level, err.min(axis=1), err.max(axis=1), color=line.get_color(), alpha=0.2)
        ax_sup.plot(level, 100 * part.support_recovery, ls, marker="o", ms=3, label=prefix + "support" if prefix else "drift")
    ax_err.set_yscale("symlog", linthresh=0.1)
    ax_err.set_xlabel("noise level (% of signal std)")
    ax_err.set_ylabel("relative error of posterior mean (%)")
    ax_err.set_title(f"(a) {sweep.example}, {sweep.framework}: coefficient error "
                     f"(median, min-max of {sweep.replicates})", fontsize=9)
    ax_err.legend(fontsize=8, loc="upper left", bbox_to_anchor=(0.0, -0.18), ncol=3, frameon=False)
    ax_sup.set_ylim(-3, 103)
    ax_sup.set_xlabel("noise level (% of signal std)")
    ax_sup.set_ylabel("exact support recovered (% of replicates)")
    ax_sup.set_title("(b) support recovery", fontsize=9)
    ax_sup.legend(fontsize=8, loc="upper left", bbox_to_anchor=(0.0, -0.18), ncol=2, frameon=False)
    fig.tight_layout()
    return _save(fig, path)


def plot_prediction(prediction, truth=None, *, states=None, names=None, units=None, path=None, label="truth"):
    """Predicted mean and 95% band of each state against ``truth (N, m)`` (the paper's
    Figs. 7-9). ``prediction`` is the dict of :func:`dtwin_jax.models.prediction.predict`; ``states``
    the indices to show (default all); ``names`` and ``units`` one string per state of the
    model (default ``x1, x2, ...`` in "state units"). The measurement is black, the twin red
    with its band, and the legend sits above the plots."""
    t = np.asarray(prediction["t"])
    mean, lower, upper = (np.asarray(prediction[k]) for k in ("mean", "lower", "upper"))
    states = range(mean.shape[1]) if states is None else states
    states = list(states)
    fig = _figure((10, 2.4 * len(states)))
    axes = fig.subplots(len(states), 1, squeeze=False, sharex=True)[:, 0]
    for ax, i in zip(axes, states):
        ax.fill_between(t, lower[:, i], upper[:, i], color="tab:red", alpha=0.3, lw=0, label="twin 95% band")
        if truth is not None:
            ax.plot(t, np.asarray(truth)[:, i], color="k", lw=0.9, label=label)
        ax.plot(t, mean[:, i], color="tab:red", lw=0.9, label="twin (mean)")
        unit = units[i] if units else "state units"
        ax.set_ylabel(f"{names[i] if names else f'x{i + 1}'} ({unit})")
    axes[0].legend(loc="lower left", bbox_to_anchor=(0.0, 1.02), fontsize=8, ncol=3, frameon=False)
    axes[-1].set_xlabel("time (s)")
    fig.tight_layout()
    return _save(fig, path)


def plot_degradation(forecast, truth=None, path=None):
    """Damage forecast (mean, 95% band, truth) and the failure-probability curve with its
    95% interval; ``forecast`` from :func:`dtwin_jax.models.prediction.degradation_forecast`."""
    t = np.asarray(forecast["t"])
    fig = _figure((11, 4))
    ax_d, ax_p = fig.subplots(1, 2)
    ax_d.fill_between(t, forecast["damage_lower"], forecast["damage_upper"], color="tab:red", alpha=0.3, lw=0,
                      label="twin 95% band")
    if truth is not None:
        ax_d.plot(t, truth, color="k", lw=1, label="truth")
    ax_d.plot(t, forecast["damage_mean"], color="tab:red", lw=1, label="twin (mean)")
    ax_d.axhline(forecast["critical"], color="gray", ls=":", lw=1, label="critical level")
    ax_d.set_xlabel("time (s)")
    ax_d.set_ylabel("damage (state units)")
    ax_d.legend(fontsize=8, loc="lower left", bbox_to_anchor=(0.0, 1.02), ncol=2, frameon=False)
    p = np.asarray(forecast["probability"])
    ax_p.fill_between(t, forecast["probability_lower"], forecast["probability_upper"], color="tab:orange",
                      alpha=0.3, lw=0, label="95% interval")
    ax_p.plot(t, p, color="tab:orange", lw=1.2, label="P(damage > critical by t)")
    if truth is not None:
        crossed = np.flatnonzero(np.asarray(truth) > forecast["critical"])
        if crossed.size:
            ax_p.axvline(t[crossed[0]], color="k", lw=1, label="true crossing")
    ax_p.set_ylim(-0.02, 1.02)
    ax_p.set_xlabel("time (s)")
    ax_p.set_ylabel("failure probability (-)")
    ax_p.legend(fontsize=8, loc="lower left", bbox_to_anchor=(0.0, 1.02), ncol=2, frameon=False)
    fig.tight_layout()
    return _save(fig, path)
