"""The package's shape: no module imports another module's private names (a leading
underscore), so that every module's contract is what it exports; and its docstrings follow
one convention (Markdown; `**Arguments:**`, one entry per parameter, and `**Returns:**`)."""

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


# The docstring convention (docs/api.md): Markdown, and for every public function and
# method with parameters one `**Arguments:**` entry per parameter and a `**Returns:**`.
_REST = (":func:`", ":class:`", ":data:`", ":mod:`", ":meth:`", ":attr:`", ":obj:`", ":exc:`", "``")


def _public_callables(tree: ast.Module):
    for node in tree.body:
        if isinstance(node, ast.FunctionDef) and not node.name.startswith("_"):
            yield node.name, node
        if isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
            for sub in node.body:
                if isinstance(sub, ast.FunctionDef) and (not sub.name.startswith("_") or sub.name == "__call__"):
                    yield f"{node.name}.{sub.name}", sub


def _parameters(node: ast.FunctionDef) -> list[str]:
    a = node.args
    names = [x.arg for x in a.posonlyargs + a.args + a.kwonlyargs]
    names += [x.arg for x in (a.vararg, a.kwarg) if x is not None]
    return names[1:] if names[:1] in (["self"], ["cls"]) else names


def _returns_a_value(node: ast.FunctionDef) -> bool:
    todo = list(node.body)
    while todo:  # the function's own statements, not those of functions defined inside it
        n = todo.pop()
        if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda, ast.ClassDef)):
            continue
        if isinstance(n, ast.Return) and n.value is not None and not (
                isinstance(n.value, ast.Constant) and n.value.value is None):
            return True
        if isinstance(n, (ast.Yield, ast.YieldFrom)):
            return True
        todo.extend(ast.iter_child_nodes(n))
    return False


def _public_module(path: Path) -> bool:
    return not any(p.startswith("_") and p != "__init__.py" for p in path.relative_to(PACKAGE).parts)


def test_every_public_function_documents_each_argument_and_what_it_returns():
    found = []
    for path in sorted(p for p in PACKAGE.rglob("*.py") if _public_module(p)):
        where = path.relative_to(PACKAGE.parent)
        for name, node in _public_callables(ast.parse(path.read_text())):
            if any(ast.unparse(d) == "property" or ast.unparse(d).endswith(".setter") for d in node.decorator_list):
                continue
            doc = ast.get_docstring(node) or ""
            params = _parameters(node)
            if not params:  # `rhat()`, `example1()`: the summary line says what comes back
                continue
            _, _, rest = doc.partition("**Arguments:**")
            entries = [line.strip() for line in rest.partition("**Returns:**")[0].splitlines()]
            missing = [p for p in params
                       if not any(e.startswith((f"- `{p}`:", f"- `*{p}`:", f"- `**{p}`:")) for e in entries)]
            if not rest or missing:
                found.append(f"{where} {name}: no **Arguments:** entry for {missing or params}")
            if _returns_a_value(node) and "**Returns:**" not in doc:
                found.append(f"{where} {name}: returns a value but has no **Returns:**")
    assert not found, "\n".join(found)


def test_docstrings_are_markdown_not_rest():
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
                doc = ast.get_docstring(node, clean=False) or ""
                if any(r in doc for r in _REST):
                    found.append(f"{path.relative_to(PACKAGE.parent)}:{getattr(node, 'lineno', 1)} "
                                 f"{getattr(node, 'name', '<module>')}: {[r for r in _REST if r in doc]}")
    assert not found, "\n".join(found)
