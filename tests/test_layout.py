"""The package's shape: no module imports another module's private names (a leading
underscore), so that every module's contract is what it exports."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "dtwin_jax"


def test_no_module_imports_another_modules_private_names():
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("dtwin_jax"):
                found += [f"{path.relative_to(PACKAGE.parent)}:{node.lineno} {node.module}.{a.name}"
                          for a in node.names if a.name.startswith("_") and not a.name.startswith("__")]
            elif isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
                base = node.value
                if isinstance(base, ast.Name) and base.id in _module_aliases(path):
                    found.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno} {base.id}.{node.attr}")
    assert not found, found


def _module_aliases(path: Path, cache={}) -> set[str]:
    """Names bound to dtwin_jax modules in ``path`` (``from dtwin_jax import sampler``)."""
    if path not in cache:
        names = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("dtwin_jax"):
                for a in node.names:
                    module = f"{node.module}.{a.name}".replace(".", "/")
                    if (PACKAGE.parent / f"{module}.py").exists() or (PACKAGE.parent / module).is_dir():
                        names.add(a.asname or a.name)
            elif isinstance(node, ast.Import):
                names |= {a.asname or a.name for a in node.names if a.name.startswith("dtwin_jax")}
        cache[path] = names
    return cache[path]
