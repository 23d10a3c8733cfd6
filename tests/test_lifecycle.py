"""The twin's lifecycle from the command line: discover --save-twin, predict, update."""

import jax
import numpy as np
import pytest

import dtwin_jax  # noqa: F401
from dtwin_jax import posterior_twins, predict
from dtwin_jax.cli import main
from dtwin_jax.io import write_nominal
from dtwin_jax.io.store import load_twin
from dtwin_jax.models import systems
from dtwin_jax.preprocess.measurement import measure

SHORT = ["--chains", "2", "--draws", "400", "--burn-in", "200", "--quiet"]


def _window(path, seed):
    ex = systems.EXAMPLES["example1"]()
    sim = systems.simulate_example(ex, jax.random.key(seed))
    meas = measure(jax.random.key(seed + 1), sim["t"], sim["x"], sim["xdot"], sim["u"], level=0.05)
    np.savez(path, t=meas.t, x=meas.x, u=meas.u, xdot=meas.xdot)
    return ex


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """Example 1 updated from one 1 s window and saved; a second window and a new input."""
    tmp = tmp_path_factory.mktemp("twin")
    ex = _window(tmp / "w1.npz", 0)
    _window(tmp / "w2.npz", 10)
    write_nominal(tmp / "nominal.toml", ex.system.nominal)
    t = np.arange(2000) * ex.dt
    u = np.asarray(jax.random.normal(jax.random.key(5), (t.size, 1))) * 20.0
    np.savez(tmp / "new.npz", t=t, x0=np.zeros(2), u=u)
    code = main(["discover", str(tmp / "w1.npz"), "--nominal", str(tmp / "nominal.toml"),
                 "--save-twin", str(tmp / "twin")] + SHORT)
    assert code == 0
    return tmp


def test_save_load_predict_is_identical_for_one_key(saved):
    out = saved / "p.npz"
    assert main(["predict", str(saved / "twin"), "--input", str(saved / "new.npz"),
                 "--draws", "16", "--seed", "3", "--out", str(out)]) == 0
    with np.load(out) as z:
        cli = {k: z[k] for k in z.files}
    assert set(cli) == {"t", "mean", "lower", "upper"} and cli["mean"].shape == (2000, 2)
    # The same prediction in Python from the loaded twin, with the CLI's keys.
    res = load_twin(saved / "twin")
    with np.load(saved / "new.npz") as z:
        new = {k: z[k] for k in z.files}
    key_draws, key_paths = jax.random.split(jax.random.key(3))
    py = predict(posterior_twins(res, 16, key_draws), new["x0"], new["t"], new["u"], key=key_paths)
    for k in ("mean", "lower", "upper"):
        np.testing.assert_array_equal(cli[k], np.asarray(py[k]))
    assert np.all(cli["lower"] <= cli["mean"]) and np.all(cli["mean"] <= cli["upper"])
    # Loaded equals saved: the discovered equation and the history.
    assert [e.equation() for e in res.equations] == res.history[0]["equations"]
    assert res.history[0]["prior"] == "spike-and-slab"


def test_prediction_simulates_only_the_terms_some_draw_uses(saved):
    """The solver evaluates the terms of the default 46-term library that some posterior draw
    includes; under jit (traced coefficients) it evaluates all of them: the same paths."""
    from dtwin_jax.models.prediction import used_terms

    res = load_twin(saved / "twin")
    twins = posterior_twins(res, 8, jax.random.key(1))
    coef = np.asarray(twins.coefficients)
    used = np.any(coef.reshape(-1, coef.shape[-1]) != 0, axis=0)
    pruned = used_terms(twins)
    assert 1 <= pruned.library.K == used.sum() < twins.library.K == 46
    assert list(pruned.library.names) == [n for n, k in zip(twins.library.names, used) if k]
    with np.load(saved / "new.npz") as z:
        x0, t, u = z["x0"], z["t"][:500], z["u"][:500]
    # Fixed steps for both (traced coefficients would make the default solver assume that
    # the library's sign and Abs terms are used), so that only the terms evaluated differ.
    fast = predict(twins, x0, t, u, substeps=4)
    whole = jax.jit(lambda tw: predict(tw, x0, t, u, substeps=4))(twins)
    for k in ("mean", "lower", "upper"):
        np.testing.assert_allclose(np.asarray(fast[k]), np.asarray(whole[k]), rtol=1e-9, atol=1e-12)


def test_twins_with_different_terms_share_one_simulation_program(lowered_programs):
    """The solver's program depends on the number of terms' size class, not on which terms
    (a monitored twin whose selection changes compiles nothing new); the paths equal the
    library twin's simulated term by term."""
    from dtwin_jax.library import parse_library
    from dtwin_jax.models.prediction import UpdatedTwin, library_as_data, used_terms

    nominal = systems.example1().system.nominal
    lib = parse_library("poly:3,input", 2, 1)
    t, u = np.arange(300) * 1e-3, np.random.default_rng(0).normal(size=(300, 1)) * 20.0
    for chosen in (("x1**3",), ("x1**2", "x2"), ("x1*x2**2", "x2**3", "u1")):
        coef = np.zeros((2, 1, lib.K))
        for k, name in enumerate(chosen):
            coef[:, 0, lib.names.index(name)] = [-50.0 / (k + 1), -55.0 / (k + 1)]
        twins = UpdatedTwin(nominal, lib, (1,), jax.numpy.asarray(coef))
        pred = predict(twins, np.array([0.01, 0.0]), t, u)
        assert library_as_data(used_terms(twins)).terms.family.shape == (4,)
    # The last draw simulated alone with the library evaluated as before: the same path.
    one = UpdatedTwin(nominal, lib, (1,), jax.numpy.asarray(coef[1]))
    x, _ = systems.simulate(one, np.array([0.01, 0.0]), t, u, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(np.asarray(pred["paths"][1]), np.asarray(x), rtol=0, atol=1e-9)
    paths = [p for p in lowered_programs if p[1] == "jit(_paths)"]
    assert len(paths) <= 1, paths


def test_a_twin_with_no_term_in_any_draw_predicts_the_nominal_model():
    from dtwin_jax.library import parse_library
    from dtwin_jax.models.prediction import UpdatedTwin

    nominal = systems.example1().system.nominal
    lib = parse_library("poly:3,sign,input", 2, 1)
    twins = UpdatedTwin(nominal, lib, tuple(int(i) for i in nominal.regressed_index), jax.numpy.zeros((4, 1, lib.K)))
    t, u = np.arange(200) * 1e-3, np.random.default_rng(0).normal(size=(200, 1)) * 20.0
    pred = predict(twins, np.zeros(2), t, u)
    x, _ = systems.simulate(nominal, np.zeros(2), t, u)
    np.testing.assert_allclose(np.asarray(pred["mean"]), np.asarray(x), rtol=0, atol=1e-8 * float(np.abs(x).max()))


def test_update_appends_history_and_uses_the_posterior_as_prior(saved, tmp_path):
    first = load_twin(saved / "twin")
    assert main(["update", str(saved / "twin"), str(saved / "w2.npz"), "--out-twin", str(tmp_path / "t2")]
                + SHORT) == 0
    second = load_twin(tmp_path / "t2")
    assert [h["update"] for h in second.history] == [1, 2]
    assert second.history[1]["prior"].startswith("posterior of update 1")
    # Two windows' data: the cubic coefficient's posterior std shrinks by ~1/sqrt(2).
    k = first.equations[0].names.index("x1**3")
    ratio = second.equations[0].std[k] / first.equations[0].std[k]
    print(f"std ratio after a second window: {ratio:.3f}")
    assert 0.55 < ratio < 0.85
    truth = systems.EXAMPLES["example1"]().identifiable()["x2"]["x1**3"]
    assert abs(second.equations[0].mean[k] - truth) < 0.01 * abs(truth)
    # --forget 0 is a fresh update from the new window alone (history kept; the window
    # is already in it, hence --allow-repeat).
    assert main(["update", str(tmp_path / "t2"), str(saved / "w2.npz"), "--forget", "0", "--allow-repeat"] + SHORT) == 0
    third = load_twin(tmp_path / "t2")
    assert len(third.history) == 3
    assert abs(third.equations[0].std[k] / first.equations[0].std[k] - 1) < 0.25


@pytest.mark.parametrize("case", ["no-twin", "bad-x0", "no-u", "forget"])
def test_lifecycle_errors_are_one_line_and_write_nothing(saved, tmp_path, capsys, case):
    out = tmp_path / "p.npz"
    twin, new = str(saved / "twin"), tmp_path / "new.npz"
    with np.load(saved / "new.npz") as z:
        arrays = {k: z[k] for k in z.files}
    if case == "bad-x0":
        arrays["x0"] = np.zeros(3)
    if case == "no-u":
        del arrays["u"]
    np.savez(new, **arrays)
    argv = {
        "no-twin": ["predict", str(tmp_path / "missing"), "--input", str(new), "--out", str(out)],
        "bad-x0": ["predict", twin, "--input", str(new), "--out", str(out)],
        "no-u": ["predict", twin, "--input", str(new), "--out", str(out)],
        "forget": ["update", twin, str(saved / "w2.npz"), "--forget", "1.5", "--out-twin", str(tmp_path / "t")],
    }[case]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("dtwin-jax: error:") and "\n" not in err
    assert not out.exists() and not (tmp_path / "t").exists()


def test_with_model_error_adds_half_widths_in_quadrature():
    from dtwin_jax import with_model_error

    pred = {"mean": np.zeros((3, 2)), "lower": -np.full((3, 2), 1.96 * 3.0), "upper": np.full((3, 2), 1.96 * 3.0)}
    wide = with_model_error(pred, [4.0, 0.0])
    np.testing.assert_allclose(np.asarray(wide["upper"]), [[1.96 * 5.0, 1.96 * 3.0]] * 3)
    np.testing.assert_allclose(np.asarray(wide["lower"]), -np.asarray(wide["upper"]))
    assert wide["mean"] is pred["mean"]
