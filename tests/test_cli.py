"""The command line: bad input gets a one-line error and no output file; discover and demo work."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from dtwin_jax.cli import main

NOMINAL = "M = [[1.0]]\nC = [[2.0]]\nK = [[1000.0]]\nB = [[0.5]]\n"


def _data(N=400, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(N) * 1e-3
    x = np.stack([0.1 * np.cos(30 * t), -3 * np.sin(30 * t)], axis=1) + 1e-4 * rng.normal(size=(N, 2))
    u = rng.normal(size=(N, 1))
    return {"t": t, "x": x, "u": u}


@pytest.fixture
def files(tmp_path):
    (tmp_path / "nominal.toml").write_text(NOMINAL)
    return tmp_path


def _run(tmp_path, data, nominal_text=NOMINAL, extra=()):
    np.savez(tmp_path / "data.npz", **data)
    (tmp_path / "nominal.toml").write_text(nominal_text)
    out = tmp_path / "result.json"
    argv = ["discover", str(tmp_path / "data.npz"), "--nominal", str(tmp_path / "nominal.toml"),
            "--out", str(out), "--draws", "50", "--burn-in", "10", "--chains", "2", "--quiet", *extra]
    return main(argv), out


def _error_line(capsys):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("dtwin-jax: error: ")
    return err[0]


BAD_CASES = {
    "missing key": (lambda d: {k: v for k, v in d.items() if k != "x"}, NOMINAL, (), "missing key 'x'"),
    "mismatched shapes": (lambda d: {**d, "u": d["u"][:-5]}, NOMINAL, (), "'u' has 395 samples"),
    "wrong width": (lambda d: {**d, "x": np.hstack([d["x"], d["x"]])}, NOMINAL, (), "'x' has 4 columns"),
    "non-uniform time": (lambda d: {**d, "t": d["t"] ** 1.01}, NOMINAL, (), "not uniformly spaced"),
    "nan": (lambda d: {**d, "x": np.where(np.arange(400)[:, None] == 7, np.nan, d["x"])}, NOMINAL, (), "'x' contains NaN"),
    "inf": (lambda d: {**d, "u": np.where(np.arange(400)[:, None] == 9, np.inf, d["u"])}, NOMINAL, (), "'u' contains NaN or infinite"),
    "singular M": (lambda d: d, NOMINAL.replace("M = [[1.0]]", "M = [[0.0]]"), (), "singular"),
    "missing nominal key": (lambda d: d, NOMINAL.replace("K = [[1000.0]]\n", ""), (), "missing key 'K'"),
    "unknown family": (lambda d: d, NOMINAL, ("--library", "poly:2,bessel"), "unknown library family 'bessel'"),
    "duplicate columns": (lambda d: {**d, "x": np.abs(d["x"]) + 0.01}, NOMINAL, ("--library", "poly:1,abs"), "duplicates"),
    "all-zero column": (lambda d: {**d, "x": d["x"] * np.array([1.0, 0.0])}, NOMINAL, ("--library", "poly:2"), "zero"),
}


@pytest.mark.parametrize("case", list(BAD_CASES))
def test_bad_input_one_line_error_and_no_file(tmp_path, capsys, case):
    mutate, nominal_text, extra, message = BAD_CASES[case]
    code, out = _run(tmp_path, mutate(_data()), nominal_text, extra)
    line = _error_line(capsys)
    assert code != 0
    assert message in line, line
    assert not out.exists()
    assert not list(tmp_path.glob(".result.json*"))  # no temporary left behind


@pytest.mark.parametrize("argv", [
    ["discover", "data.npz"],  # --nominal missing
    ["discover", "data.npz", "--nominal", "n.toml", "--chains", "0"],
    ["frobnicate"],
    ["sweep", "--mode", "sideways"],
    ["monitor", "twin", "w1.npz", "--track", "x2:x1", "--critical", "1", "--trend", "cubic"],
])
def test_usage_errors_are_one_line_with_status_2(capsys, argv):
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2
    _error_line(capsys)


def test_unwritable_out_is_refused_before_any_work(tmp_path, capsys):
    # The data file does not exist: reaching it would be a different error.
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    for flag, target in (("--out", blocker / "result.json"), ("--out", tmp_path), ("--plot", blocker / "p.png")):
        argv = ["discover", str(tmp_path / "missing.npz"), "--nominal", str(tmp_path / "missing.toml"), flag, str(target)]
        assert main(argv) == 2
        assert "output" in _error_line(capsys)
    assert main(["sweep", "--out-dir", str(blocker)]) == 2
    assert "is not a folder" in _error_line(capsys)


def test_result_json_is_strict(tmp_path):
    from dtwin_jax.io import write_json

    write_json(tmp_path / "r.json", {"hdi": [float("nan"), 1.0], "rhat": float("inf"), "n": {"x": [2]}})
    text = (tmp_path / "r.json").read_text()
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"hdi": [None, 1.0], "rhat": None, "n": {"x": [2]}}


def test_discover_writes_the_result_file(tmp_path, capsys):
    code, out = _run(tmp_path, _data(), extra=("--library", "poly:3,input", "--plot", str(tmp_path / "pip.png")))
    assert code == 0
    doc = json.loads(out.read_text(), parse_constant=lambda c: pytest.fail(f"bare {c} in the result JSON"))
    assert doc["mode"] == "input-output" and doc["equations"][0]["state"] == "x2"
    assert set(doc["equations"][0]["pip"]) == {"1", "x1", "x2", "x1**2", "x1*x2", "x2**2", "x1**3", "x1**2*x2", "x1*x2**2", "x2**3", "u1"}
    assert (tmp_path / "pip.png").stat().st_size > 10_000


def test_csv_input(tmp_path, capsys):
    d = _data()
    rows = np.column_stack([d["t"], d["x"], d["u"]])
    (tmp_path / "data.csv").write_text("t,x1,x2,u1\n" + "\n".join(",".join(repr(float(v)) for v in r) for r in rows) + "\n")
    (tmp_path / "nominal.toml").write_text(NOMINAL)
    code = main(["discover", str(tmp_path / "data.csv"), "--nominal", str(tmp_path / "nominal.toml"),
                 "--library", "poly:2,input", "--draws", "30", "--burn-in", "5", "--chains", "2", "--quiet"])
    assert code == 0
    assert capsys.readouterr().out.startswith("x2:")


def test_demo_end_to_end(tmp_path, capsys):
    # In this process, as the next call: the command's own process set-up is tested in
    # test_runtime_set_up_is_the_command_line_s_only, and a process of its own would compile
    # every program again (under the command line's compiler flags).
    out = tmp_path / "demo"
    assert main(["demo", "--out-dir", str(out), "--draws", "300", "--burn-in", "100", "--chains", "2"]) == 0
    stdout = capsys.readouterr().out
    assert "x2: -" in stdout and "x1**3" in stdout
    doc = json.loads((out / "result.json").read_text())
    assert [t["expr"] for t in doc["equations"][0]["terms"]] == ["x1**3"]
    assert (out / "pip.png").stat().st_size > 10_000
    # The demo's own files feed `discover`.
    assert main(["discover", str(out / "measurements.npz"), "--nominal", str(out / "nominal.toml"),
                 "--library", "poly:3,input", "--draws", "200", "--burn-in", "100", "--chains", "2", "--quiet"]) == 0
    assert "x1**3" in capsys.readouterr().out


def test_runtime_set_up_is_the_command_line_s_only(tmp_path):
    """The `dtwin-jax` process pins itself and caches compiled programs; `main()` called from
    Python leaves the caller's process alone (`dtwin_jax.configure_runtime()` is the opt-in);
    a bad DTWIN_JAX_CORES or DTWIN_JAX_PLATFORM is a one-line error. `platform="cpu"` keeps JAX
    on the CPU (the command line's choice for single updates, where a GPU is slower)."""
    before = os.sched_getaffinity(0)
    assert main(["sweep", "--levels", "2", "--out-dir", str(tmp_path / "s")]) == 2  # fails fast, after set-up
    assert os.sched_getaffinity(0) == before
    for name, value in [("DTWIN_JAX_CORES", "many"), ("DTWIN_JAX_PLATFORM", "gpu")]:
        env = dict(os.environ, **{name: value})
        proc = subprocess.run([sys.executable, "-m", "dtwin_jax.cli", "sweep", "--levels", "0.1"],
                              capture_output=True, text=True, env=env, cwd=tmp_path)
        assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and name in proc.stderr, proc.stderr
    assert not (tmp_path / "dtwin-sweep").exists()  # the default --out-dir: nothing written
    code = ("from dtwin_jax import configure_runtime; import os, jax; print(configure_runtime(platform='cpu'), "
            "jax.default_backend(), jax.config.jax_platforms, len(os.sched_getaffinity(0)))")
    env = dict(os.environ, DTWIN_JAX_CACHE=str(tmp_path / "cache"), DTWIN_JAX_CORES="1")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True).stdout
    assert str(tmp_path / "cache") in out and out.strip().endswith("cpu cpu 1")


def test_the_command_line_s_cpu_programs_compile_at_llvm_level_2_unless_the_user_set_one(tmp_path):
    """`configure_runtime(platform="cpu")` appends XLA's backend optimization level 2 to
    $XLA_FLAGS (the sampler's chunk compiles 25% sooner and runs as fast:
    docs/performance.md); a level the user set stands, and `"auto"` (a GPU maybe) adds none."""
    # jax._src.compiler: the options XLA compiles with, as JAX builds them for every program.
    code = ("from dtwin_jax import configure_runtime; import os, sys; done = configure_runtime(platform=sys.argv[1]); "
            "from jax._src import compiler; "
            "print(compiler.get_compile_options(1, 1).executable_build_options.debug_options"
            ".xla_backend_optimization_level, os.environ.get('XLA_FLAGS', ''), 'xla_flags' in done)")
    for platform, flags, expected in [("cpu", None, "2 --xla_backend_optimization_level=2 True"),
                                      ("cpu", "--xla_backend_optimization_level=1", "1 --xla_backend_optimization_level=1 False"),
                                      ("auto", None, "3  False")]:
        env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_DISABLE_MOST_OPTIMIZATIONS")}
        env.update(DTWIN_JAX_CACHE="off", DTWIN_JAX_CORES="all", **({"XLA_FLAGS": flags} if flags else {}))
        out = subprocess.run([sys.executable, "-c", code, platform], capture_output=True, text=True, env=env,
                             check=True, cwd=tmp_path).stdout
        assert out.strip() == expected.strip() and out.count(" ") == 2, (platform, flags, out)
