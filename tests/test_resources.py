"""Issue 25: oversize requests are refused at once in one line, before anything is allocated
(:mod:`dtwin_jax.resources`); Ctrl-C, out of memory and internal errors are one line too."""

import io
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import types
import zipfile
from pathlib import Path

import numpy as np
import pytest
from test_store import _edit_header, _rehash

from dtwin_jax import resources
from dtwin_jax.cli import INTERRUPTED, main
from dtwin_jax.errors import DataError

ROOT = Path(__file__).resolve().parents[1]
NOMINAL = "M = [[1.0]]\nC = [[2.0]]\nK = [[1000.0]]\nB = [[0.5]]\n"
NOMINAL_2DOF = "M = [[1.0, 0.0], [0.0, 1.0]]\nC = [[2.0, 0.0], [0.0, 2.0]]\nK = [[1000.0, 0.0], [0.0, 500.0]]\n"
TINY = ["--draws", "50", "--burn-in", "10", "--chains", "2", "--quiet"]
# A refusal costs at most this many times the command line's import floor (`import
# dtwin_jax.cli`, which imports jax), measured in the same test: CPU time stretches with the load.
MAX_OVER_FLOOR, MAX_RSS_MB = 1.5, 500


def _data(N=400, states=2, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(N) * 1e-3
    x = np.stack([0.1 * np.cos(30 * t), -3 * np.sin(30 * t)], axis=1) + 1e-4 * rng.normal(size=(N, 2))
    x = np.concatenate([x, 0.5 * x[:, ::-1] + 1e-3 * rng.normal(size=(N, 2))], axis=1)[:, :states]
    return {"t": t, "x": x, "u": rng.normal(size=(N, states // 2))}


def _bomb(path):
    """An .npz of a few hundred bytes whose headers declare 1e10 samples of t and x (2 states)."""
    with zipfile.ZipFile(path, "w") as zf:
        for name, shape in (("t", (10**10,)), ("x", (10**10, 2))):
            header = io.BytesIO()
            np.lib.format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False, "shape": shape})
            zf.writestr(f"{name}.npy", header.getvalue() + bytes(64))


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """Data and nominal files, and a tiny twin saved by discover --save-twin."""
    tmp = tmp_path_factory.mktemp("resources")
    np.savez(tmp / "data.npz", **_data())
    np.savez(tmp / "data4.npz", **_data(states=4))
    (tmp / "nominal.toml").write_text(NOMINAL)
    (tmp / "nominal2.toml").write_text(NOMINAL_2DOF)
    (tmp / "huge.toml").write_text(NOMINAL + "extra_states = 100000000\n")
    np.savez(tmp / "new.npz", t=np.arange(400) * 1e-3, x0=np.array([0.1, 0.0]), u=np.zeros((400, 1)))
    assert main(["discover", str(tmp / "data.npz"), "--nominal", str(tmp / "nominal.toml"), "--library",
                 "poly:3,input", "--save-twin", str(tmp / "twin"), *TINY]) == 0
    _bomb(tmp / "bomb.npz")
    bad = tmp / "bad-twin"
    shutil.copytree(tmp / "twin", bad)
    _edit_header(bad, lambda h: h.update(num_inputs=1e8))
    _rehash(bad)  # a crafted twin passes its checksums; the size check must still refuse it
    return tmp


# Measures the command in a small process of its own: a child forked from pytest would count
# pytest's memory in its peak RSS (Linux records the forked copy's at exec).
_LAUNCHER = """
import json, os, subprocess, sys, time
start = time.perf_counter()
proc = subprocess.Popen(sys.argv[1:], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
err = proc.stderr.read()
_, status, use = os.wait4(proc.pid, 0)
proc.returncode = os.waitstatus_to_exitcode(status)
print(json.dumps({"code": proc.returncode, "err": err, "wall": time.perf_counter() - start,
                  "cpu": use.ru_utime + use.ru_stime, "rss_mb": use.ru_maxrss / 1024}))
"""


def _measured(argv, cwd, module=True) -> dict:
    """Run the command line (or, with ``module=False``, Python with ``argv``) in a fresh
    process: its exit ``code``, ``err`` (stderr), ``wall`` and ``cpu`` seconds and peak ``rss_mb``."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    command = ["-m", "dtwin_jax.cli", *argv] if module else argv
    out = subprocess.run([sys.executable, "-c", _LAUNCHER, sys.executable, *command], cwd=cwd,
                         env=env, capture_output=True, text=True, check=True).stdout
    return json.loads(out)


OVERSIZE = {
    "draws": (["discover", "data.npz", "--nominal", "nominal.toml", "--draws", "1000000000"],
              "--draws 1000000000 needs about"),
    "poly:40 on 4 states": (["discover", "data4.npz", "--nominal", "nominal2.toml", "--library", "poly:40"],
                            "library 'poly:40' has 135751 terms; at most 10000"),
    "extra_states": (["discover", "data.npz", "--nominal", "huge.toml"], "extra_states 100000000 needs about"),
    "twin num_inputs": (["predict", "bad-twin", "--input", "new.npz"], "header.json' has num_inputs 100000000.0; expected 0 or 1 (the nominal B's columns)"),
    "predict draws": (["predict", "twin", "--input", "new.npz", "--draws", "1000000000"],
                      "--draws 1000000000 needs about"),
    "a small file declaring huge arrays": (["discover", "bomb.npz", "--nominal", "nominal.toml"],
                                           "measurement file 'bomb.npz' needs about 671 GiB for its arrays"),
}


@pytest.mark.parametrize("case", list(OVERSIZE))
def test_oversize_request_is_refused_at_once_in_one_line(folder, case):
    argv, expected = OVERSIZE[case]
    out = "prediction.npz" if argv[0] == "predict" else "result.json"
    floor = _measured(["-c", "import dtwin_jax.cli"], folder, module=False)
    run = _measured([*argv, "--out", out], folder)
    code, err = run["code"], run["err"]
    print(f"{case}: wall {run['wall']:.2f} s, cpu {run['cpu']:.2f} s ({run['cpu'] / floor['cpu']:.2f}x the import "
          f"floor's {floor['cpu']:.2f} s), peak RSS {run['rss_mb']:.0f} MB: {err.strip()}")
    assert code == 2 and err.count("\n") == 1 and err.startswith("dtwin-jax: error: ") and expected in err, err
    # Wall time on a loaded machine (the 2 cores are shared) stretches with the load.
    load = max(1.0, os.getloadavg()[0] / os.cpu_count())
    assert run["cpu"] < MAX_OVER_FLOOR * floor["cpu"], (run, floor)
    assert run["wall"] < MAX_OVER_FLOOR * floor["wall"] * load and run["rss_mb"] < MAX_RSS_MB, (run, floor)
    assert not (folder / out).exists()


def test_count_terms_matches_the_parsed_library():
    from dtwin_jax.cli import _DEFAULT_LIBRARY
    from dtwin_jax.library import DEFAULT_LIBRARY, count_terms, parse_library

    assert _DEFAULT_LIBRARY == DEFAULT_LIBRARY
    for spec, m, n in [(DEFAULT_LIBRARY, 2, 1), (DEFAULT_LIBRARY, 4, 2), ("poly:3,expx,terms:u2;sin(x3)*1", 3, 2),
                       ("poly:6,sign,abs,xabs,exp,expxx,sin,cos", 6, 0), ("poly:1,cos", 1, 0)]:
        assert count_terms(spec, m, n) == parse_library(spec, m, n).K, spec
    assert count_terms("poly:40", 4, 0) == 135751


@pytest.mark.parametrize("spec, m, n, message", [
    ("poly:40", 4, 0, "has 135751 terms; at most 10000"),
    ("poly:1000000000", 4, 0, "has 4.17e+34 terms"),
    ("poly:100000", 5000, 0, "has more than 1e+300 terms"),
    ("sign", 2, 10**8, "num_inputs <= 10000, got 100000000"),
])
def test_parse_library_refuses_a_huge_library_before_building_it(spec, m, n, message):
    from dtwin_jax.library import parse_library

    start = time.perf_counter()
    with pytest.raises(DataError, match=re.escape(message)):
        parse_library(spec, m, n)
    assert time.perf_counter() - start < 0.1


def test_api_entry_points_check_before_allocating(folder, monkeypatch):
    from dtwin_jax import LinearSecondOrder
    from dtwin_jax.io.store import load_twin
    from dtwin_jax.models.prediction import posterior_twins, predict
    from dtwin_jax.update import (
        SamplerSettings,
        update_input_output,
        update_output_only,
    )

    with pytest.raises(DataError, match="extra_states 100000000 needs about .* for the nominal model"):
        LinearSecondOrder.create([[1.0]], [[1.0]], [[1.0]], extra_states=100_000_000)
    nominal = LinearSecondOrder.create([[1.0]], [[2.0]], [[1000.0]], [[0.5]])
    d = _data()
    huge = SamplerSettings(num_draws=10**9)
    with pytest.raises(DataError, match=r"^num_draws 1000000000 needs about .* \(1 equation x 4 chains x"):
        update_input_output(nominal, d["t"], d["x"], d["u"], library="poly:2,input", settings=huge)
    with pytest.raises(DataError, match=r"^num_draws 1000000000 needs about"):
        update_output_only(nominal, d["t"], d["x"], library="poly:2", settings=huge)
    result = load_twin(folder / "twin")
    with pytest.raises(DataError, match=r"^num_draws 1000000000 needs about .* for the posterior twins"):
        posterior_twins(result, 10**9)
    twins = posterior_twins(result, 5)
    monkeypatch.setattr(resources, "available_bytes", lambda: 1000)
    with pytest.raises(DataError, match=r"^draws 5 needs about .* for the predicted paths \(5 draws x 400 samples x "
                                        r"2 states\); 1000 bytes is available"):
        predict(twins, np.zeros(2), d["t"], d["u"])
    with pytest.raises(DataError, match="design matrix"):
        resources.check_design(10**6, 50, 2)


def test_available_memory_is_read():
    avail = resources.available_bytes()
    assert 2**20 < avail < 2**62
    assert resources.size_text(37 * 2**30) == "37 GiB" and resources.size_text(1.5 * 2**40) == "1.5 TiB"


def _fail_with(monkeypatch, exc):
    import dtwin_jax.input_output.update as io_update

    def boom(*args, **kwargs):
        raise exc

    monkeypatch.setattr(io_update, "update_input_output", boom)


def _discover(folder):
    return main(["discover", str(folder / "data.npz"), "--nominal", str(folder / "nominal.toml"),
                 "--out", str(folder / "oom.json"), *TINY])


@pytest.mark.parametrize("exc, expected", [
    (MemoryError("Unable to allocate 137 GiB for an array with shape (135751, 135751) and data type float64"),
     "out of memory: Unable to allocate 137 GiB for an array with shape (135751, 135751) and data type float64; "
     "try fewer --draws/--chains or a smaller --library"),
    (MemoryError(), "out of memory: MemoryError; try fewer"),
    ("jax", "out of memory: RESOURCE_EXHAUSTED: Out of memory while trying to allocate 8589934592 bytes.; try fewer"),
])
def test_out_of_memory_is_one_line(folder, monkeypatch, capsys, exc, expected):
    if exc == "jax":
        import jax

        exc = jax.errors.JaxRuntimeError(
            "RESOURCE_EXHAUSTED: Out of memory while trying to allocate 8589934592 bytes.\nBufferAssignment OOM Debugging.")
    _fail_with(monkeypatch, exc)
    assert _discover(folder) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"dtwin-jax: error: {expected}"), err
    assert not (folder / "oom.json").exists()


def test_internal_error_is_one_line_unless_debugging(folder, monkeypatch, capsys):
    _fail_with(monkeypatch, ZeroDivisionError("float division by zero\nsecond line"))
    assert _discover(folder) == 1
    err = capsys.readouterr().err
    assert err == ("dtwin-jax: error: internal error: ZeroDivisionError: float division by zero "
                   "(set DTWIN_JAX_DEBUG=1 for the traceback)\n")
    monkeypatch.setenv("DTWIN_JAX_DEBUG", "1")
    with pytest.raises(ZeroDivisionError):
        _discover(folder)


def test_keyboard_interrupt_in_process(folder, monkeypatch, capsys):
    _fail_with(monkeypatch, KeyboardInterrupt())
    assert _discover(folder) == 130
    assert capsys.readouterr().err == INTERRUPTED + "\n"


def test_outputs_are_written_with_ctrl_c_held():
    from dtwin_jax.cli import _uninterrupted

    before = signal.getsignal(signal.SIGINT)
    with _uninterrupted():
        os.kill(os.getpid(), signal.SIGINT)  # held: the block runs to its end
        time.sleep(0.05)
    assert signal.getsignal(signal.SIGINT) is before


# The command as a shell starts it, with Ctrl-C's default action: pytest-xdist's workers
# ignore SIGINT, and a program started with SIGINT ignored keeps ignoring it.
_DEFAULT_SIGINT = ("import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); "
                   "os.execv(sys.executable, [sys.executable, '-m', 'dtwin_jax.cli', *sys.argv[1:]])")


def test_ctrl_c_stops_a_run_in_one_line_and_leaves_no_file(tmp_path):
    """SIGINT a few seconds into a long discover: exit 130, one line, no result or temporary file."""
    np.savez(tmp_path / "data.npz", **_data(N=2000))
    (tmp_path / "nominal.toml").write_text(NOMINAL)
    before = sorted(p.name for p in tmp_path.iterdir())
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen(
        [sys.executable, "-c", _DEFAULT_SIGINT, "discover", "data.npz", "--nominal", "nominal.toml", "--out", "r.json",
         "--save-twin", "twin", "--draws", "200000", "--chains", "2"],
        cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(4)
    assert proc.poll() is None, proc.communicate()
    proc.send_signal(signal.SIGINT)
    start = time.perf_counter()
    _, err = proc.communicate(timeout=60)
    print(f"exit {proc.returncode} {time.perf_counter() - start:.2f} s after SIGINT")
    lines = [line.strip() for line in re.split(r"[\r\n]", err) if line.strip()]
    assert proc.returncode == 130 and lines[-1] == INTERRUPTED and "Traceback" not in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == before


_INTERRUPT_IN_STRING_EXEC = """import sys
from dtwin_jax.cli import _interrupted
try:
    exec("raise KeyboardInterrupt")
except KeyboardInterrupt:
    sys.exit(_interrupted())
"""


def test_an_interrupt_inside_a_string_exec_still_exits_130_under_python_m(tmp_path):
    """CPython 3.12 under ``python -m`` dies by SIGINT (-2) after a caught Ctrl-C that ended in a
    string ``exec`` (a namedtuple's or sympy's), whatever status the handler returned; the CLI's
    handler clears that. (The bare ``sys.exit(130)`` there exits -2: measured on 3.12.1.)"""
    (tmp_path / "interrupted_in_exec.py").write_text(_INTERRUPT_IN_STRING_EXEC)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), str(ROOT)]))
    proc = subprocess.run([sys.executable, "-m", "interrupted_in_exec"], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 130 and proc.stderr.strip() == INTERRUPTED, proc.stderr


def test_demo_records_are_checked(tmp_path, capsys):
    assert main(["demo", "--mode", "output-only", "--records", "1000000000", "--out-dir", str(tmp_path / "demo")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("dtwin-jax: error: --records 1000000000 needs about") and err.count("\n") == 1, err
    assert not (tmp_path / "demo").exists()


def test_a_ctrl_c_lost_in_a_callback_is_raised_again():
    """A KeyboardInterrupt raised inside a garbage-collector callback (where jaxlib's lands)
    is reported to ``sys.unraisablehook`` and lost; the CLI's hook raises it again in the
    main thread once the callback is over. Other reports pass on to the previous hook."""
    import gc

    from dtwin_jax.cli import _keep_interrupts

    reported = []
    fired = []

    def callback(phase, info):
        if phase == "start" and not fired:
            fired.append(True)
            raise KeyboardInterrupt

    before_hook, before_signal = sys.unraisablehook, signal.signal(signal.SIGINT, signal.default_int_handler)
    sys.unraisablehook = _keep_interrupts(reported.append)
    gc.callbacks.append(callback)
    try:
        with pytest.raises(KeyboardInterrupt):
            gc.collect()  # the callback's interrupt is unraisable here
            for _ in range(200):
                time.sleep(0.01)
        other = types.SimpleNamespace(exc_value=ValueError("x"))
        sys.unraisablehook(other)
        assert fired and reported == [other]
    finally:
        gc.callbacks.remove(callback)
        sys.unraisablehook = before_hook
        signal.signal(signal.SIGINT, before_signal)
