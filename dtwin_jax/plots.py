"""Figures: posterior inclusion probabilities as stem plots."""

from __future__ import annotations

import numpy as np

__all__ = ["plot_pip"]


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
