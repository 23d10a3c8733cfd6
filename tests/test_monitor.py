"""The monitor (formats.md, "Monitoring a structure in service"; issue 28): the window test's
false-alarm rate, detection of a stiffness drop and of a new term in a simulated life, the
timeline files, the command line's errors, and a resumed run equal to an uninterrupted one."""

import json
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

import dtwin_jax  # noqa: F401  (float64)
from dtwin_jax.cli import main
from dtwin_jax.io import write_nominal
from dtwin_jax.io.store import load_twin, save_twin
from dtwin_jax.models import zoo
from dtwin_jax.models.lives import simulate_life
from dtwin_jax.monitor import FALSE_ALARM, MONITOR_SETTINGS, Monitor, window_test
from dtwin_jax.monitor.service import combined_p_value, pooled_tests
from dtwin_jax.monitor.timeline import timeline_csv
from dtwin_jax.sampler import SuffStats
from dtwin_jax.update.from_data import update_from_data

FAST = ["--quiet"]


def _synthetic(key, K=12, n0=400, n=300, windows=4000, shift=0.0):
    """`windows` pairs of a twin's statistics over `n0` rows and a window's over `n` rows from
    the same linear model (`shift` added to coefficient 0 in the window). Each pair draws its
    own data."""
    k0, k1, k2 = jax.random.split(key, 3)
    beta, sigma = jax.random.normal(k0, (K,)), 0.7
    mix = jnp.eye(K) + 0.5 * jax.random.normal(k1, (K, K)) / np.sqrt(K)  # correlated columns

    def rows(k, size, b):
        ka, kb = jax.random.split(k)
        X = jax.random.normal(ka, (size, K)) @ mix
        return X, X @ b + sigma * jax.random.normal(kb, (size,))

    def stats_of(X, y):
        return SuffStats((X.T @ X)[None], (X.T @ y)[None], (y @ y)[None], jnp.asarray([float(X.shape[0])]))

    def pair(k):
        ka, kb = jax.random.split(k)
        return stats_of(*rows(ka, n0, beta)), stats_of(*rows(kb, n, beta.at[0].add(shift)))

    return jax.vmap(pair)(jax.random.split(k2, windows))


@pytest.fixture(scope="module")
def stationary():
    """4000 twin-and-window pairs that follow one linear model (:func:`_synthetic`)."""
    return _synthetic(jax.random.key(0))


def test_the_window_test_holds_its_false_alarm_rate_and_sees_a_small_shift(stationary):
    twins, windows = stationary
    test = jax.vmap(window_test)(twins, windows)
    p = np.asarray(test.p_all[:, 0])
    assert np.all(np.asarray(test.df) == 12)
    # Uniform p-values: the F is exact here (4000 windows).
    assert stats.kstest(p, "uniform").statistic < 0.025
    assert abs(np.mean(p < 0.01) - 0.01) < 0.005 and abs(np.mean(p < 0.1) - 0.1) < 0.015
    # Each term's t is Student's; the largest, Bonferroni-corrected, and the window's
    # p-value are conservative (to three binomial standard deviations).
    for q in (test.p_term[:, 0], test.p_value[:, 0]):
        assert np.mean(np.asarray(q) < 0.05) < 0.05 + 0.010 and np.mean(np.asarray(q) < 0.01) < 0.01 + 0.005
    one = window_test(*jax.tree.map(lambda a: a[7], (twins, windows)))
    assert np.allclose(one.statistic, test.statistic[7], rtol=1e-12)
    # A change: the power the noncentral F predicts, at a false-alarm rate of 1e-3.
    shift = 0.2
    twins, shifted = _synthetic(jax.random.key(1), windows=400, shift=shift)
    found = jax.vmap(window_test)(twins, shifted)
    p_shift = np.asarray(found.p_all[:, 0])
    G0, G1 = np.asarray(twins.gram[:, 0]), np.asarray(shifted.gram[:, 0])
    # ncp = delta^T G0 (G0 + G1)^-1 G1 delta / sigma^2, delta = shift on coefficient 0
    ncp = shift**2 * (G0 @ np.linalg.solve(G0 + G1, G1))[:, 0, 0] / 0.7**2
    dof = 400 + 300 - 2 * 12
    predicted = np.mean(stats.ncf.sf(stats.f.isf(1e-3, 12, dof), 12, dof, ncp))
    assert 0.3 < predicted < 0.9 and abs(np.mean(p_shift < 1e-3) - predicted) < 0.06
    # A change one term carries: its own score is the largest in most windows, and the
    # window's p-value (both tests) sees it more often than the chi-square alone.
    assert np.mean(np.asarray(found.term[:, 0]) == 0) > 0.8
    assert np.mean(np.asarray(found.p_value[:, 0]) < 1e-3) > np.mean(p_shift < 1e-3) + 0.1


def test_the_nominal_linear_terms_are_tested_together_at_their_own_rate(stationary):
    # Columns 0 and 1 stand for the nominal's displacement and velocity: their score alone is
    # F(2, dof) on windows that follow the twin, and a change there (a stiffness that moved)
    # is seen with the power of a 2-degree-of-freedom F, more often than by the other tests.
    linear = np.arange(12) < 2
    test = jax.vmap(window_test, in_axes=(0, 0, None, None, None))(*stationary, 1.0, 0.0, linear)
    p = np.asarray(test.p_linear[:, 0])
    # Measured: KS 0.014, 1.0% below 0.01, 9.9% below 0.1; the window's p-value 1.05% below 0.01.
    assert stats.kstest(p, "uniform").statistic < 0.025
    assert abs(np.mean(p < 0.01) - 0.01) < 0.005 and abs(np.mean(p < 0.1) - 0.1) < 0.015
    q = np.asarray(test.p_value[:, 0])
    assert np.mean(q < 0.05) < 0.05 + 0.010 and np.mean(q < 0.01) < 0.01 + 0.005
    shift = 0.2
    twins, shifted = _synthetic(jax.random.key(1), windows=400, shift=shift)
    found = jax.vmap(window_test, in_axes=(0, 0, None, None, None))(twins, shifted, 1.0, 0.0, linear)
    G0, G1 = np.asarray(twins.gram[:, 0]), np.asarray(shifted.gram[:, 0])
    ncp = shift**2 * (G0 @ np.linalg.solve(G0 + G1, G1))[:, 0, 0] / 0.7**2
    dof = 400 + 300 - 2 * 12
    predicted = np.mean(stats.ncf.sf(stats.f.isf(1e-3, 2, dof), 2, dof, ncp))  # 0.74
    assert abs(np.mean(np.asarray(found.p_linear[:, 0]) < 1e-3) - predicted) < 0.06  # measured 0.77
    # The window's p-value: 68% below 1e-3 with the linear terms' test, 61% without it.
    without = np.asarray(jax.vmap(window_test)(twins, shifted).p_value[:, 0])
    assert np.mean(np.asarray(found.p_value[:, 0]) < 1e-3) > np.mean(without < 1e-3) + 0.05


def test_a_window_whose_score_carries_its_own_error_is_tested_with_that_spread(stationary):
    # Each window's coefficients are off by its own eta ~ N(0, E) (the error its estimated
    # states put in every row at once): its score has the extra covariance Omega = G1 E G1,
    # and the twin's data (400 rows against the window's 300) n0 / n1 Omega, as the test
    # takes it. Without it the test alarms far too often; with it the p-values are uniform.
    twins, windows = stationary
    K, rng = 12, np.random.default_rng(3)
    G1 = np.asarray(windows.gram[:, 0])
    omega = G1 @ (0.02 * np.eye(K)) @ G1
    extra = np.einsum("ikl,il->ik", np.linalg.cholesky(omega), rng.standard_normal(G1.shape[:2]))
    twin_extra = np.einsum("ikl,il->ik", np.linalg.cholesky(400 / 300 * omega), rng.standard_normal(G1.shape[:2]))
    shifted = windows._replace(xty=windows.xty + jnp.asarray(extra)[:, None])
    twins = twins._replace(xty=twins.xty + jnp.asarray(twin_extra)[:, None])
    bare = np.asarray(jax.vmap(window_test)(twins, shifted).p_all[:, 0])
    spread = np.asarray(jax.vmap(window_test, in_axes=(0, 0, None, 0))(twins, shifted, 1.0,
                                                                       jnp.asarray(omega)[:, None]).p_all[:, 0])
    # Measured: 77% of the bare tests below 1e-3; with the spread KS distance 0.035 (a little
    # conservative: the F's s2 is estimated, Omega is not), 0.85% below 0.01, 9.2% below 0.1.
    assert np.mean(bare < 1e-3) > 0.7
    assert stats.kstest(spread, "uniform").statistic < 0.04
    assert abs(np.mean(spread < 0.01) - 0.01) < 0.005 and abs(np.mean(spread < 0.1) - 0.1) < 0.015


def test_pooled_windows_see_a_change_no_window_shows_alone():
    # Five windows after a small shift, each tested alone and pooled against a twin of ten
    # windows' data before the first: the pooled p-value falls as the windows add up.
    twins, shifted = _synthetic(jax.random.key(2), n0=3000, windows=5, shift=0.08)
    twin = jax.tree.map(lambda a: a[0], twins)
    windows = [jax.tree.map(lambda a, j=j: a[j], shifted) for j in range(5)]
    alone = [float(window_test(twin, w).p_value[0]) for w in windows]
    tests = pooled_tests(twin, windows[4], [(w, twin, None) for w in windows[3::-1]])
    p, p_window = combined_p_value(tests)
    assert p_window == pytest.approx(alone[4]) and min(alone) > 0.02
    pooled = [float(t.p_value[0]) for t in tests]
    assert pooled[-1] < 1e-5 and p == pytest.approx(5 * min(pooled)) and p < 1e-4


@pytest.fixture(scope="module")
def life():
    """Zoo member 4 (an SDOF with Coulomb friction, the friction absent at first): its
    stiffness drops 5% at window 2, the friction appears at window 4; 5% noise on every
    signal (force, displacement, velocity, acceleration)."""
    ex = zoo.draw_member(4).example
    assert zoo.draw_member(4).family == "coulomb"
    scale = np.array([0, 0, 0, 0, 1, 1, 1.0])
    stiffness = np.array([1, 1, 0.95, 0.95, 0.95, 0.95, 0.95])
    windows = simulate_life(ex, jax.random.key(4), scale=scale, stiffness=stiffness, level=0.05)
    base = update_from_data("input-output", ex.system.nominal, windows[0], library=ex.library, settings=MONITOR_SETTINGS)
    return ex, windows, base


def test_a_stiffness_drop_and_a_new_term_are_flagged_when_they_appear_and_named(life):
    ex, windows, base = life
    mon = Monitor(base)
    entries = [mon.step(w, source=f"w{i}") for i, w in enumerate(windows[1:], start=1)]
    assert [e["alarm"] for e in entries] == [False, True, False, True, False, False]
    assert [e["index"] for e in entries] == list(range(6))
    drop, friction = entries[1], entries[3]
    k_over_m = float(ex.system.nominal.K[0, 0] / ex.system.nominal.M[0, 0])
    assert drop["new_terms"] == ["x2:x1"] and drop["p_value"] < 1e-4
    assert "x2:sign(x2)" in friction["new_terms"] and friction["p_value"] < 1e-10
    # The restarted twin's stiffness change is the 5% drop (0.05 k/m), within its interval.
    x1 = next(t for t in entries[2]["equations"][0]["terms"] if t["expr"] == "x1")
    assert x1["hdi_95"][0] < 0.05 * k_over_m < x1["hdi_95"][1]
    assert abs(x1["mean"] / (0.05 * k_over_m) - 1) < 0.2
    assert all(e["p_value"] > 1e-3 for e in entries if not e["alarm"])
    history = mon.twin.history
    assert [h["monitor"]["restarted"] for h in history[1:]] == [False, True, False, True, False, False]
    assert history[2]["prior"].startswith("spike-and-slab (restarted")
    assert history[3]["prior"].startswith("posterior of update 3")
    # One row per window; the terms ever selected as columns.
    header, *rows = timeline_csv(mon.timeline).splitlines()
    assert len(rows) == 6 and "pip[x2:x1]" in header and "mean[x2:sign(x2)]" in header
    assert rows[1].split(",")[3] == "True" and rows[1].split(",")[8] == "x2:x1"


def test_an_output_only_twin_from_accelerometers_flags_a_new_term_at_its_own_rate():
    """Ambient vibration read by accelerometers alone (no force, no displacement; 5% noise):
    zoo member 10's cubic hardening appears in window 2 of 10 s windows. The monitor of an
    output-only twin asks for its framework's false-alarm rate."""
    member = zoo.draw_member(10)
    assert member.family == "cubic-hardening"
    ex = member.example._replace(duration=10.0)
    windows = simulate_life(ex, jax.random.key(10), scale=[0.0, 0.0, 1.0], level=0.05, output_only=True)
    data = [{k: w[k] for k in ("t", "xdot", "xdot_names")} for w in windows]
    base = update_from_data("output-only", ex.system.nominal, data[0], library=ex.library_output_only,
                            settings=MONITOR_SETTINGS)
    mon = Monitor(base)
    assert mon.false_alarm == FALSE_ALARM["output-only"] == 5e-4
    assert Monitor(base, false_alarm=1e-3).false_alarm == 1e-3
    still, change = (mon.step(w, source=f"w{i}") for i, w in enumerate(data[1:], start=1))
    # measured: p = 1.0 for the stationary window, 2.0e-10 for the change
    assert not still["alarm"] and still["p_value"] > 0.5
    assert change["alarm"] and change["new_terms"] == ["x2:x1**3"] and change["p_value"] < 1e-9


@pytest.fixture
def files(life, tmp_path):
    ex, windows, base = life
    write_nominal(tmp_path / "nominal.toml", ex.system.nominal)
    for i, w in enumerate(windows):
        np.savez(tmp_path / f"w{i}.npz", **w)
    np.savez(tmp_path / "record.npz", **{k: np.concatenate([w[k] for w in windows]) for k in ("t", "x", "xdot", "u")})
    save_twin(base, tmp_path / "twin")
    return tmp_path


def _without_clocks(timeline):
    return [{k: v for k, v in w.items() if k != "seconds"} for w in timeline]


def test_a_resumed_monitor_has_the_history_of_an_uninterrupted_one(files, monkeypatch, capsys):
    tmp = files
    shutil.copytree(tmp / "twin", tmp / "again")
    windows = [str(tmp / f"w{i}.npz") for i in range(1, 5)]
    assert main(["monitor", str(tmp / "twin"), *windows, "--out", str(tmp / "m.json"), "--csv",
                 str(tmp / "m.csv"), "--plot", str(tmp / "m.png"), "--track", "x2:x1", "--critical", "100",
                 "--trend", "wiener"] + FAST) == 0
    full = json.loads((tmp / "m.json").read_text())
    assert full["false_alarm"] == FALSE_ALARM["input-output"] == 1e-3 and full["forget"] == 0.9  # the defaults
    rul = full.pop("remaining_life")
    assert rul["term"] == "x2:x1" and rul["windows"] == 4 and rul["critical"] == 100.0 and rul["trend"] == "wiener"
    # Four noisy windows: the walk may never get there, an unbounded interval (JSON null).
    assert rul["lower"] <= rul["median"] and rul["upper"] is None and rul["now"] == 4.0
    assert full["first_alarm"] == 1 and [w["alarm"] for w in full["windows"]] == [False, True, False, True]
    assert (tmp / "m.png").stat().st_size > 10_000 and len((tmp / "m.csv").read_text().splitlines()) == 5
    # Killed after the third window's twin was saved, before its timeline was written.
    import dtwin_jax.monitor.timeline as timeline

    calls = []

    def dies(path, tl, **kw):
        calls.append(len(tl))
        if len(tl) == 3:
            raise KeyboardInterrupt
        return write(path, tl, **kw)

    write = timeline.write_timeline
    monkeypatch.setattr(timeline, "write_timeline", dies)
    assert main(["monitor", str(tmp / "again"), *windows, "--out", str(tmp / "r.json")] + FAST) == 130
    monkeypatch.setattr(timeline, "write_timeline", write)
    assert len(json.loads((tmp / "r.json").read_text())["windows"]) == 2
    assert len(load_twin(tmp / "again").history) == 4  # the baseline and three windows
    capsys.readouterr()
    assert main(["monitor", str(tmp / "again"), *windows, "--out", str(tmp / "r.json")] + FAST) == 0
    out = capsys.readouterr().out
    assert out.count("already in the timeline; skipped") == 3
    resumed = json.loads((tmp / "r.json").read_text())
    assert "remaining_life" not in resumed
    assert _without_clocks(resumed["windows"]) == _without_clocks(full["windows"])
    a, b = load_twin(tmp / "twin"), load_twin(tmp / "again")
    for ea, eb in zip(a.equations, b.equations):
        assert np.array_equal(ea.theta, eb.theta) and np.array_equal(ea.gamma, eb.gamma)


def test_windows_cut_from_a_record_are_the_files_windows(files):
    tmp = files
    shutil.copytree(tmp / "twin", tmp / "a")
    shutil.copytree(tmp / "twin", tmp / "b")
    assert main(["monitor", str(tmp / "a"), str(tmp / "w1.npz"), str(tmp / "w2.npz"), "--out", str(tmp / "a.json")]
                + FAST) == 0
    record = tmp / "record.npz"
    data = dict(np.load(record))
    np.savez(record, **{k: v[1000:3000] for k, v in data.items()})
    assert main(["monitor", str(tmp / "b"), "--record", str(record), "--window", "1", "--out", str(tmp / "b.json")]
                + FAST) == 0
    a, b = (json.loads((tmp / f"{n}.json").read_text())["windows"] for n in "ab")
    assert [w["source"] for w in b] == ["record.npz[0:1000]", "record.npz[1000:2000]"]
    assert [w["t_start"] for w in b] == [1.0, 2.0]
    assert [w["p_value"] for w in a] == pytest.approx([w["p_value"] for w in b], rel=1e-9)


@pytest.mark.parametrize("case, message", [
    ("both", "give the windows as files, or one --record with --window (not both)"),
    ("no-window", "--window goes with --record"),
    ("not-a-twin", "is not a saved twin (no twin.json)"),
    ("false-alarm", "--false-alarm must be in (0, 1), got 2"),
    ("short-window", "--window 0.001 s is 1 samples"),
    ("nan", "bad.npz': 'x' contains NaN or infinite values"),
    ("track", "--track and --critical go together"),
])
def test_monitor_errors_are_one_line_and_keep_what_was_done(files, case, message, capsys):
    tmp = files
    w = [str(tmp / "w1.npz")]
    args = {"both": [str(tmp / "twin"), *w, "--record", str(tmp / "record.npz"), "--window", "1"],
            "no-window": [str(tmp / "twin"), "--record", str(tmp / "record.npz")],
            "not-a-twin": [str(tmp), *w],
            "false-alarm": [str(tmp / "twin"), *w, "--false-alarm", "2"],
            "short-window": [str(tmp / "twin"), "--record", str(tmp / "record.npz"), "--window", "0.001"],
            "track": [str(tmp / "twin"), *w, "--track", "x2:x1"]}
    if case == "nan":
        bad = dict(np.load(tmp / "w2.npz"))
        bad["x"][10, 0] = np.nan
        np.savez(tmp / "bad.npz", **bad)
        args["nan"] = [str(tmp / "twin"), *w, str(tmp / "bad.npz")]
    before = sorted(p.name for p in tmp.iterdir())
    assert main(["monitor", *args[case], "--out", str(tmp / "m.json")] + FAST) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    if case == "nan":  # the first window was tested, absorbed and written; the bad one left nothing
        assert [w["source"] for w in json.loads((tmp / "m.json").read_text())["windows"]] == w
        assert len(load_twin(tmp / "twin").history) == 2
    else:
        assert sorted(p.name for p in tmp.iterdir()) == before


def test_the_command_line_monitor_samples_as_the_python_monitor_does():
    from dtwin_jax.cli import _parser

    args = _parser().parse_args(["monitor", "twin", "w1.npz", "--out", "m.json"])
    assert (args.chains, args.draws, args.burn_in) == (
        MONITOR_SETTINGS.num_chains, MONITOR_SETTINGS.num_draws, MONITOR_SETTINGS.num_burnin)
