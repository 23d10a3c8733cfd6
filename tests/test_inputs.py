"""Issue 25's smaller cases: bad nominal models, complex or boolean data, epoch timestamps,
odd CSV files, file modes, coefficient and diagnostics formats, progress in redirected output.

Every bad input gets one line naming the problem (a ``DataError``; the command line prints
``dtwin-jax: error: ...``, exits 2 and writes no file)."""

import json
import os
import re
import stat
import sys

import numpy as np
import pytest

from dtwin_jax.cli import main
from dtwin_jax.data import check_records, uniform_times
from dtwin_jax.errors import DataError
from dtwin_jax.io import load_measurements, load_nominal, write_json
from dtwin_jax.models import zoo
from dtwin_jax.models.systems import EXAMPLES, LinearSecondOrder
from dtwin_jax.posterior import format_coefficient, format_equation
from dtwin_jax.progress import Stages, draws_bars

NOMINAL = "M = [[1.0]]\nC = [[2.0]]\nK = [[1000.0]]\nB = [[0.5]]\n"
SHORT = ("--draws", "50", "--burn-in", "10", "--chains", "2", "--library", "poly:3,input")


def _data(N=400, t0=0.0, seed=0):
    rng = np.random.default_rng(seed)
    s = np.arange(N) * 1e-3
    x = np.stack([0.1 * np.cos(30 * s), -3 * np.sin(30 * s)], axis=1) + 1e-4 * rng.normal(size=(N, 2))
    return {"t": t0 + s, "x": x, "u": rng.normal(size=(N, 1))}


def _one_line(err: DataError) -> str:
    text = str(err)
    assert "\n" not in text and text
    return text


# --- 1 and 3: nominal models ---------------------------------------------------------------

BAD_MODELS = {
    "negative mass": (([[-1.0]], [[1.0]], [[1.0]]), {}, r"^nominal mass matrix M is not positive definite$"),
    "indefinite": (([[1.0, 2.0], [2.0, 1.0]], np.eye(2), np.eye(2)), {}, "M is not positive definite"),
    "nonsymmetric": (([[1.0, 0.5], [0.4, 1.0]], np.eye(2), np.eye(2)), {}, r"M is not symmetric \(largest \|M - M\^T\| = 0\.1\)"),
    "singular": (([[0.0]], [[1.0]], [[1.0]]), {}, "M is singular"),
    "F0 overflows": (([[1.0]], [[2.0]], [[1.0]]), {"F0": [1e308]}, r"^nominal M\^-1 F0 has entries beyond 1e150"),
    "K over tiny M": (([[1e-200]], [[2.0]], [[1e-40]]), {}, r"^nominal M\^-1 K has entries beyond 1e150"),
    "B overflows": (([[0.5]], [[2.0]], [[1.0]], [[1e308]]), {}, r"^nominal M\^-1 B has entries"),
    "infinite C": (([[1.0]], [[np.inf]], [[1.0]]), {}, "nominal C has non-finite entries"),
    "complex M": (([[1.0 + 1.0j]], [[1.0]], [[1.0]]), {}, r"^nominal M must hold real numbers, got complex values$"),
    "boolean K": (([[1.0]], [[1.0]], [[True]]), {}, "nominal K must hold real numbers, got boolean values"),
    "string F0": (([[1.0]], [[1.0]], [[1.0]]), {"F0": ["1"]}, "nominal F0 must hold real numbers, got string values"),
}


@pytest.mark.parametrize("case", list(BAD_MODELS))
def test_create_refuses_bad_nominal_models(case):
    args, kwargs, message = BAD_MODELS[case]
    with pytest.raises(DataError, match=message) as err:
        LinearSecondOrder.create(*args, **kwargs)
    _one_line(err.value)


def test_good_nominal_models_and_every_example_still_build():
    # Symmetric to rounding (a product of decimal inputs) and large but sane gains pass.
    M = np.array([[2.0, 0.1 + 0.2], [0.3, 2.0]])
    model = LinearSecondOrder.create(M, np.eye(2), 1e12 * np.eye(2), F0=[1e100, 0.0])
    assert model.d == 2
    for build in EXAMPLES.values():
        assert build().system.nominal.d >= 1
    rng = np.random.default_rng(0)
    for _ in range(25):  # the zoo's random nominals: Rayleigh-damped chains, SDOFs
        assert zoo._draw_chain(rng).model.d == 2 and zoo._draw_sdof(rng).model.d == 1


BAD_TOML = {
    "boolean M": ("M = [[true]]\nC = [[2.0]]\nK = [[1.0]]\n", r"^'M' in '.*n\.toml' has the entry true, not a number$"),
    "boolean among numbers": ("M = [[1.0, 0.0], [0.0, false]]\nC = [[2.0]]\nK = [[1.0]]\n", "'M' in .* has the entry false"),
    "string C": ('M = [[1.0]]\nC = [["2.0"]]\nK = [[1.0]]\n', r"'C' in .* has the entry '2\.0', not a number"),
    "boolean F0": ("M = [[1.0]]\nC = [[2.0]]\nK = [[1.0]]\nF0 = [true]\n", "'F0' in .* has the entry true"),
    "boolean B": ("M = [[1.0]]\nC = [[2.0]]\nK = [[1.0]]\nB = [[1, true]]\n", "'B' in .* has the entry true"),
    "negative mass": ("M = [[-1.0]]\nC = [[2.0]]\nK = [[1.0]]\n", "M is not positive definite"),
    "huge F0": ("M = [[1.0]]\nC = [[2.0]]\nK = [[1.0]]\nF0 = [1e308]\n", r"M\^-1 F0 has entries beyond 1e150"),
    "not UTF-8": ("M = [[1.0]]\n# \xe9\n".encode("latin-1"), r"^nominal model file '.*n\.toml' is not UTF-8 text$"),
}


@pytest.mark.parametrize("case", list(BAD_TOML))
def test_nominal_file_refuses_booleans_strings_and_bad_models(tmp_path, case):
    text, message = BAD_TOML[case]
    path = tmp_path / "n.toml"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(DataError, match=message) as err:
        load_nominal(path)
    _one_line(err.value)


def test_integer_entries_still_read_as_numbers(tmp_path):
    (tmp_path / "n.toml").write_text("M = [[1]]\nC = [[2]]\nK = [[1000]]\nB = [[1, 2]]\nF0 = [0]\n")
    model = load_nominal(tmp_path / "n.toml")
    assert float(model.K[0, 0]) == 1000.0 and model.n == 2


# --- 2: complex, boolean and string data ---------------------------------------------------


@pytest.mark.parametrize("key, value, word", [
    ("x", np.ones((20, 2)) * (1 + 1j), "complex"),
    ("x", np.ones((20, 2), dtype=bool), "boolean"),
    ("u", np.full((20, 1), "1.0"), "string"),
    ("t", np.arange(20) * (1e-3 + 0j), "complex"),
])
def test_measurement_file_refuses_non_real_arrays(tmp_path, key, value, word):
    data = {"t": np.arange(20) * 1e-3, "x": np.ones((20, 2)), "u": np.ones((20, 1)), key: value}
    np.savez(tmp_path / "d.npz", **data)
    with pytest.raises(DataError, match=rf"^'{key}' in '.*d\.npz' must hold real numbers, got {word} values$"):
        load_measurements(tmp_path / "d.npz")


@pytest.mark.parametrize("key", ["t", "x", "u", "xdot"])
def test_check_records_refuses_complex_arrays(key):
    data = {"t": np.arange(20) * 1e-3, "x": np.ones((20, 2)), "u": np.ones((20, 1)), "xdot": np.ones((20, 2))}
    data[key] = data[key] * (1 + 1e-3j)
    with pytest.raises(DataError, match=rf"^'{key}' must hold real numbers, got complex values$"):
        check_records(data["t"], data["x"], data["u"], data["xdot"])
    data[key] = np.zeros(data[key].shape, dtype=bool)
    with pytest.raises(DataError, match=rf"^'{key}' must hold real numbers, got boolean values$"):
        check_records(data["t"], data["x"], data["u"], data["xdot"])


# --- 4: uniform spacing relative to the step -------------------------------------------------


@pytest.mark.parametrize("t0, dt", [(0.0, 1e-3), (1e9, 1e-3), (1.7e9, 1e-3), (1.7e9, 1e-4), (-5.0, 0.25)])
def test_epoch_timestamps_are_uniform_and_rebased(t0, dt):
    N = 2000
    t = t0 + np.arange(N) * dt
    out = uniform_times(t)
    assert out[0] == 0.0 and np.all(np.diff(out) > 0)
    # One grid step, known to the rounding of the stored ends over the record's span.
    rtol = 1e-12 + 2 * np.spacing(np.abs(t).max()) / (t[-1] - t[0])
    np.testing.assert_allclose(np.diff(out), dt, rtol=rtol)
    np.testing.assert_allclose(np.diff(out), np.diff(out)[0], rtol=1e-9)  # uniform, unlike t's
    rec = check_records(t, np.zeros((N, 2)))
    assert rec.t[0] == 0.0 and rec.dt == pytest.approx(dt, rel=rtol)


def test_windows_cut_at_any_offset_have_one_step_bit_for_bit():
    # (t[-1] - t[0]) / (N - 1) takes 6 values a few ulps apart over these 200 windows; the
    # programs keyed on dt compiled once for each.
    steps = {float(uniform_times(t0 + k + np.arange(1000) * 1e-3)[1]) for k in range(200) for t0 in (0.0, 1.7e9)}
    assert steps == {1e-3}


def test_printed_timestamps_within_a_percent_of_the_step_pass():
    # 1024 Hz printed to the microsecond: steps 976 and 977 us around 976.5625 us.
    t = np.round(np.arange(500) / 1024, 6)
    assert uniform_times(t)[-1] == pytest.approx(499 / 1024, rel=1e-6)


@pytest.mark.parametrize("make", [
    lambda t: np.delete(t, 100),  # a dropped sample: one step twice as long
    lambda t: t**1.01,  # a drifting clock
    lambda t: np.where(np.arange(t.size) == 50, t + 2e-5, t),  # 2% of a step off on one sample
    lambda t: t[::-1],  # decreasing
    lambda t: 1e16 + t,  # beyond float64 resolution: equal times
])
def test_non_uniform_times_are_refused(make):
    t = make(np.arange(400) * 1e-3)
    with pytest.raises(DataError, match=r"^'t' is not uniformly spaced \(steps from .* s\)$"):
        uniform_times(t)


def _discover(tmp_path, data, name, *extra):
    np.savez(tmp_path / f"{name}.npz", **data)
    out = tmp_path / f"{name}.json"
    code = main(["discover", str(tmp_path / f"{name}.npz"), "--nominal", str(tmp_path / "nominal.toml"),
                 "--out", str(out), "--quiet", *SHORT, *extra])
    assert code == 0
    return json.loads(out.read_text())


def test_discover_with_epoch_times_matches_times_from_zero(tmp_path):
    (tmp_path / "nominal.toml").write_text(NOMINAL)
    base = _discover(tmp_path, _data(), "zero")
    for t0 in (1e9, 1.7e9):
        doc = _discover(tmp_path, _data(t0=t0), f"epoch{t0:.0e}")
        for a, b in zip(base["equations"], doc["equations"]):
            assert [t["expr"] for t in a["terms"]] == [t["expr"] for t in b["terms"]]
            for ta, tb in zip(a["terms"], b["terms"]):
                assert tb["mean"] == pytest.approx(ta["mean"], rel=1e-3, abs=1e-6 * abs(ta["std"]) + 1e-9)


# --- 5: odd CSV files ------------------------------------------------------------------------

ROWS = "".join(f"{i * 1e-3!r},{float(np.cos(i / 10))!r},{float(np.sin(i / 10))!r}\n" for i in range(20))
BAD_CSV = {
    "not UTF-8": ("t,x1,x2\n".encode() + ROWS.encode() + b"0.02,\xe9,1\n", r"^measurement file '.*d\.csv' is not UTF-8 text$"),
    "UTF-16": (("t,x1,x2\n" + ROWS).encode("utf-16"), "is not UTF-8 text"),
    "empty": (b"", r"^measurement file '.*d\.csv' is empty$"),
    "blank lines only": (b"\n \n\n", "is empty"),
    "header only": (b"t,x1,x2\n", r"^measurement file '.*d\.csv' has a header but no data rows$"),
    "ragged row": (("t,x1,x2\n" + ROWS + "0.02,1.0\n").encode(), r"^'.*d\.csv' line 22 has 2 values but its header names 3$"),
    "long row": (("t,x1,x2\n" + ROWS + "0.02,1.0,2.0,3.0\n").encode(), "line 22 has 4 values"),
    "text value": (("t,x1,x2\n" + ROWS + "0.02,abc,1.0\n").encode(), r"line 22 has a non-numeric value 'abc'$"),
    "empty field": (("t,x1,x2\n0.0,,1.0\n" + ROWS).encode(), r"line 2 has a non-numeric value ''$"),
    "duplicate column": (("t,x1,x1\n" + ROWS).encode(), r"names column 'x1' more than once$"),
}


@pytest.mark.parametrize("case", list(BAD_CSV))
def test_odd_csv_files_get_one_line_errors(tmp_path, case):
    raw, message = BAD_CSV[case]
    (tmp_path / "d.csv").write_bytes(raw)
    with pytest.raises(DataError, match=message) as err:
        load_measurements(tmp_path / "d.csv")
    _one_line(err.value)


def test_csv_with_bom_crlf_and_blank_lines_reads(tmp_path):
    text = "t,x1,x2\r\n" + ROWS.replace("\n", "\r\n") + "\r\n\r\n"
    (tmp_path / "d.csv").write_bytes(b"\xef\xbb\xbf" + text.encode())
    data = load_measurements(tmp_path / "d.csv")
    assert data["x_names"] == ["x1", "x2"] and data["x"].shape == (20, 2)
    assert data["t"][1] == 1e-3


def test_command_line_bad_csv_is_one_line_and_no_file(tmp_path, capsys):
    (tmp_path / "nominal.toml").write_text(NOMINAL)
    (tmp_path / "x.csv").write_bytes("t,x1,x2\n".encode() + ROWS.encode("latin-1") + "0.02,\xe9,1\n".encode("latin-1"))
    out = tmp_path / "r.json"
    code = main(["discover", str(tmp_path / "x.csv"), "--nominal", str(tmp_path / "nominal.toml"), "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err == [f"dtwin-jax: error: measurement file '{tmp_path / 'x.csv'}' is not UTF-8 text"]
    assert not out.exists()


@pytest.mark.parametrize("nominal, message", [
    (NOMINAL.replace("M = [[1.0]]", "M = [[-1.0]]"), "M is not positive definite"),
    (NOMINAL + "F0 = [1e308]\n", r"M^-1 F0 has entries beyond 1e150"),
    (NOMINAL.replace("M = [[1.0]]", "M = [[true]]"), "has the entry true, not a number"),
])
def test_command_line_bad_nominal_is_one_line_and_no_file(tmp_path, capsys, nominal, message):
    (tmp_path / "nominal.toml").write_text(nominal)
    np.savez(tmp_path / "d.npz", **_data())
    out = tmp_path / "r.json"
    code = main(["discover", str(tmp_path / "d.npz"), "--nominal", str(tmp_path / "nominal.toml"), "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith("dtwin-jax: error: ") and message in err[0]
    assert not out.exists()


# --- 6, 8, 9: file modes, printed diagnostics, no progress bars in redirected output ---------


@pytest.fixture
def umask():
    """Set the umask for one test (the writers read it at each write)."""
    old = os.umask(0o022)
    os.umask(old)
    yield os.umask
    os.umask(old)


def test_write_json_follows_the_umask(tmp_path, umask):
    for mask, mode in ((0o022, 0o644), (0o077, 0o600), (0o002, 0o664)):
        umask(mask)
        write_json(tmp_path / f"r{mask:o}.json", {"a": 1})
        assert stat.S_IMODE((tmp_path / f"r{mask:o}.json").stat().st_mode) == mode


def test_discover_output_modes_diagnostics_and_no_bars_in_redirected_stderr(tmp_path, capsys, umask, monkeypatch):
    """One discover run with progress on and standard error captured (not a terminal)."""
    monkeypatch.delitem(sys.modules, "ipykernel", raising=False)
    umask(0o022)
    (tmp_path / "nominal.toml").write_text(NOMINAL)
    np.savez(tmp_path / "d.npz", **_data())
    out, png = tmp_path / "r.json", tmp_path / "pip.png"
    code = main(["discover", str(tmp_path / "d.npz"), "--nominal", str(tmp_path / "nominal.toml"),
                 "--out", str(out), "--plot", str(png), *SHORT])
    captured = capsys.readouterr()
    assert code == 0
    assert stat.S_IMODE(out.stat().st_mode) == 0o644 and stat.S_IMODE(png.stat().st_mode) == 0o644
    assert "\r" not in captured.err and "\x1b" not in captured.err and "stages" not in captured.err
    line = [s for s in captured.out.splitlines() if s.startswith("diagnostics: ")]
    assert len(line) == 1
    assert re.fullmatch(r"diagnostics: R-hat max (\d\.\d{4}|n/a), bulk ESS min (\d+|n/a), largest PIP disagreement "
                        r"between chains \d\.\d{3}, checks (passed|failed: \d+ of \d+), \d+\.\d s", line[0]), line[0]
    doc = json.loads(out.read_text())
    diag = doc["diagnostics"]
    for key in ("chains", "draws", "rhat_max", "ess_bulk_min", "seconds"):  # formats.md's keys
        assert key in diag
    if diag["rhat_max"] is not None:
        assert diag["rhat_max"] == round(diag["rhat_max"], 4)
    if diag["ess_bulk_min"] is not None:
        assert diag["ess_bulk_min"] == round(diag["ess_bulk_min"])
    # The summary prints every selected coefficient as format_coefficient does.
    terms = [t for e in doc["equations"] for t in e["terms"]]
    assert terms
    for t in terms:
        text = format_coefficient(t["mean"], t["std"]).lstrip("-")
        expr = "" if t["expr"] == "1" else f" {t['expr']}"  # a constant term is written bare
        assert f"{text}{expr}" in captured.out, (text, captured.out)
        assert re.fullmatch(r"\d{1,3}\.\d{1,3}(e-?\d+)?\(±\d+\.\d{1,3}(e-?\d+)?\)", text), text


class _Terminal:
    """A standard error that says it is a terminal and keeps what is written."""

    def __init__(self):
        self.text = ""

    def write(self, s):
        self.text += s

    def flush(self):
        pass

    def isatty(self):
        return True


def test_progress_bars_only_on_a_terminal(monkeypatch, capsys):
    monkeypatch.delitem(sys.modules, "ipykernel", raising=False)
    assert not draws_bars()  # captured: a pipe
    with Stages(True, 2, "update") as stages:
        with stages("one"):
            pass
    assert capsys.readouterr().err == "" and "one" in stages.seconds
    term = _Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    assert draws_bars()
    with Stages(True, 2, "update") as stages:
        with stages("one"):
            pass
    assert "update" in term.text and "\r" in term.text


def test_progress_in_a_jupyter_kernel(monkeypatch):
    monkeypatch.setitem(sys.modules, "ipykernel", sys)  # any module: only its presence counts
    assert draws_bars()


# --- 7: coefficients in engineering notation -------------------------------------------------


@pytest.mark.parametrize("mean, std, text", [
    (-99821.0, 506.0, "-99.82e3(±0.51e3)"),
    (1e5, 3.0, "100.0e3(±0.0e3)"),
    (-1.234567e-13, 5e-15, "-123.5e-15(±5.0e-15)"),
    (4.2e-13, 1e-13, "420.0e-15(±100.0e-15)"),
    (2.0004, 0.007, "2.000(±0.007)"),
    (-629139.0, 2386.0, "-629.1e3(±2.4e3)"),
    (0.010021, 1e-5, "10.02e-3(±0.01e-3)"),
    (0.247, 0.006, "247.0e-3(±6.0e-3)"),
    (999.96, 1.0, "1.000e3(±0.001e3)"),  # rounds up into the next exponent
    (1.5, 300.0, "1.500(±300.000)"),
    (-99821.0, 0.0, "-99.82e3"),  # zero std: the mean alone
    (-1e-13, float("nan"), "-100.0e-15"),
    (0.0, 0.005, "0.000e-3(±5.000e-3)"),  # a zero mean takes the std's exponent
    (-0.0, 0.0, "0"),
    (float("nan"), 1.0, "nan"),
    (float("-inf"), 1.0, "-inf"),
    (float("inf"), float("inf"), "inf"),
    (5e-324, 0.0, "4.941e-324"),  # no overflow shifting a denormal
])
def test_format_coefficient_engineering_notation(mean, std, text):
    assert format_coefficient(mean, std) == text


def test_format_equation_signs_and_small_coefficients():
    terms = [{"expr": "x1**3", "mean": -99821.0, "std": 506.0}, {"expr": "1", "mean": -2.5e-13, "std": 1e-14},
             {"expr": "x2", "mean": 3e-13, "std": 0.0}]
    assert format_equation("x2", terms) == "x2: -99.82e3(±0.51e3) x1**3 - 250.0e-15(±10.0e-15) + 300.0e-15 x2"
    assert format_equation("x2", [], "diffusion") == "x2 [diffusion]: 0"


def test_simulation_does_not_depend_on_the_time_origin():
    """simulate (and so predict) starts time at 0: a time-invariant system under a sampled
    input gives the same states from epoch timestamps, to their float64 rounding."""
    import jax.numpy as jnp

    from dtwin_jax.models.systems import example1, simulate

    ex = example1()
    s = np.arange(200) * 1e-3
    u = np.sin(40 * s)[:, None]
    ref, _ = simulate(ex.system, ex.x0, jnp.asarray(s), jnp.asarray(u))
    for t0 in (1e9, 1.7e9):
        x, xdot = simulate(ex.system, ex.x0, jnp.asarray(t0 + s), jnp.asarray(u))
        assert np.all(np.isfinite(np.asarray(xdot)))
        # Stored times are off by up to 1.2e-7 s (2.4e-7 at 1.7e9): x moves by |xdot| * that.
        np.testing.assert_allclose(np.asarray(x), np.asarray(ref), atol=1e-5 * float(np.abs(ref).max()) + 1e-6)
