"""A closed loop's reference as an instrument (dtwin_jax.preprocess.instruments): the positioning stage
under PD control with an unmeasured random force of 20 N, which the controller fights, so the
measured motor force carries it. Least squares then hands part of the friction to the input;
two-stage least squares on the reference's lags does not."""

import jax
import numpy as np
import pytest

from dtwin_jax import SamplerSettings, update_input_output
from dtwin_jax.errors import DataError
from dtwin_jax.models.plants import StageParams, positioning_stage, stage_nominal

PARAMS = StageParams(disturbance=20.0)
LIBRARY = "terms:1;x2;sign(x2);x2**3;u1"
SETTINGS = SamplerSettings(num_chains=2, num_draws=1000, num_burnin=500)


@pytest.fixture(scope="module")
def stage():
    return positioning_stage(jax.random.key(0), duration=10.0, params=PARAMS)


def _fit(stage, reference):
    result = update_input_output(stage_nominal(PARAMS), stage["t"], stage["x"], stage["u"], x_names=["x1"],
                                 library=LIBRARY, reference=reference, settings=SETTINGS, seed=0)
    eq = result.equations[0]
    out = {}
    for k in np.flatnonzero(eq.selected):
        draws = eq.theta[..., k][eq.gamma[..., k]]
        out[eq.names[k]] = (draws.mean(), *np.quantile(draws, [0.025, 0.975]))
    return result, out


def test_the_reference_removes_the_closed_loops_bias(stage):
    # Measured (10 s at 1 kHz): least squares, sign(x2) -0.095 [-0.141, -0.043] and a spurious
    # u1 -0.0048; with the reference, sign(x2) -0.177 [-0.252, -0.077], 1 -0.055 [-0.102, -0.008],
    # no u1 (truth -0.2 and -0.05, acceleration units).
    coulomb, offset = -PARAMS.coulomb / PARAMS.mass, -PARAMS.offset / PARAMS.mass
    _, plain = _fit(stage, None)
    assert "u1" in plain and not plain["sign(x2)"][1] < coulomb < plain["sign(x2)"][2], plain
    result, iv = _fit(stage, stage["reference"])
    assert set(iv) == {"1", "sign(x2)"}, iv
    for term, truth in (("sign(x2)", coulomb), ("1", offset)):
        assert iv[term][1] < truth < iv[term][2], (term, iv[term])
        assert abs(iv[term][0] / truth - 1) < 0.15, (term, iv[term])
    assert "instrument" in result.preprocessing["state_smoothing"]["regression"]


@pytest.mark.parametrize("case", ["samples", "measured rates"])
def test_a_reference_that_cannot_serve_is_refused_in_one_line(stage, case):
    nominal = stage_nominal(PARAMS)
    if case == "samples":
        call = lambda: update_input_output(nominal, stage["t"], stage["x"], stage["u"], x_names=["x1"],
                                           reference=stage["reference"][:-1])
        message = "'reference' has 10000 samples but 't' has 10001"
    else:
        call = lambda: update_input_output(nominal, stage["t"], stage["x"], stage["u"], stage["u"] / 100.0,
                                           x_names=["x1"], xdot_names=["x2"], reference=stage["reference"])
        message = "a 'reference' instrument needs the weak form"
    with pytest.raises(DataError, match=message) as err:
        call()
    assert "\n" not in str(err.value)
