"""The input's interpolation chosen from its spectrum (issue 26, item 5): the fraction of
its variance above 0.8 Nyquist on held, band-limited, noisy and measured (Silverbox) inputs,
and ``interpolation="auto"`` in the update reporting what it chose."""

from pathlib import Path

import jax
import numpy as np
import pytest

from dtwin_jax.errors import DataError
from dtwin_jax.io.store import load_twin, save_twin
from dtwin_jax.models import systems
from dtwin_jax.models.systems import (
    HIGH_BAND_THRESHOLD,
    choose_interpolation,
    high_band_fraction,
    resolve_interpolation,
)
from dtwin_jax.preprocess.measurement import measure
from dtwin_jax.update import SamplerSettings, update_input_output

N = 4000
SILVERBOX = Path(__file__).resolve().parents[1] / "data" / "silverbox" / "SNLS80mV.csv"


def _held(rng, every, n=1):
    return np.repeat(rng.standard_normal((N // every + 1, n)), every, axis=0)[:N]


def _multisine(rng, fraction_of_nyquist, noise=0.0):
    """Unit-std random-phase multisine on every bin up to the fraction of Nyquist, plus
    white measurement noise of std ``noise``."""
    f = np.arange(1, int(fraction_of_nyquist * 0.5 * N)) / N  # cycles per sample
    s = np.cos(2 * np.pi * f[None] * np.arange(N)[:, None] + rng.uniform(0, 2 * np.pi, f.size)).sum(axis=1)
    return (s / s.std() + noise * rng.standard_normal(N))[:, None]


def _cases():
    rng = np.random.default_rng(0)
    cases = {"held white": (_held(rng, 1), "held")}
    for k in (2, 5, 20):
        cases[f"held random, new value every {k}"] = (_held(rng, k), "held")
    for r in (0.1, 0.2, 0.3, 0.4):
        cases[f"multisine to {r:.0%} Nyquist"] = (_multisine(rng, r), "bandlimited")
        for noise in (0.02, 0.05):
            cases[f"multisine to {r:.0%} Nyquist, {noise:.0%} noise"] = (_multisine(rng, r, noise), "bandlimited")
    return cases


def _silverbox_input():
    table = np.loadtxt(SILVERBOX, delimiter=",", skiprows=1)  # as examples/silverbox.py
    return table[40496:127414, :1]  # its ESTIMATION slice


def test_each_input_gets_its_interpolation_with_margin_from_the_threshold():
    rows = []
    for name, (u, expected) in _cases().items():
        frac = float(high_band_fraction(u)[0])
        rows.append((name, frac, choose_interpolation(u), expected))
    print("\ncase | fraction of variance above 0.8 Nyquist | chosen")
    for name, frac, chosen, _ in rows:
        print(f"{name} | {frac:.3g} | {chosen}")
    for name, frac, chosen, expected in rows:
        assert chosen == expected, (name, frac)
        # Measured: held every 20 samples 0.0047 (2.3x above), 5% noise 5.6e-4 (3.6x below).
        assert (frac > 2 * HIGH_BAND_THRESHOLD) if expected == "held" else (frac < HIGH_BAND_THRESHOLD / 2), name
    held_white = high_band_fraction(_cases()["held white"][0])[0]
    assert abs(held_white - 0.2) < 0.02  # white: 20% of the band holds 20% of the variance


def test_silverbox_input_is_bandlimited():
    u = _silverbox_input()
    frac = float(high_band_fraction(u)[0])
    print(f"\nSilverbox estimation input: fraction above 0.8 Nyquist {frac:.3g}")
    assert frac < 1e-4  # measured 2.9e-6
    assert choose_interpolation(u) == "bandlimited"


def test_records_columns_and_edge_cases():
    rng = np.random.default_rng(1)
    band = _multisine(rng, 0.2)
    held = _held(rng, 1)
    # Any held column makes the whole input held; a constant column is ignored.
    assert choose_interpolation(np.concatenate([band, held], axis=1)) == "held"
    assert choose_interpolation(np.concatenate([band, np.full_like(band, 3.0)], axis=1)) == "bandlimited"
    assert np.isnan(high_band_fraction(np.ones((N, 1)))[0])
    assert choose_interpolation(np.ones((N, 1))) == "held"
    # (R, N, n): pooled over records, the same answer as each record alone.
    assert choose_interpolation(np.stack([band, _multisine(rng, 0.3)])) == "bandlimited"
    assert choose_interpolation(np.stack([held, _held(rng, 1)])) == "held"
    assert choose_interpolation(band[:20]) == "held"  # too short to judge
    # A band-limited input with a slow trend and an offset: the window keeps the leakage out.
    assert choose_interpolation(band + 5.0 + np.linspace(0, 3, N)[:, None]) == "bandlimited"
    assert resolve_interpolation("auto", held) == ("held", "spectrum")
    assert resolve_interpolation("linear", held) == ("linear", "user")
    with pytest.raises(DataError, match="must be one of"):
        resolve_interpolation("cubic", held)
    with pytest.raises(DataError, match="non-finite"):
        choose_interpolation(np.full((N, 1), np.nan))
    with pytest.raises(DataError, match="shape"):
        choose_interpolation(np.ones(N))


SHORT = SamplerSettings(num_chains=2, num_draws=200, num_burnin=100)


def _example1_update(**kwargs):
    ex = systems.example1()
    sim = systems.simulate_example(ex, jax.random.key(0), duration=0.5)
    meas = measure(jax.random.key(1), sim["t"], sim["x"], sim["xdot"], sim["u"], level=0.05)
    return update_input_output(ex.system.nominal, meas.t, meas.x, meas.u, meas.xdot, library="poly:3,input",
                               settings=SHORT, **kwargs)


def test_default_update_on_example1_chooses_held_by_spectrum(tmp_path):
    res = _example1_update()
    assert res.preprocessing["input_interpolation"] == "held"
    assert res.preprocessing["input_interpolation_chosen_by"] == "spectrum"
    user = _example1_update(interpolation="held")
    assert user.preprocessing["input_interpolation_chosen_by"] == "user"
    # The same choice, so the same posterior (the paper's examples do not move).
    np.testing.assert_array_equal(res.equations[0].mean, user.equations[0].mean)
    bl = _example1_update(interpolation="bandlimited")
    assert bl.preprocessing["input_interpolation"] == "bandlimited"
    assert bl.preprocessing["input_interpolation_chosen_by"] == "user"
    # A saved twin keeps both keys, and its prediction uses the chosen interpolation.
    loaded = load_twin(save_twin(res, tmp_path / "twin"))
    assert loaded.preprocessing["input_interpolation"] == "held"
    assert loaded.preprocessing["input_interpolation_chosen_by"] == "spectrum"
    assert load_twin(save_twin(bl, tmp_path / "bl")).twin.interpolation == "bandlimited"
