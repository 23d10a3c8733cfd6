"""The simulated positioning stage (issue 26, item 6): closed loop, quantized, and faithful
to its own equation of motion."""

import jax
import numpy as np

import dtwin_jax  # noqa: F401 (float64)
from dtwin_jax.plants import StageParams, positioning_stage, stage_nominal


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
