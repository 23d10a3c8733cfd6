"""Predictions that fail fast and in one line, and non-smooth twins that simulate fast
(issue 25): divergence stopped by a diffrax Event, fixed steps for sign(v) friction, a
constant output-only diffusion, and a refinement failure that keeps the discover result."""

import json
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dtwin_jax  # noqa: F401
from dtwin_jax.cli import main
from dtwin_jax.errors import DataError
from dtwin_jax.io import write_nominal
from dtwin_jax.io.store import load_twin, save_twin
from dtwin_jax.library import parse_library
from dtwin_jax.models import systems, zoo
from dtwin_jax.models.prediction import (
    PredictionWarning,
    UpdatedTwin,
    divergence_bounds,
    fixed_substeps,
    is_nonsmooth,
    posterior_twins,
    predict,
)
from dtwin_jax.models.systems import LinearSecondOrder
from dtwin_jax.preprocess.measurement import measure

SHORT = ["--chains", "2", "--draws", "300", "--burn-in", "150", "--quiet"]
NOMINAL = dict(M=[[1.0]], C=[[2.0]], K=[[1000.0]], B=[[1.0]])  # 5 Hz, 3% damping


def _friction_twins(draws: int, coulomb=-2.0, seed=0) -> UpdatedTwin:
    """`draws` twins of the nominal oscillator plus Coulomb friction `coulomb sign(x2)`
    (5% spread between draws), library poly:1,sign."""
    nominal = LinearSecondOrder.create(**NOMINAL)
    lib = parse_library("poly:1,sign", 2, 1)
    coef = np.zeros((draws, 1, lib.K))
    spread = 1 + 0.05 * np.random.default_rng(seed).standard_normal(draws)
    coef[:, 0, lib.names.index("sign(x2)")] = coulomb * spread
    return UpdatedTwin(nominal, lib, (1,), jnp.asarray(coef), state_range=jnp.array([[-0.05, 0.05], [-1.0, 1.0]]))


def _held_input(seconds: float, dt=1e-3, scale=10.0, seed=1):
    """A random input held over each sample: `t (N,)`, `u (N, 1)`, the force sticking
    (|force| < 2 at a few % of the samples) as well as slipping."""
    t = np.arange(int(round(seconds / dt))) * dt
    return t, scale * np.asarray(jax.random.normal(jax.random.key(seed), (t.size, 1)))


def _relative_rms(path, reference):
    return np.sqrt(np.mean((path - reference) ** 2, axis=0)) / np.sqrt(np.mean(reference**2, axis=0))


@pytest.mark.slow  # the command line's 25 s friction prediction runs by default (test below)
def test_friction_twin_predicts_25_s_fast_within_1_percent_of_a_fine_reference():
    twins = _friction_twins(20)
    t, u = _held_input(25.0)
    assert is_nonsmooth(twins) and fixed_substeps(twins.nominal, t) == 4
    start = time.perf_counter()
    out = predict(twins, [0.01, 0.0], t, u)
    jax.block_until_ready(out["mean"])
    seconds = time.perf_counter() - start
    print(f"friction twin: 25 s at 1 kHz, 20 draws, {seconds:.1f} s (compilation included)")
    assert seconds < 30.0
    assert np.all(np.asarray(out["status"]) == systems.OK) and out["warnings"] == []
    # Draw 0 against the same twin at 16x smaller fixed steps.
    one = UpdatedTwin(twins.nominal, twins.library, twins.regressed, twins.coefficients[0])
    reference = np.asarray(systems.simulate(one, jnp.array([0.01, 0.0]), t, u, substeps=64)[0])
    error = _relative_rms(np.asarray(out["paths"][0]), reference)
    print(f"relative RMS error per state: {error}")
    assert np.all(error < 0.01)
    # The twin does stick: friction exceeds the input force at some velocity reversals.
    assert np.mean(np.abs(u) < 2.0) > 0.05


def test_fixed_steps_respect_the_held_input():
    """Bosh3 on the sub-grid: a step input held from t = 0.5 s moves nothing before it."""
    nominal = LinearSecondOrder.create(**NOMINAL)
    t = np.arange(1001) * 1e-3
    u = np.where(t >= 0.5, 1.0, 0.0)[:, None]
    fixed = np.asarray(systems.simulate(nominal, jnp.zeros(2), t, u, substeps=4)[0])
    adaptive = np.asarray(systems.simulate(nominal, jnp.zeros(2), t, u)[0])
    assert np.all(fixed[t <= 0.5] == 0.0) and np.any(fixed[t > 0.5] != 0.0)
    np.testing.assert_allclose(fixed, adaptive, atol=1e-6 * np.abs(adaptive).max())  # Bosh3: third order


@pytest.fixture(scope="module")
def friction_cli(tmp_path_factory):
    """A zoo Coulomb member updated with discover --save-twin, and a 25 s held input."""
    tmp = tmp_path_factory.mktemp("friction")
    ex = zoo.draw(4, "coulomb")
    sim = systems.simulate_example(ex, jax.random.key(0))
    meas = measure(jax.random.key(1), sim["t"], sim["x"], sim["xdot"], sim["u"], level=0.03)
    np.savez(tmp / "data.npz", t=meas.t, x=meas.x, u=meas.u, xdot=meas.xdot)
    write_nominal(tmp / "nominal.toml", ex.system.nominal)
    code = main(["discover", str(tmp / "data.npz"), "--nominal", str(tmp / "nominal.toml"), "--library",
                 "poly:3,sign,input", "--save-twin", str(tmp / "twin"), "--out", str(tmp / "result.json")] + SHORT)
    assert code == 0
    t = np.arange(25000) * ex.dt
    u = ex.input_std * np.asarray(jax.random.normal(jax.random.key(7), (t.size, 1)))
    np.savez(tmp / "new.npz", t=t, x0=np.asarray(ex.x0), u=u)
    return tmp, ex


@pytest.mark.optimized
def test_friction_twin_from_the_cli_predicts_25_s(friction_cli, capsys, monkeypatch):
    monkeypatch.setattr("dtwin_jax.progress.draws_bars", lambda: True)  # as on a terminal
    tmp, ex = friction_cli
    result = load_twin(tmp / "twin")
    assert "sign(x2)" in [n for n, s in zip(result.equations[0].names, result.equations[0].selected) if s]
    rng = np.asarray(result.preprocessing["state_range"])
    assert rng.shape == (2, 2) and np.all(rng[:, 0] < rng[:, 1])
    start = time.perf_counter()
    code = main(["predict", str(tmp / "twin"), "--input", str(tmp / "new.npz"), "--draws", "20",
                 "--out", str(tmp / "p.npz")])
    seconds = time.perf_counter() - start
    print(f"CLI predict of the friction twin, 25 s at 1 kHz, 20 draws: {seconds:.1f} s")
    assert code == 0 and seconds < 30.0
    assert "predict (draws)" in capsys.readouterr().err  # the progress bar (no --quiet)
    with np.load(tmp / "p.npz") as z:
        mean, lower, upper = z["mean"], z["lower"], z["upper"]
    assert mean.shape == (25000, 2) and np.all(np.isfinite(mean))
    assert np.all(lower <= mean + 1e-12) and np.all(mean <= upper + 1e-12)
    # The band holds the twin's model error (saved with it) unless --no-model-error.
    assert len(result.preprocessing["model_error_sd"]) == 2 and result.preprocessing["model_error_sd"][0] > 0
    assert main(["predict", str(tmp / "twin"), "--input", str(tmp / "new.npz"), "--draws", "20", "--quiet",
                 "--no-model-error", "--out", str(tmp / "bare.npz")]) == 0
    with np.load(tmp / "bare.npz") as z:
        np.testing.assert_allclose(z["mean"], mean)
        assert np.all(z["upper"] - z["lower"] <= upper - lower + 1e-12)
        assert np.mean(z["upper"][:, 0] - z["lower"][:, 0]) < np.mean(upper[:, 0] - lower[:, 0])
    # The posterior-mean twin against the true system (tanh friction) on the new input.
    with np.load(tmp / "new.npz") as z:
        truth = np.asarray(systems.simulate(ex.system, z["x0"], z["t"], z["u"])[0])
    assert np.all(_relative_rms(mean, truth) < 0.25)


def _diverging(tmp_path, friction_cli):
    """The friction twin saved with negative damping, +40 x2 and nothing else in every draw:
    unstable (another term, such as a nonlinear damping, could bound a draw's growth)."""
    tmp, _ = friction_cli
    result = load_twin(tmp / "twin")
    eq = result.equations[0]
    k = eq.names.index("x2")
    eq.theta[...] = 0.0
    eq.gamma[...] = False
    eq.theta[..., k] = 40.0
    eq.gamma[..., k] = True
    save_twin(result, tmp_path / "bad")
    return tmp_path / "bad", tmp / "new.npz"


@pytest.mark.optimized
def test_a_diverging_twin_is_one_line_in_seconds_and_writes_nothing(friction_cli, tmp_path, capsys):
    twin, new = _diverging(tmp_path, friction_cli)
    out = tmp_path / "p.npz"
    start = time.perf_counter()
    code = main(["predict", str(twin), "--input", str(new), "--quiet", "--out", str(out)])
    seconds = time.perf_counter() - start
    err = capsys.readouterr().err.strip()
    print(f"{err} ({seconds:.1f} s)")
    assert code == 2 and not out.exists()
    assert err.startswith("dtwin-jax: error: the twin diverged at t = ") and "\n" not in err
    assert "in 100 of 100 posterior draws" in err
    assert seconds < 15.0


@pytest.mark.optimized
def test_smooth_diverging_twin_stops_early_with_the_time_and_count():
    """A cubic softening spring (stiffness -1e7 x1^3, rate +1e7 x1^3) in 10 of 40 draws:
    adaptive Dopri8 stops at the bound."""
    nominal = LinearSecondOrder.create(**NOMINAL)
    lib = parse_library("poly:3", 2, 1)
    coef = np.zeros((40, 1, lib.K))
    coef[:, 0, lib.names.index("x1**3")] = np.where(np.arange(40) < 30, -1e5, 1e7)
    twins = UpdatedTwin(nominal, lib, (1,), jnp.asarray(coef), state_range=jnp.array([[-0.05, 0.05], [-1.0, 1.0]]))
    t, u = _held_input(2.0, scale=30.0)
    with pytest.raises(DataError, match=r"diverged at t = 0\.\d+ s in 10 of 40 posterior draws") as info:
        predict(twins, [0.05, 0.0], t, u)
    assert "\n" not in str(info.value)
    # A few failing draws are dropped with a warning (their paths NaN); the rest stand.
    with pytest.warns(PredictionWarning, match="in 10 of 40"):
        out = predict(twins, [0.05, 0.0], t, u, max_failed=0.5)
    status = np.asarray(out["status"])
    assert np.all(status[:30] == systems.OK) and np.all(status[30:] == systems.DIVERGED)
    assert np.all(np.isnan(np.asarray(out["paths"])[30:])) and np.all(np.isfinite(np.asarray(out["mean"])))
    # Jittable: under jit nothing is raised, the status says which draws failed.
    jitted = jax.jit(lambda tw: predict(tw, jnp.array([0.05, 0.0]), t, u)["status"])
    np.testing.assert_array_equal(np.asarray(jitted(twins)), status)


def test_max_steps_is_one_line():
    """Adaptive steps too few for the input's sample count: reported, not raised by equinox."""
    nominal = LinearSecondOrder.create(**NOMINAL)
    x, status, stop = systems.simulate_checked(nominal, jnp.array([0.01, 0.0]), jnp.arange(100) * 1e-3,
                                               jnp.ones((100, 1)), -jnp.inf * jnp.ones(2), jnp.inf * jnp.ones(2),
                                               max_steps=20)
    assert int(status) == systems.MAX_STEPS and 0 < float(stop) < 0.099
    from dtwin_jax.models.prediction import failure_message

    msg = failure_message(np.array([int(status), 0]), np.array([float(stop), 0.099]))
    assert msg.startswith("the solver ran out of steps at t = ") and "in 1 of 2 posterior draws" in msg


def test_divergence_bounds_without_a_training_range_are_generous():
    twins = _friction_twins(2)
    twins = UpdatedTwin(twins.nominal, twins.library, twins.regressed, twins.coefficients)
    lower, upper = divergence_bounds(twins, jnp.array([0.01, 0.0]), jnp.ones((10, 1)))
    assert np.all(np.asarray(upper) >= 1e3) and np.all(np.asarray(lower) == -np.asarray(upper))


def test_constant_diffusion_output_only_twin_predicts():
    """Diffusion of the constant 1 only (diffusion_library "terms:1"): ShARK, finite paths."""
    nominal = LinearSecondOrder.create(**NOMINAL)
    lib = parse_library("poly:3", 2, 0)
    dlib = parse_library("terms:1", 2, 0)
    coef = np.zeros((8, 1, lib.K))
    coef[:, 0, lib.names.index("x1**3")] = -1e4
    dcoef = np.full((8, 1, 1), 0.5)  # Gamma_vv = 0.5 (m/s)^2 / s
    twins = UpdatedTwin(nominal, lib, (1,), jnp.asarray(coef), dlib, jnp.asarray(dcoef))
    assert twins.additive_noise
    out = predict(twins, [0.01, 0.0], np.arange(2001) * 1e-3, key=jax.random.key(3))
    paths = np.asarray(out["paths"])
    assert np.all(np.isfinite(paths)) and np.all(np.asarray(out["status"]) == systems.OK)
    # Stationary velocity variance of the linear part, Gamma / (2 c): 0.125; the cubic
    # spring changes the displacement's, not the velocity's (equipartition).
    var = paths[:, 1000:, 1].var()
    assert 0.08 < var < 0.17


def test_failed_refinement_keeps_the_discover_result(friction_cli, tmp_path, monkeypatch, capsys):
    import dtwin_jax.input_output.update as io_update

    def boom(*args, **kwargs):
        raise RuntimeError("The maximum number of solver steps was reached.\nmore lines of traceback")

    monkeypatch.setattr(io_update, "refine_output_error", boom)
    tmp, _ = friction_cli
    out = tmp_path / "r.json"
    code = main(["discover", str(tmp / "data.npz"), "--nominal", str(tmp / "nominal.toml"), "--library",
                 "poly:3,sign,input", "--refine", "--save-twin", str(tmp_path / "twin"), "--out", str(out)] + SHORT)
    err = capsys.readouterr().err
    assert code == 0
    line = [w for w in err.splitlines() if "refinement" in w]
    assert line == ["dtwin-jax: warning: refinement: failed (RuntimeError): The maximum number of solver steps was "
                    "reached.; the twin is the Gibbs posterior's, unrefined"]
    result = json.loads(out.read_text())
    assert "refinement" not in result and result["checks"]["refinement"]["ok"] is False
    assert result["equations"][0]["pip"]["sign(x2)"] > 0.5
    assert load_twin(tmp_path / "twin").refinement is None


def test_refine_on_a_friction_twin_finishes(friction_cli):
    """Output-error refinement of the sign(x2) twin: fixed steps, no chatter, refined."""
    from dtwin_jax.input_output.output_error import refine_output_error

    tmp, _ = friction_cli
    result = load_twin(tmp / "twin")
    with np.load(tmp / "data.npz") as z:
        data = {k: z[k] for k in z.files}
    start = time.perf_counter()
    refined = refine_output_error(result, data["t"], data["x"], data["u"], max_iter=5, reweight=0)
    print(f"refinement of the friction twin: {time.perf_counter() - start:.1f} s")
    assert refined.refinement is not None
    twins = posterior_twins(refined, 4)
    assert np.all(np.isfinite(np.asarray(twins.coefficients)))
