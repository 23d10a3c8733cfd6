"""The simulated positioning stage (issue 26, item 6): closed loop, quantized, and faithful
to its own equation of motion."""

import jax
import numpy as np

import dtwin_jax  # noqa: F401 (float64)
from dtwin_jax.models.plants import StageParams, positioning_stage, stage_nominal


def test_the_stage_tracks_its_reference_with_a_quantized_encoder_and_sticks_at_reversals():
    p = StageParams()
    d = positioning_stage(jax.random.key(0), duration=10.0, params=p)
    q, v, r, x = d["q"], d["v"], d["reference"], d["x"][:, 0]
    assert d["t"].shape == (10001,) and d["x"].shape == (10001, 1) and d["u"].shape == (10001, 1)
    assert np.all(q > 0.0)  # the axis never crosses 0: x1*x2 and x2*Abs(x1) are one column
    assert np.sqrt(np.mean((q - r) ** 2)) < 2e-4 and np.abs(q - r).max() < 1e-3
    steps = x / p.resolution
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-6)  # whole encoder counts
    assert np.abs(x - q).max() <= p.resolution / 2 + 1e-12
    noise = d["u"][:, 0] - d["force"]
    assert abs(np.std(noise) / p.force_noise - 1) < 0.05
    assert 0.005 < np.mean(np.abs(v) < 1e-4) < 0.2  # stick-slip at the reversals
    assert stage_nominal(p).M[0, 0] == p.mass and stage_nominal(p).K[0, 0] == 0.0


def test_each_sample_obeys_the_equation_of_motion():
    # Impulse over a sample where v keeps its sign: m dv = (u - F0 - Fc sign v) dt - c dq.
    p = StageParams()
    d = positioning_stage(jax.random.key(1), duration=5.0, params=p)
    q, v, u, dt = d["q"], d["v"], d["force"], d["t"][1]
    keep = (np.sign(v[:-1]) == np.sign(v[1:])) & (np.abs(v[:-1]) > 1e-3)
    lhs = p.mass * np.diff(v)
    rhs = (u[:-1] - p.offset - p.coulomb * np.sign(v[:-1])) * dt - p.viscous * np.diff(q)
    assert keep.sum() > 3000
    assert np.max(np.abs(lhs - rhs)[keep]) < 1e-6 * np.max(np.abs(u)) * dt


def test_the_default_library_drops_what_an_axis_that_never_crosses_zero_cannot_identify():
    # Before: the default route was refused ('sign(x1)' and '1' are duplicates on these
    # data). The default library now drops those columns, says which, and the update runs.
    from dtwin_jax import SamplerSettings, update_input_output
    from dtwin_jax.library import DEFAULT_LIBRARY, parse_library

    p = StageParams()
    d = positioning_stage(jax.random.key(0), duration=2.0, params=p)
    result = update_input_output(stage_nominal(p), d["t"], d["x"], d["u"], x_names=["x1"],
                                 settings=SamplerSettings(num_chains=2, num_draws=200, num_burnin=100))
    full = parse_library(DEFAULT_LIBRARY, 2, 1).names
    dropped = set(full) - set(result.library.names)
    assert dropped == {"sign(x1)", "Abs(x1)", "x1*Abs(x1)", "x2*Abs(x1)"}
    assert result.library.names == tuple(n for n in full if n not in dropped)  # order kept
    warning = next(w for w in result.warnings() if "default library" in w)
    assert "sign(x1) (= 1)" in warning and "x2*Abs(x1) (= x1*x2)" in warning
    # An explicit library is the user's: still refused with one line.
    with np.testing.assert_raises_regex(dtwin_jax.DataError, "duplicates on these data"):
        update_input_output(stage_nominal(p), d["t"], d["x"], d["u"], x_names=["x1"], library=DEFAULT_LIBRARY)
