"""Collinear library columns (issue 26, item 3): a position that keeps its sign makes
x1*x2 and x2*Abs(x1) one column; the group is reported, and the twin counts it once."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dtwin_jax.cli import main
from dtwin_jax.collinearity import COSINE_MIN, PIP_MIN, collinear_groups
from dtwin_jax.io import write_nominal
from dtwin_jax.io.store import load_twin
from dtwin_jax.models import systems
from dtwin_jax.preprocess.measurement import measure
from dtwin_jax.update import SamplerSettings, update_input_output

TRUE_C = -3000.0  # x2' += TRUE_C * x1 * x2
Q0 = 0.0055  # equilibrium: the position dips below zero on 0.35% of the samples
LIBRARY = "poly:2,xabs,input"
GROUP = ["x1*x2", "x2*Abs(x1)"]
SHORT = SamplerSettings(num_chains=2, num_draws=1000, num_burnin=500)


def _stage():
    k = 1000.0
    nominal = systems.LinearSecondOrder.create([[1.0]], [[2.0]], [[k]], [[0.5]], F0=[k * Q0])

    def pert(x, u, p):
        return jnp.stack([jnp.zeros_like(x[0]), p["c"] * x[0] * x[1]])

    true = systems.PerturbedSystem(nominal, pert, {"c": jnp.asarray(TRUE_C)})
    t = jnp.arange(2000) * 1e-3
    u = 1e3**0.5 * jax.random.normal(jax.random.key(0), (2000, 1))
    x, xdot = systems.simulate(true, jnp.array([Q0, 0.0]), t, u)
    return nominal, measure(jax.random.key(1), t, x, xdot, u, level=0.05)


@pytest.fixture(scope="module")
def stage():
    nominal, meas = _stage()
    result = update_input_output(nominal, meas.t, meas.x, meas.u, meas.xdot, library=LIBRARY, settings=SHORT)
    return nominal, meas, result


def test_groups_are_connected_components_of_the_cosine_graph():
    a = np.array([1.0, 2.0, 3.0, 4.0])
    L = np.stack([a, a + 1e-4 * np.array([1, -1, 1, -1]), -a, np.ones(4), a**2], axis=1)
    groups = collinear_groups(L.T @ L)
    assert [g for g, _ in groups] == [[0, 1, 2]]
    assert COSINE_MIN < groups[0][1] < 1.0
    assert collinear_groups(L.T @ L, cosine_min=1.0 - 1e-12) == [([0, 2], 1.0)]


def test_stage_group_reported_and_counted_once(stage):
    _, _, result = stage
    check = result.checks["x2 collinearity"]
    assert check["ok"] is False and GROUP in check["groups"]
    assert all(c > COSINE_MIN for c in check["cosines"])
    assert any("x1*x2, x2*Abs(x1) are nearly the same column" in w for w in result.warnings())
    assert result.checks["x2"]["ok"]  # residual checks of the twin's coefficients, the group counted once
    e = result.equations[0]
    idx = [e.names.index(n) for n in GROUP]
    # Both selected, each with the whole effect given its inclusion: the old twin doubled it.
    assert (e.pip[idx] > 0.5).all()
    old = e.coefficients[idx].sum()
    assert 1.6 < old / TRUE_C < 2.2
    new = np.asarray(result.twin.coefficients)[0, idx].sum()
    assert abs(new / TRUE_C - 1) < 0.1, new
    # Terms outside the groups keep their coefficients.
    rest = [k for k in range(len(e.names)) if e.names[k] not in sum(check["groups"], [])]
    np.testing.assert_array_equal(np.asarray(result.twin.coefficients)[0, rest], e.coefficients[rest])


def test_example1_no_group_and_twin_unchanged():
    ex = systems.example1()
    sim = systems.simulate_example(ex, jax.random.key(0))
    meas = measure(jax.random.key(1), sim["t"], sim["x"], sim["xdot"], sim["u"], level=0.05)
    result = update_input_output(ex.system.nominal, meas.t, meas.x, meas.u, meas.xdot, library=ex.library,
                                 settings=SHORT)
    assert not [k for k in result.checks if "collinearity" in k]
    assert not any("same column" in w for w in result.warnings())
    np.testing.assert_array_equal(np.asarray(result.twin.coefficients), result.equations[0].coefficients[None])
    # The paper's library has near-duplicates on these data (x1 ~ 0.1: sin(x1) ~ x1, cos(x1) ~ 1),
    # none with a PIP that matters: found in the Gram, not reported.
    e = result.equations[0]
    groups = collinear_groups(np.asarray(result.statistics["drift"].gram[0]))
    assert sorted([e.names[k] for k in g] for g, _ in groups) == [["1", "exp(-x1**2)", "cos(x1)"], ["x1", "sin(x1)"]]
    assert all(e.pip[g].max() < PIP_MIN for g, _ in groups)


def test_cli_prints_group_and_saved_twin_keeps_it(tmp_path, capsys):
    nominal, meas = _stage()
    np.savez(tmp_path / "data.npz", t=np.asarray(meas.t), x=np.asarray(meas.x), u=np.asarray(meas.u),
             xdot=np.asarray(meas.xdot))
    write_nominal(tmp_path / "nominal.toml", nominal)
    code = main(["discover", str(tmp_path / "data.npz"), "--nominal", str(tmp_path / "nominal.toml"),
                 "--library", LIBRARY, "--chains", "2", "--draws", "1000", "--burn-in", "500", "--quiet",
                 "--out", str(tmp_path / "result.json"), "--save-twin", str(tmp_path / "twin")])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "dtwin-jax: warning: x2 collinearity: terms x1*x2, x2*Abs(x1) are nearly the same column" in err
    loaded = load_twin(tmp_path / "twin")
    assert GROUP in loaded.checks["x2 collinearity"]["groups"]
    e = loaded.equations[0]
    idx = [e.names.index(n) for n in GROUP]
    new = np.asarray(loaded.twin.coefficients)[0, idx].sum()
    assert abs(new / TRUE_C - 1) < 0.1, new
