"""Nothing from outside runs code: every route by which a term expression reaches the
package (the Python API, ``--library``, ``--diffusion-library``, a twin's ``library`` and
``diffusion_library``) is parsed by the allow-list grammar, never evaluated."""

import numpy as np
import pytest
import sympy

from dtwin_jax import DataError
from dtwin_jax.cli import main
from dtwin_jax.expressions import parse_term
from dtwin_jax.library import FAMILIES, _family_terms, parse_library, symbols

NOMINAL = "M = [[1.0]]\nC = [[2.0]]\nK = [[1000.0]]\nB = [[0.5]]\n"


def payloads(marker):
    """Expressions that would create ``marker`` if evaluated, as the reviewer wrote them."""
    cmd = f"__import__('os').system('touch {marker}')"
    return [
        cmd,
        f"x1**3+0*{cmd}",
        f"x1*({cmd})",
        f"sign({cmd})",
        f"(lambda: {cmd})()",
        "[c for c in ().__class__.__bases__[0].__subclasses__()]",
        f"exec(\"{cmd}\")",
        f"eval(\"{cmd}\")",
        "x1.__class__.__init__.__globals__",
        "Symbol('x1')",
    ]


def _data(tmp_path, with_input=True):
    rng = np.random.default_rng(0)
    t = np.arange(400) * 1e-3
    x = np.stack([0.1 * np.cos(30 * t), -3 * np.sin(30 * t)], axis=1) + 1e-4 * rng.normal(size=(400, 2))
    data = {"t": t, "x": x, **({"u": rng.normal(size=(400, 1))} if with_input else {})}
    np.savez(tmp_path / "data.npz", **data)
    (tmp_path / "nominal.toml").write_text(NOMINAL)
    return tmp_path / "data.npz", tmp_path / "nominal.toml"


def _one_line_error(capsys):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("dtwin-jax: error: library term "), err
    return err[0]


def test_python_api_parses_without_running_code(tmp_path):
    marker = tmp_path / "ran"
    for text in payloads(marker):
        with pytest.raises(DataError) as e:
            parse_library(f"poly:1,terms:{text}", 2, 1)
        assert "\n" not in str(e.value) and len(str(e.value)) < 300
        with pytest.raises(DataError):
            parse_term(text)
    assert not marker.exists()


@pytest.mark.parametrize("option, with_input", [("--library", True), ("--diffusion-library", False)])
def test_command_line_library_options_parse_without_running_code(tmp_path, capsys, option, with_input):
    marker = tmp_path / "ran"
    data, nominal = _data(tmp_path, with_input)
    for text in payloads(marker)[:3]:
        out = tmp_path / "r.json"
        code = main(["discover", str(data), "--nominal", str(nominal), "--out", str(out), option,
                     f"terms:{text}", "--quiet"])
        assert code == 2 and not out.exists()
        _one_line_error(capsys)
    assert not marker.exists()


def test_the_grammar_reads_every_family_term_as_sympify_does():
    # The safe parser's expressions equal SymPy's own for every term the families name (a
    # trusted string here: the test may call sympify).
    xs, us = symbols(3, 2)
    for family in FAMILIES:
        _, raw = _family_terms(family, 4 if family == "poly" else None, xs, us)
        for name in raw:
            assert parse_term(name) == sympy.sympify(name), name
    for text in ("x1*x1", "x2*x1**2", "exp(-x2*x1)", "x2*exp(-x1)", "Abs(x1)*x2", "--x1", "+x1", "(x1)"):
        assert parse_term(text) == sympy.sympify(text), text


@pytest.mark.parametrize("text, match", [
    ("x1**x2", "not an integer literal"),
    ("x1**65", "exponent above 64"),
    ("x1**8*x2**60", "degree above 64"),
    ("2**64", "raises a number to a power"),
    ("1.5*x1", "only integers"),
    ("'x1'", "only integers"),
    ("y1", "the name 'y1'"),
    ("sign", "without calling it"),
    ("sign(x1, x2)", "other than one argument"),
    ("tanh(x1)", "none of the library's functions"),
    ("x1[0]", "'Subscript'"),
    ("x1 +* )", "not an expression"),
    ("x1+" * 400 + "x1", "too long"),
])
def test_refusals_name_what_was_found(text, match):
    with pytest.raises(DataError, match=match):
        parse_term(text)


def test_random_token_soup_is_a_term_or_one_line_error(tmp_path):
    # 3000 random strings over the grammar's tokens and dangerous ones: each is a library term
    # whose name parses back to itself, or a DataError of one line; no other exception, and
    # nothing runs.
    marker = tmp_path / "ran"
    tokens = ["x1", "x2", "u1", "1", "2", "65", "-", "+", "*", "/", "**", "(", ")", "sign(", "Abs(", "exp(",
              "sin(", "cos(", "tanh(", "__import__('os').system('touch " + str(marker) + "')", ".", "[", "]",
              "lambda:", "'", "2.5", "True", "x1.real", "y", ",", " "]
    rng = np.random.default_rng(0)
    accepted = 0
    for _ in range(3000):
        text = "".join(rng.choice(tokens, size=rng.integers(1, 9)))
        try:
            lib = parse_library(f"terms:{text}", 2, 1)
        except DataError as e:
            assert "\n" not in str(e)
            continue
        accepted += 1
        assert all(str(parse_term(name)) == name for name in lib.names)
    assert not marker.exists()
    print(f"{accepted} of 3000 accepted")
    assert accepted >= 40  # the soup (50 with this seed) does hold terms (x1, sign(x2), x1**2*x2, ...)
