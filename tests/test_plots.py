"""Figures: units on every axis, the twin and the measurement in different colours, legends
outside the data, and every PIP of at least 0.1 named."""

from types import SimpleNamespace

import numpy as np
from matplotlib.colors import to_hex

from dtwin_jax.plots import PIP_LABEL, plot_degradation, plot_pip, plot_prediction


def _units_everywhere(fig):
    for ax in fig.axes:
        for label in (ax.get_xlabel(), ax.get_ylabel()):
            assert not label or label.rstrip().endswith(")"), label  # "name (unit)"
        assert ax.get_ylabel(), "a y axis without a label"


def _legends_outside(fig):
    for ax in fig.axes:
        legend = ax.get_legend()
        if legend is not None:
            anchor = legend.get_bbox_to_anchor().transformed(ax.transAxes.inverted())
            assert anchor.y0 >= 1.0 or anchor.y0 < 0.0 or anchor.x0 >= 1.0, anchor


def test_prediction_figure_has_units_colours_and_an_outside_legend():
    t = np.linspace(0.0, 1.0, 200)
    x = np.stack([np.sin(t), np.cos(t)], axis=1)
    fig = plot_prediction({"t": t, "mean": x, "lower": x - 0.1, "upper": x + 0.1}, x + 0.01,
                          names=["x1", "x2"], units=["m", "m/s"])
    _units_everywhere(fig)
    _legends_outside(fig)
    assert fig.axes[0].get_ylabel() == "x1 (m)" and fig.axes[1].get_ylabel() == "x2 (m/s)"
    measured, twin = (to_hex(line.get_color()) for line in fig.axes[0].get_lines())
    assert measured != twin


def test_every_pip_above_a_tenth_is_named():
    pip = np.array([0.02, 0.09, 0.1, 0.3, 0.97])
    eq = SimpleNamespace(state="x2", kind="drift", names=("a", "b", "c", "d", "e"), pip=pip, selected=pip > 0.5)
    fig = plot_pip(SimpleNamespace(equations=[eq], pip_threshold=0.5))
    named = [t.get_text() for t in fig.axes[0].texts]
    assert named == [n for n, p in zip(eq.names, pip) if p >= PIP_LABEL] == ["c", "d", "e"]
    _units_everywhere(fig)


def test_degradation_figure_has_units_and_outside_legends():
    t = np.linspace(0.0, 10.0, 50)
    d = 0.01 * t
    fc = {"t": t, "damage_mean": d, "damage_lower": d - 0.01, "damage_upper": d + 0.01, "critical": 0.05,
          "probability": np.clip(t / 10, 0, 1), "probability_lower": np.clip(t / 12, 0, 1),
          "probability_upper": np.clip(t / 8, 0, 1)}
    fig = plot_degradation(fc, d)
    _units_everywhere(fig)
    _legends_outside(fig)
