"""The documentation cannot drift from the code: docs/architecture.md lists every module of
the package, one line each (`` - `dtwin_jax/path.py` — what it holds ``), and nothing else."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ENTRY = re.compile(r"^- `(dtwin_jax/[^`]+\.py)` — \S")


def listed_modules() -> list[str]:
    text = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    return [m.group(1) for line in text.splitlines() if (m := ENTRY.match(line))]


def package_modules() -> set[str]:
    return {
        p.relative_to(ROOT).as_posix()
        for p in (ROOT / "dtwin_jax").rglob("*.py")
        if "__pycache__" not in p.parts
    }


def test_architecture_page_lists_every_module_once():
    listed = listed_modules()
    assert listed, "docs/architecture.md lists no module (lines '- `dtwin_jax/x.py` — ...')"
    duplicates = sorted({m for m in listed if listed.count(m) > 1})
    assert not duplicates, f"listed twice in docs/architecture.md: {duplicates}"
    actual = package_modules()
    missing = sorted(actual - set(listed))
    stale = sorted(set(listed) - actual)
    assert not missing and not stale, (
        f"docs/architecture.md is out of date: add {missing}, remove {stale}"
    )
