"""A twin folder is untrusted and shared: damaged or crafted files get one line and exit 2,
saving deletes nothing it did not write, is atomic under kills and locked against
concurrent updates, and writes with the user's umask (issue 25)."""

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from dtwin_jax.io import store
from dtwin_jax.cli import main
from dtwin_jax.errors import DataError
from dtwin_jax.io import write_nominal
from dtwin_jax.io.store import load_twin, locked, save_twin
from test_lifecycle import _window

TINY = ["--chains", "2", "--draws", "200", "--burn-in", "100", "--quiet"]
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """Example 1 from one window, saved as ``twin``; two more windows and a prediction input."""
    tmp = tmp_path_factory.mktemp("store")
    ex = _window(tmp / "w1.npz", 0)
    _window(tmp / "w2.npz", 10)
    _window(tmp / "w3.npz", 20)
    write_nominal(tmp / "nominal.toml", ex.system.nominal)
    t = np.arange(200) * ex.dt
    np.savez(tmp / "new.npz", t=t, x0=np.zeros(2), u=np.zeros((t.size, 1)))
    assert main(["discover", str(tmp / "w1.npz"), "--nominal", str(tmp / "nominal.toml"),
                 "--save-twin", str(tmp / "twin")] + TINY) == 0
    return tmp


def _copy(saved, tmp_path, name="twin") -> Path:
    shutil.copytree(saved / "twin", tmp_path / name)
    return tmp_path / name


def _content(twin) -> Path:
    return twin / json.loads((twin / "twin.json").read_text())["current"]


def _rehash(twin) -> None:
    """Recompute the manifest's checksums: a crafted twin passes them, the readers must not."""
    manifest = json.loads((twin / "twin.json").read_text())
    for name in manifest["files"]:
        manifest["files"][name] = store.twin_files.sha256((_content(twin) / name).read_bytes())
    (twin / "twin.json").write_text(json.dumps(manifest))


def _edit_header(twin, change) -> None:
    head = json.loads((_content(twin) / "header.json").read_text())
    change(head)
    (_content(twin) / "header.json").write_text(json.dumps(head))


def _edit_stats(twin, change) -> None:
    with np.load(_content(twin) / "statistics.npz") as z:
        arrays = {k: z[k] for k in z.files}
    change(arrays)
    np.savez(_content(twin) / "statistics.npz", **arrays)


def _external(twin, secret: Path) -> None:
    """posterior.nc whose theta is HDF5 external storage over ``secret``."""
    folder = _content(twin)
    head = json.loads((folder / "header.json").read_text())
    C, D = head["settings"]["num_chains"], head["settings"]["num_draws"]
    eq = head["equations"][0]
    tag, K = f"{eq['state']}_{eq['kind']}", len(eq["terms"])
    nbytes = C * D * K * 8
    secret.write_bytes((b"TOPSECRET" * (nbytes // 9 + 1))[:nbytes])
    (folder / "posterior.nc").unlink()
    with h5py.File(folder / "posterior.nc", "w") as f:
        g = f.create_group("posterior")
        g.create_dataset(f"gamma_{tag}", data=np.zeros((C, D, K), np.int8))
        g.create_dataset(f"theta_{tag}", (C, D, K), "<f8", external=[(str(secret), 0, nbytes)])
        g.create_dataset(f"sigma2_{tag}", data=np.ones((C, D)))


def _soft_link(twin, secret: Path) -> None:
    folder = _content(twin)
    with h5py.File(folder / "posterior.nc", "a") as f:
        tag = next(k for k in f["posterior"] if k.startswith("theta_"))
        f["stolen"] = f[f"posterior/{tag}"][()]
        del f[f"posterior/{tag}"]
        f[f"posterior/{tag}"] = h5py.SoftLink("/stolen")


def _truncate(p: Path) -> None:
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])


TAMPER = {
    "truncated posterior.nc": (lambda tw, s: _truncate(_content(tw) / "posterior.nc"), True, "posterior.nc"),
    "garbage posterior.nc": (lambda tw, s: (_content(tw) / "posterior.nc").write_bytes(os.urandom(5000)), True,
                             "not a readable HDF5"),
    "external storage": (_external, True, "external storage"),
    "soft link": (_soft_link, True, "SoftLink"),
    "statistics missing key": (lambda tw, s: _edit_stats(tw, lambda a: a.pop("drift_xty")), True,
                               "missing key 'drift_xty'"),
    "statistics wrong shape": (lambda tw, s: _edit_stats(tw, lambda a: a.update(drift_gram=a["drift_gram"][:, :3])),
                               True, "'drift_gram' has shape (1, 3, 46)"),
    "statistics object array": (
        lambda tw, s: _edit_stats(tw, lambda a: a.update(drift_n=np.array([{}], dtype=object))), True, "statistics.npz"),
    "header missing settings": (lambda tw, s: _edit_header(tw, lambda h: h.pop("settings")), True,
                                "field 'settings' is missing"),
    "header unknown state": (lambda tw, s: _edit_header(tw, lambda h: h["equations"][0].update(state="x9")), True,
                             "unknown state 'x9'"),
    "header unknown mode": (lambda tw, s: _edit_header(tw, lambda h: h.update(mode="telepathy")), True,
                            "field 'mode' must be"),
    "edited nominal.toml": (lambda tw, s: (_content(tw) / "nominal.toml").write_text(
        (_content(tw) / "nominal.toml").read_text().replace("K = [[", "K = [[2")), False, "nominal.toml' does not match"),
    "truncated, checksums kept": (lambda tw, s: _truncate(_content(tw) / "posterior.nc"), False,
                                  "posterior.nc' does not match its checksum"),
}


@pytest.mark.parametrize("case", list(TAMPER))
def test_tampered_twin_one_line_exit_2_nothing_written(saved, tmp_path, capsys, case):
    tamper, rehash, expect = TAMPER[case]
    twin, secret, out = _copy(saved, tmp_path), tmp_path / "secret.bin", tmp_path / "p.npz"
    tamper(twin, secret)
    if rehash:
        _rehash(twin)
    before = {p: p.stat().st_mtime_ns for p in tmp_path.rglob("*")}
    for argv in (["predict", str(twin), "--input", str(saved / "new.npz"), "--out", str(out)],
                 ["update", str(twin), str(saved / "w2.npz"), "--out", str(tmp_path / "r.json")] + TINY):
        assert main(argv) == 2
        captured = capsys.readouterr()
        err = captured.err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("dtwin-jax: error: "), captured.err
        assert expect in err[0] and "Traceback" not in captured.err
        assert "TOPSECRET" not in captured.out + captured.err
    after = {p: p.stat().st_mtime_ns for p in tmp_path.rglob("*")}
    assert after == before  # nothing written, nothing removed
    with pytest.raises(DataError):
        load_twin(twin)
    if case == "external storage":
        assert not [p for p in tmp_path.rglob("*") if p.is_file() and p != secret and b"TOPSECRET" in p.read_bytes()]


@pytest.mark.parametrize("spec", ["terms:{cmd}", "terms:x1**3+0*{cmd};x1;x2;u1", "poly:1,terms:sign({cmd})"])
def test_a_crafted_library_in_a_twin_runs_no_code(saved, tmp_path, capsys, spec):
    # The reviewer's routes: twin.json's library evaluated on predict and update (and written
    # back by update, so it ran again on every later load). Checksums recomputed, so that the
    # parser, not the manifest, is what refuses it.
    from test_security import payloads

    marker = tmp_path / "ran"
    twin, out = _copy(saved, tmp_path), tmp_path / "p.npz"
    _edit_header(twin, lambda h: h.update(library=spec.format(cmd=payloads(marker)[0])))
    _rehash(twin)
    for argv in (["predict", str(twin), "--input", str(saved / "new.npz"), "--out", str(out)],
                 ["update", str(twin), str(saved / "w2.npz")] + TINY):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("dtwin-jax: error: "), err
        assert "library" in err[0]
    assert not marker.exists() and not out.exists()


def test_user_files_survive_an_update_in_place(saved, tmp_path):
    twin = _copy(saved, tmp_path)
    (twin / "NOTES.txt").write_text("mine")
    (twin / "plots").mkdir()
    (twin / "plots" / "a.png").write_bytes(b"png")
    shutil.copy(saved / "w2.npz", twin / "new_window.npz")
    old = _content(twin)
    assert main(["update", str(twin), str(twin / "new_window.npz")] + TINY) == 0
    assert (twin / "NOTES.txt").read_text() == "mine" and (twin / "plots" / "a.png").read_bytes() == b"png"
    assert (twin / "new_window.npz").read_bytes() == (saved / "w2.npz").read_bytes()
    assert not old.exists() and _content(twin).name == "v000002"
    assert sorted(os.listdir(twin)) == [".lock", "NOTES.txt", "new_window.npz", "plots", "twin.json", "v000002"]
    assert [h["update"] for h in load_twin(twin).history] == [1, 2]


def test_discover_refuses_a_user_folder_and_an_existing_twin_before_running(saved, tmp_path, capsys):
    proj = tmp_path / "proj"
    (proj / "src").mkdir(parents=True)
    (proj / "NOTES.txt").write_text("notes")
    (proj / "src" / "main.py").write_text("print()")
    twin = _copy(saved, tmp_path)
    history = load_twin(twin).history
    outs = ["--out", str(tmp_path / "r.json"), "--plot", str(tmp_path / "p.png")]
    for target, expect in ((proj, "is not empty and not a dtwin-jax twin"), (twin, "already holds a twin")):
        start = time.perf_counter()
        assert main(["discover", str(saved / "w2.npz"), "--nominal", str(saved / "nominal.toml"),
                     "--save-twin", str(target)] + outs + TINY) == 2
        assert time.perf_counter() - start < 1.0  # refused before the run
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and expect in err[0]
    assert not (tmp_path / "r.json").exists() and not (tmp_path / "p.png").exists()
    assert sorted(p.name for p in proj.rglob("*")) == ["NOTES.txt", "main.py", "src"]
    assert load_twin(twin).history == history
    # The repeat of a window in the history is refused (it would count twice) before sampling.
    assert main(["update", str(twin), str(saved / "w1.npz")] + TINY) == 2
    assert "already in the twin's history" in capsys.readouterr().err


def test_update_out_twin_refuses_another_twin_before_running(saved, tmp_path, capsys):
    twin, other = _copy(saved, tmp_path), _copy(saved, tmp_path, "other")
    before = load_twin(other).history
    start = time.perf_counter()
    assert main(["update", str(twin), str(saved / "w2.npz"), "--out-twin", str(other)] + TINY) == 2
    assert time.perf_counter() - start < 5.0  # refused before the update runs
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"dtwin-jax: error: --out-twin '{other}' already holds another twin; give a new or empty folder"]
    assert load_twin(other).history == before


def test_force_replaces_the_twin_but_not_the_files_beside_it(saved, tmp_path):
    twin = _copy(saved, tmp_path)
    (twin / "NOTES.txt").write_text("notes")
    other = load_twin(saved / "twin")
    other = dataclasses.replace(other, history=[dict(other.history[0], update=1, time="elsewhere")])
    with pytest.raises(DataError, match="does not continue"):
        save_twin(other, twin)
    assert main(["discover", str(saved / "w2.npz"), "--nominal", str(saved / "nominal.toml"),
                 "--save-twin", str(twin), "--force"] + TINY) == 0
    history = load_twin(twin).history
    assert len(history) == 1 and history[0]["window_sha256"] != load_twin(saved / "twin").history[0]["window_sha256"]
    assert (twin / "NOTES.txt").read_text() == "notes"
    assert sorted(os.listdir(twin)) == [".lock", "NOTES.txt", "twin.json", "v000002"]


def _next(result, tag):
    """``result`` with one more (made-up) history entry: an update without the sampling."""
    return dataclasses.replace(result, history=list(result.history) + [{"update": len(result.history) + 1, "tag": tag}])


def test_concurrent_python_saves_under_the_lock_lose_nothing(saved, tmp_path):
    twin = _copy(saved, tmp_path)
    errors = []

    def worker(name):
        try:
            for i in range(5):
                with locked(twin):
                    save_twin(_next(load_twin(twin), f"{name}{i}"), twin)
        except Exception as e:  # pragma: no cover - reported below
            errors.append(e)

    threads = [threading.Thread(target=worker, args=(n,)) for n in "ab"]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert not errors
    tags = [h.get("tag") for h in load_twin(twin).history[1:]]
    assert sorted(tags) == sorted(f"{n}{i}" for n in "ab" for i in range(5))
    # Without the lock, the second of two saves from the same revision is refused, not lost.
    first = load_twin(twin)
    a, b = _next(first, "a"), _next(first, "b")
    save_twin(a, twin, expect_revision=first.twin_revision)
    with pytest.raises(DataError, match="saved meanwhile") as e:
        save_twin(b, twin, expect_revision=first.twin_revision)
    assert "\n" not in str(e.value)
    with pytest.raises(DataError, match="does not continue"):
        save_twin(b, twin)
    assert load_twin(twin).history[-1]["tag"] == "a"


def test_two_update_processes_keep_both_windows(saved, tmp_path):
    twin = _copy(saved, tmp_path)
    cmd = [sys.executable, "-m", "dtwin_jax.cli", "update", str(twin)]
    quick = ["--chains", "2", "--draws", "100", "--burn-in", "50", "--quiet"]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    procs = [subprocess.Popen(cmd + [str(saved / w)] + quick, env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for w in ("w2.npz", "w3.npz")]
    results = [(p.wait(timeout=300), p.stdout.read(), p.stderr.read()) for p in procs]
    for code, out, err in results:
        assert code == 0, err
        assert all(line.startswith(("dtwin-jax: waiting", "dtwin-jax: warning")) for line in err.splitlines())
    history = load_twin(twin).history
    assert [h["update"] for h in history] == [1, 2, 3]
    assert len({h["window_sha256"] for h in history}) == 3


_UPDATER = """
import dataclasses, sys
from dtwin_jax.io.store import load_twin, locked, save_twin
twin, name = sys.argv[1], sys.argv[2]
print("ready", flush=True)
sys.stdin.readline()  # both processes start their rounds together
for i in range(5):
    with locked(twin):  # read, update (a made-up history entry) and write under the lock
        result = load_twin(twin)
        entry = {"update": len(result.history) + 1, "tag": f"{name}{i}"}
        save_twin(dataclasses.replace(result, history=list(result.history) + [entry]), twin)
"""


def test_two_processes_update_one_twin_five_times_each_and_lose_nothing(saved, tmp_path):
    # Five rounds of two processes updating one twin at once (the sampling replaced by a
    # made-up history entry, so that the rounds overlap within a second).
    twin = _copy(saved, tmp_path)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    procs = [subprocess.Popen([sys.executable, "-c", _UPDATER, str(twin), name], env=env, text=True,
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE) for name in "ab"]
    for p in procs:
        assert p.stdout.readline().strip() == "ready"
    for p in procs:
        p.stdin.write("go\n")
        p.stdin.flush()
    for p in procs:
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, err
    history = load_twin(twin).history
    tags = [h["tag"] for h in history[1:]]
    assert sorted(tags) == sorted(f"{n}{i}" for n in "ab" for i in range(5))
    assert [h["update"] for h in history] == list(range(1, 12))


@pytest.mark.parametrize("step", ["files", "folder", "pointer", "cleanup"])
def test_a_save_killed_at_any_step_leaves_a_twin_and_no_leftovers(saved, tmp_path, monkeypatch, step):
    twin = _copy(saved, tmp_path)
    (twin / "NOTES.txt").write_text("notes")
    old = load_twin(twin)

    def fail(name):
        if name == step:
            raise KeyboardInterrupt(name)

    monkeypatch.setattr(store, "_AFTER_STEP", fail)
    with pytest.raises(KeyboardInterrupt):
        save_twin(_next(old, "new"), twin)
    monkeypatch.setattr(store, "_AFTER_STEP", None)
    now = load_twin(twin).history
    assert now == old.history if step in ("files", "folder") else now[-1] == {"update": 2, "tag": "new"}
    save_twin(load_twin(twin), twin)  # the next save cleans up
    assert sorted(os.listdir(twin)) == [".lock", "NOTES.txt", "twin.json", _content(twin).name]


_SAVER = """
import sys
from dtwin_jax.io.store import load_twin, save_twin
result = load_twin(sys.argv[1])
save_twin(result, sys.argv[1])  # the first save imports arviz and h5netcdf
print("ready", flush=True)
while True:
    save_twin(result, sys.argv[1])
"""


def test_sigkill_while_saving_leaves_a_loadable_twin(saved, tmp_path):
    twin = _copy(saved, tmp_path)
    history = load_twin(twin).history
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    for delay in (0.0, 0.05, 0.17):
        proc = subprocess.Popen([sys.executable, "-c", _SAVER, str(twin)], env=env, stdout=subprocess.PIPE, text=True)
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(delay)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        assert load_twin(twin).history == history
    revision = store.twin_revision(twin)
    assert revision > 1  # the saves ran
    save_twin(load_twin(twin), twin)
    assert sorted(os.listdir(twin)) == [".lock", "twin.json", f"v{revision + 1:06d}"]


def test_files_get_the_user_umask_and_version_1_twins_still_load(saved, tmp_path):
    # A version-1 (flat) twin made from the saved one: read, then migrated by the next save.
    v1 = tmp_path / "v1"
    shutil.copytree(_content(saved / "twin"), v1)
    head = json.loads((v1 / "header.json").read_text())
    head["version"] = 1
    for eq in head["equations"]:
        del eq["terms"]
    (v1 / "twin.json").write_text(json.dumps(head))
    (v1 / "header.json").unlink()
    (v1 / "NOTES.txt").write_text("notes")
    result = load_twin(v1)
    assert result.twin_revision == 0 and result.history == load_twin(saved / "twin").history
    old = os.umask(0o022)
    try:
        save_twin(result, v1)
        save_twin(result, tmp_path / "fresh" / "twin")
    finally:
        os.umask(old)
    assert sorted(os.listdir(v1)) == [".lock", "NOTES.txt", "twin.json", "v000001"]
    twin = tmp_path / "fresh" / "twin"
    assert sorted(os.listdir(twin)) == [".lock", "twin.json", "v000001"]
    for p in [twin, *twin.rglob("*")]:
        assert p.stat().st_mode & 0o777 == (0o755 if p.is_dir() else 0o644), p
    np.testing.assert_array_equal(load_twin(twin).equations[0].theta, result.equations[0].theta)
