"""Term expressions from outside (a `--library` option, a twin's `twin.json`, an API
argument) parsed without running code.

`sympy.sympify` evaluates Python, so no outside string may reach it. `parse_term`
parses with Python's `ast` in `eval` mode and builds the SymPy expression node by node
from an allow-list: integers; the names `x1, x2, ...` and `u1, u2, ...`; `+ - * / **`;
unary `-` and `+`; one-argument calls of `sign`, `Abs`, `exp`, `sin`, `cos`.
Anything else (attributes, subscripts, other names or calls, keywords, strings, lambdas,
comprehensions) is refused before any of it is evaluated. SymPy then only combines
already-built expressions, as `sympify` would: the results are equal.
"""

from __future__ import annotations

import ast
import re

import sympy

from dtwin_jax.errors import DataError

__all__ = ["parse_term", "FUNCTIONS"]

FUNCTIONS = {"sign": sympy.sign, "Abs": sympy.Abs, "exp": sympy.exp, "sin": sympy.sin, "cos": sympy.cos}
_SYMBOL = re.compile(r"[xu][1-9][0-9]{0,5}")
# Bounds that keep SymPy's work on a term small whatever the text: a library term is a
# monomial or one of a few functions of one or two states.
_MAX_CHARS = 1000
_MAX_EXPONENT = 64
_MAX_DEGREE = 64
_MAX_INTEGER = 10**6
_BINARY = {ast.Add: lambda a, b: a + b, ast.Sub: lambda a, b: a - b, ast.Mult: lambda a, b: a * b,
           ast.Div: lambda a, b: a / b, ast.Pow: lambda a, b: a**b}
_UNARY = {ast.USub: lambda a: -a, ast.UAdd: lambda a: a}


class _Refused(Exception):
    """A node outside the grammar; the message says which."""


def parse_term(text: str) -> sympy.Expr:
    """Parse one term expression, such as `"x1**2*x2"` or `"exp(-x3)*x1"`, safely.

    **Arguments:**

    - `text`: the expression, at most 1000 characters.

    **Returns:** the SymPy expression, equal to what `sympy.sympify(text)` gives for
    every expression of the grammar (names are plain symbols `x1..`, `u1..`).

    Raises `DataError` (one line) for anything outside the grammar, naming what was found.
    """
    if not isinstance(text, str):
        raise DataError(f"library term {_shown(text)} is not a string")
    if len(text) > _MAX_CHARS:
        raise DataError(f"library term of {len(text)} characters is too long (at most {_MAX_CHARS})")
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except (SyntaxError, ValueError, RecursionError, MemoryError):
        raise DataError(f"cannot parse library term {_shown(text)}: not an expression") from None
    try:
        expr, _ = _build(tree.body)
    except _Refused as e:
        raise DataError(f"library term {_shown(text)} {e}") from None
    except RecursionError:
        raise DataError(f"library term {_shown(text)} is nested too deeply") from None
    return expr


def _shown(text, limit: int = 80) -> str:
    """`repr` of an outside string, cut to `limit` characters for a one-line message."""
    text = repr(text)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _build(node) -> tuple[sympy.Expr, int]:
    """`(expression, bound on its polynomial degree)` of an allowed node."""
    if isinstance(node, ast.Constant):
        value = node.value
        # Integers only (terms carry no coefficients), small, so arithmetic on them stays cheap.
        if isinstance(value, bool) or not isinstance(value, int):
            raise _Refused(f"has the constant {value!r}; only integers are allowed")
        if abs(value) > _MAX_INTEGER:
            raise _Refused(f"has an integer above {_MAX_INTEGER}")
        return sympy.Integer(value), 0
    if isinstance(node, ast.Name):
        if node.id in FUNCTIONS:
            raise _Refused(f"uses the function {node.id!r} without calling it")
        if not _SYMBOL.fullmatch(node.id):
            raise _Refused(f"uses the name {node.id!r}: only states x1..xm and inputs u1..un are allowed")
        return sympy.Symbol(node.id), 1
    if isinstance(node, ast.UnaryOp) and type(node.op) in _UNARY:
        expr, degree = _build(node.operand)
        return _UNARY[type(node.op)](expr), degree
    if isinstance(node, ast.BinOp) and type(node.op) in _BINARY:
        left, dl = _build(node.left)
        if isinstance(node.op, ast.Pow):
            if not left.free_symbols:
                raise _Refused("raises a number to a power; powers apply to states or inputs")
            exponent = _exponent(node.right)
            degree = dl * abs(exponent)
            right = sympy.Integer(exponent)
        else:
            right, dr = _build(node.right)
            degree = dl + dr if isinstance(node.op, (ast.Mult, ast.Div)) else max(dl, dr)
        if degree > _MAX_DEGREE:
            raise _Refused(f"has degree above {_MAX_DEGREE}")
        return _BINARY[type(node.op)](left, right), degree
    if isinstance(node, ast.Call):
        name = node.func.id if isinstance(node.func, ast.Name) else None
        if name not in FUNCTIONS:
            raise _Refused("is none of the library's functions (monomials, sign, Abs, x*Abs(y), "
                           "exp(-x), exp(-x)*y, exp(-x*y), sin, cos, u)")
        if len(node.args) != 1 or node.keywords or isinstance(node.args[0], ast.Starred):
            raise _Refused(f"calls {name} with other than one argument")
        arg, degree = _build(node.args[0])
        return FUNCTIONS[name](arg), degree
    raise _Refused(f"has {type(node).__name__!r}, which is not allowed in a term")


def _exponent(node) -> int:
    """A power's exponent: an integer literal, optionally negated, at most 64 in size."""
    sign = 1
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
        sign = -1 if isinstance(node.op, ast.USub) else 1
        node = node.operand
    value = node.value if isinstance(node, ast.Constant) else None
    if isinstance(value, bool) or not isinstance(value, int):
        raise _Refused("has a power whose exponent is not an integer literal")
    if value > _MAX_EXPONENT:
        raise _Refused(f"has an exponent above {_MAX_EXPONENT}")
    return sign * value
