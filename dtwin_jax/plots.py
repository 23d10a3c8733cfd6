"""Figures: posterior inclusion probabilities as stem plots; noise sweeps (Fig. 10)."""

from __future__ import annotations

import numpy as np

__all__ = ["plot_pip", "plot_noise_sweep"]


def plot_pip(result, path=None):
    """Stem plot of every equation's PIPs with the selection threshold; returns the figure.

    ``result`` is an :class:`~dtwin_jax.twin.UpdateResult`; selected terms are labelled.
    Written to ``path`` (PNG) when given.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    eqs = result.equations
    fig, axes = plt.subplots(len(eqs), 1, figsize=(10, 2.6 * len(eqs)), squeeze=False)
    for ax, eq in zip(axes[:, 0], eqs):
        pip = eq.pip
        k = np.arange(pip.size)
        ax.stem(k, pip, basefmt="k-")
        ax.axhline(result.pip_threshold, color="r", ls="-.", lw=1)
        for i in np.flatnonzero(eq.selected):
            ax.annotate(eq.names[i], (i, pip[i]), textcoords="offset points", xytext=(4, -12), fontsize=8)
        ax.set_ylim(0, 1.08)
        ax.set_xlim(-1, pip.size)
        ax.set_ylabel("PIP")
        ax.set_title(f"{eq.state} ({eq.kind}): {int(eq.selected.sum())} of {pip.size} terms selected", fontsize=10)
    axes[-1, 0].set_xlabel("library term index")
    fig.tight_layout()
    if path is not None:
        from dtwin_jax.io import atomic_path

        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=110, format="png")
    return fig


def plot_noise_sweep(sweep, path=None):
    """The paper's Fig. 10 for a :class:`~dtwin_jax.studies.SweepResult`: against the noise
    level (% of each signal's std), (a) the relative error (%) of every true term's posterior
    mean, median over replicates with the min-max band, and (b) the support recovery rate
    (% of replicates whose every equation has exactly the true support). Framework 2's
    diffusion terms are drawn dashed. Written to ``path`` (PNG) when given; returns the figure.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    level = 100 * np.asarray(sweep.levels)
    fig, (ax_err, ax_sup) = plt.subplots(1, 2, figsize=(11, 4))
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
    ax_err.legend(fontsize=8)
    ax_sup.set_ylim(-3, 103)
    ax_sup.set_xlabel("noise level (% of signal std)")
    ax_sup.set_ylabel("exact support recovered (% of replicates)")
    ax_sup.set_title("(b) support recovery", fontsize=9)
    ax_sup.legend(fontsize=8)
    fig.tight_layout()
    if path is not None:
        from dtwin_jax.io import atomic_path

        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=110, format="png")
    return fig
