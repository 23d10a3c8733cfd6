"""The walkthroughs in notebooks/ run top to bottom with short settings (nbclient).

Every notebook's first code cell is tagged ``parameters`` and sets every size the notebook
uses. This test replaces that cell with the short settings in ``SHORT`` (a notebook without an
entry fails: add one), executes the notebook in a temporary directory with a ``python3``
kernel of this interpreter (nothing is written into the repository), and checks what it
printed with the notebook's entry in ``CHECKS``.

Compiling JAX programs is most of a short run's time, so the kernel runs with
``JAX_DISABLE_MOST_OPTIMIZATIONS=1`` (measured: 1.4-1.7x less time for these short runs,
the same printed numbers). Measured on one idle core: 20 s, 42 s and 50 s.
"""

import ast
import json
import os
import re
import sys
import time
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = Path(__file__).resolve().parent.parent / "notebooks"

# The parameters cell of each notebook, short: same names as the notebook's own cell.
SHORT = {
    "framework1_examples.ipynb": """
CHAINS = 2
DRAWS = 300
BURNIN = 150
NOISE = 0.05
OTHER_EXAMPLES = ()
SWEEP_CHAINS = 2
SWEEP_DRAWS = 300          # burn-in 150: the same settings as above, one compiled sampler
NOISE_LEVELS = (0.0, 0.45)
""",
    "framework2_output_only.ipynb": """
RECORDS = 20
DURATION = 1.0
NOISE = 0.05
CHAINS = 2
DRAWS = 300
BURNIN = 150
HIGH_NOISE = 0.35
""",
    "prediction_and_degradation.ipynb": """
CHAINS = 2
DRAWS = 300
BURNIN = 150
NOISE = 0.05
PREDICT_DRAWS = 8
DURATION = 1.0             # as long as the training window: one compiled simulation
HORIZON = 1.0
PLOT_SECONDS = 0.5
""",
    "positioning_stage.ipynb": """
DURATION = 5.0
DRAWS = 4
SEED = 0
""",
    "silverbox.ipynb": """
REALIZATIONS = 1
DRAWS = 2
SEED = 0
""",
}


def _numbers(text: str) -> list[float]:
    return [float(v) for v in re.findall(r"-?\d+(?:\.\d+)?(?:e[-+]?\d+)?", text)]


def _line(text: str, start: str) -> str:
    """The first printed line that starts with ``start``."""
    found = [line for line in text.splitlines() if line.startswith(start)]
    assert found, f"no printed line starts with {start!r}"
    return found[0][len(start):]


def check_framework1(text: str) -> None:
    assert _line(text, "selected terms: ").strip() == "['x1**3']"
    mean = _numbers(_line(text, "x1**3: truth -100000, posterior mean "))[0]
    assert abs(mean / -1e5 - 1) < 0.02, mean
    assert "warnings: none" in text
    for level in ("0%", "45%"):
        assert f"{level}: selected ['x1**3']" in text, level


def check_framework2(text: str) -> None:
    assert _line(text, "selected drift terms of x2: ").strip() == "['x1**3']"
    assert _line(text, "selected diffusion terms of x2: ").strip() == "['1']"
    mean = _numbers(_line(text, "x1**3: truth -100000, posterior mean "))[0]
    assert abs(mean / -1e5 - 1) < 0.05, mean
    gamma = _numbers(_line(text, "Gamma = "))[0]
    assert abs(gamma / 0.25 - 1) < 0.15, gamma
    # 35% noise: the noise-correction check flags the fit.
    assert "noise correction removed more than the data hold" in text


def check_prediction(text: str) -> None:
    assert _line(text, "selected terms: ").strip() == "['x1**3']"
    twin = _numbers(_line(text, "normalised RMSE of the twin's mean (%): "))
    nominal = _numbers(_line(text, "normalised RMSE of the nominal model (%): "))
    assert len(twin) == 2 and max(twin) < 5.0 and min(nominal) > 50.0, (twin, nominal)
    assert _line(text, "loaded twin predicts identically: ").strip() == "True"
    assert len(re.findall(r"^update \d: ", text, flags=re.M)) == 2
    assert _line(text, "selected terms of x2: ").strip() == "['x1', 'x1*exp(-x3)']"
    inside = _numbers(_line(text, "true damage inside the twins' 95% band: "))[0]
    assert inside > 90.0, inside


def check_silverbox(text: str) -> None:
    """One multisine realization (8,692 samples), two posterior twins, the default route.
    Measured (seed 0): twin 0.426 mV on the arrow, 0.328 mV within the training amplitude
    (samples 0-26,192), 32.7x below the identified linear model. ``python
    examples/silverbox.py`` runs the full study (0.419 mV, 34x)."""
    twin, within = _numbers(_line(text, "updated twin: "))
    ratio, samples = _numbers(_line(text, "ratio: "))
    assert twin < 0.6 and ratio > 20.0 and within < 0.5, (twin, ratio, within)
    assert samples == 26193
    # The default band: posterior draws and the twin's model error. This short run's band is
    # wider (a twin from 1 realization): measured 99.6% within the training range, 97.1% of
    # the arrow (the full study, examples/silverbox.py: 96.1% and 91.0%). Twin 0.426 mV, 32.7x
    # below linear, 0.328 mV within the range.
    arrow, inside = _numbers(_line(text, "95% band: "))[1:]
    assert inside > 95.0 and arrow > 95.0, (inside, arrow)


def check_positioning_stage(text: str) -> None:
    """5 s records, 4 posterior twins. ``python examples/positioning_stage.py`` runs the full
    study (25 s, 100 draws: 1.77 mm against the textbook model's 4.96 mm). Measured here:
    0.574 mm against 4.743 mm."""
    textbook = _numbers(_line(text, "textbook free run: "))[0]
    twin = _numbers(_line(text, "twin free run: "))[0]
    print("positioning stage notebook:", textbook, twin)
    assert twin < 0.7 * textbook, (twin, textbook)  # the bar: 30% below the textbook model


CHECKS = {
    "framework1_examples.ipynb": (check_framework1, 2),  # (check, least number of figures)
    "framework2_output_only.ipynb": (check_framework2, 2),
    "prediction_and_degradation.ipynb": (check_prediction, 4),
    "positioning_stage.ipynb": (check_positioning_stage, 2),
    "silverbox.ipynb": (check_silverbox, 2),
}


@pytest.fixture
def python3_kernel(tmp_path, monkeypatch):
    """Kernel ``python3`` = this interpreter, whatever other kernel specs the user has."""
    spec = tmp_path / "jupyter" / "kernels" / "python3"
    spec.mkdir(parents=True)
    (spec / "kernel.json").write_text(json.dumps({
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "Python 3", "language": "python",
    }))
    monkeypatch.setenv("JUPYTER_PATH", str(tmp_path / "jupyter"))
    # The kernels share the tests' compilation cache (built, as theirs, without most of
    # XLA's optimizations: tests/conftest.py).
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", os.environ["DTWIN_JAX_CACHE"])
    monkeypatch.setenv("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    monkeypatch.delenv("MPLBACKEND", raising=False)
    work = tmp_path / "work"
    work.mkdir()
    return work


def _assigned(source: str) -> set[str]:
    return {t.id for node in ast.parse(source).body if isinstance(node, ast.Assign)
            for t in node.targets if isinstance(t, ast.Name)}


def _text(nb) -> str:
    """What the notebook printed. One ``print`` can arrive as two stream messages (``kernel
    prefix:`` then `` /path``), so consecutive stream texts are joined as they are."""
    parts = []
    for cell in nb.cells:
        for out in cell.get("outputs", []):
            if out.output_type == "stream" and out.name == "stdout":
                parts.append(out.text)
            elif out.output_type in ("execute_result", "display_data"):
                parts.append("\n" + out.data.get("text/plain", "") + "\n")
    return "".join(parts)


def test_every_notebook_has_short_settings():
    names = sorted(p.name for p in NOTEBOOKS.glob("*.ipynb"))
    assert names, "no notebooks found"
    missing = [n for n in names if n not in SHORT or n not in CHECKS]
    assert not missing, f"notebooks without short settings or checks in tests/test_notebooks.py: {missing}"


# One notebook runs by default, all with `pytest -m slow`: each other notebook's pipeline has
# default-run tests of its own (output-only, prediction and degradation, friction, silverbox).
DEFAULT_RUN = "framework1_examples.ipynb"


def _notebook(path):
    return pytest.param(path, id=path.stem, marks=() if path.name == DEFAULT_RUN else pytest.mark.slow)


@pytest.mark.parametrize("path", [_notebook(p) for p in sorted(NOTEBOOKS.glob("*.ipynb"))])
def test_notebook_runs_with_short_settings(path, python3_kernel):
    if path.name not in SHORT or path.name not in CHECKS:
        pytest.fail(f"{path.name}: add its short settings to SHORT and its checks to CHECKS")
    nb = nbformat.read(path, as_version=4)
    code = [c for c in nb.cells if c.cell_type == "code"]
    params = code[0]
    assert "parameters" in params.metadata.get("tags", []), "the first code cell must be tagged 'parameters'"
    assert _assigned(SHORT[path.name]) == _assigned(params.source), "short settings must set the same names"
    params.source = SHORT[path.name].strip()
    nb.cells.append(nbformat.v4.new_code_cell("import sys; print('kernel prefix:', sys.prefix)"))

    start = time.perf_counter()
    NotebookClient(nb, timeout=600, kernel_name="python3",
                   resources={"metadata": {"path": str(python3_kernel)}}).execute()
    print(f"{path.name}: {time.perf_counter() - start:.1f} s")

    outputs = [o for c in nb.cells for o in c.get("outputs", [])]
    assert not [o for o in outputs if o.output_type == "error"]
    stderr = "".join(o.text for o in outputs if o.output_type == "stream" and o.name == "stderr")
    assert "Traceback" not in stderr and "Warning" not in stderr, stderr
    text = _text(nb)
    assert _line(text, "kernel prefix: ").strip() == sys.prefix
    check, figures = CHECKS[path.name]
    check(text)
    images = [o for o in outputs if "image/png" in o.get("data", {})]
    assert len(images) >= figures, f"{len(images)} figures"
    assert list(python3_kernel.iterdir()) == []  # the notebook wrote nothing into its folder
