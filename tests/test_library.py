import math
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import sympy

import dtwin_jax  # noqa: F401  (float64)
from dtwin_jax.errors import DataError
from dtwin_jax.library import (
    DEFAULT_LIBRARY,
    FAMILIES,
    Library,
    check_columns,
    column_scales,
    default_library,
    eval_terms,
    parse_library,
    symbols,
    term_table,
    to_sympy,
)


def _data(m, n, N=200, seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(N, m)), rng.normal(size=(N, n))


def _default_K(m, n):
    # poly:6 (incl. '1') + sign, abs, exp, sin, cos + xabs (m^2) + expxx (i <= j) + input
    return math.comb(m + 6, 6) + 5 * m + m * m + m * (m + 1) // 2 + n


def test_constants():
    assert DEFAULT_LIBRARY == "poly:6,sign,abs,xabs,exp,expxx,sin,cos,input"
    assert FAMILIES == ("poly", "sign", "abs", "xabs", "exp", "expx", "expxx", "sin", "cos", "input")


@pytest.mark.parametrize("m, K", [(1, 15), (2, 46), (3, 115), (4, 257)])
def test_default_counts(m, K):
    lib = default_library(m, 1)
    assert lib.K == K == _default_K(m, 1)
    assert len(set(lib.names)) == lib.K
    assert default_library(m, 0).K == K - 1
    assert "u1" not in default_library(m, 0).names


def test_poly_and_order():
    assert parse_library("poly:6", 2, 1).K == 28
    lib = parse_library("poly:3", 2, 0)
    assert lib.names == (
        "1", "x1", "x2", "x1**2", "x1*x2", "x2**2", "x1**3", "x1**2*x2", "x1*x2**2", "x2**3",
    )  # fmt: skip
    lib = parse_library("sign,xabs,expx,expxx,input", 2, 2)
    assert lib.names == (
        "sign(x1)", "sign(x2)",
        "x1*Abs(x1)", "x1*Abs(x2)", "x2*Abs(x1)", "x2*Abs(x2)",
        "x1*exp(-x1)", "x2*exp(-x1)", "x1*exp(-x2)", "x2*exp(-x2)",
        "exp(-x1**2)", "exp(-x1*x2)", "exp(-x2**2)",
        "u1", "u2",
    )  # fmt: skip
    # Monomial names are exactly sympy's printing of the product.
    x1, x2, x3 = symbols(3, 0)[0]
    names = parse_library("poly:3", 3, 0).names
    for expr in (x1**2 * x2, x1 * x2**2, x2**3, x1 * x2 * x3, x3**3):
        assert str(expr) in names


def test_names_round_trip():
    lib = parse_library(DEFAULT_LIBRARY + ",expx", 3, 2)
    for name in lib.names:
        assert str(sympy.sympify(name)) == name
        assert str(to_sympy(name)) == name
        assert to_sympy(name) == sympy.sympify(name)


def test_named_columns():
    x, u = _data(3, 1)
    lib = parse_library("poly:3,sign,abs,xabs,exp,expx,expxx,sin,cos,input", 3, 1)
    L = np.asarray(lib(x, u))
    assert L.shape == (200, lib.K) and L.dtype == np.float64
    col = {name: L[:, k] for k, name in enumerate(lib.names)}
    x1, x2, x3 = x.T
    expected = {
        "1": np.ones(200),
        "x1**2*x2": x1**2 * x2,
        "x1*x2*x3": x1 * x2 * x3,
        "x3**3": x3**3,
        "x1*Abs(x2)": x1 * np.abs(x2),
        "x2*Abs(x2)": x2 * np.abs(x2),
        "exp(-x1*x2)": np.exp(-x1 * x2),
        "exp(-x3**2)": np.exp(-(x3**2)),
        "x1*exp(-x2)": np.exp(-x2) * x1,
        "exp(-x3)": np.exp(-x3),
        "sign(x2)": np.sign(x2),
        "Abs(x3)": np.abs(x3),
        "sin(x1)": np.sin(x1),
        "cos(x3)": np.cos(x3),
        "u1": u[:, 0],
    }
    for name, want in expected.items():
        np.testing.assert_allclose(col[name], want, rtol=1e-14, atol=0, err_msg=name)


def test_columns_match_lambdify():
    m, n = 3, 2
    x, u = _data(m, n, N=100, seed=1)
    lib = parse_library(DEFAULT_LIBRARY + ",expx", m, n)
    L = np.asarray(lib(x, u))
    xs, us = symbols(m, n)
    f = sympy.lambdify(xs + us, [to_sympy(name) for name in lib.names], modules="numpy")
    want = np.stack([np.broadcast_to(c, (100,)) for c in f(*x.T, *u.T)], axis=1)
    np.testing.assert_allclose(L, want, rtol=1e-12, atol=0)


def test_jit_vmap_single():
    lib = default_library(2, 1)
    x, u = _data(2, 1, N=30)
    L = lib(x, u)
    np.testing.assert_array_equal(jax.jit(lib)(x, u), L)
    # Closed over, and as a static argument (hashable).
    np.testing.assert_array_equal(jax.jit(lambda x, u: lib(x, u))(x, u), L)
    f = jax.jit(lambda lib, x, u: lib(x, u), static_argnums=0)
    np.testing.assert_array_equal(f(default_library(2, 1), x, u), L)
    assert hash(lib) == hash(default_library(2, 1)) and lib == default_library(2, 1)
    # Records axis: (R, N, m) -> (R, N, K).
    xr, ur = x.reshape(3, 10, 2), u.reshape(3, 10, 1)
    Lr = jax.vmap(lib)(xr, ur)
    assert Lr.shape == (3, 10, lib.K)
    np.testing.assert_allclose(Lr.reshape(30, -1), L, rtol=1e-15)
    np.testing.assert_allclose(lib(xr, ur).reshape(30, -1), L, rtol=1e-15)
    # One sample.
    single = jax.jit(lib.eval_single)(x[7], u[7])
    assert single.shape == (lib.K,)
    np.testing.assert_allclose(single, L[7], rtol=1e-15)
    # Gradients (used inside ODE right-hand sides) are finite away from the kinks.
    g = jax.jacfwd(lib.eval_single)(jnp.array([0.3, -0.7]), jnp.array([0.2]))
    assert g.shape == (lib.K, 2) and np.isfinite(g).all()


@pytest.mark.parametrize("spec, m, n", [(DEFAULT_LIBRARY + ",expx", 3, 2), ("poly:3,sign,abs,xabs", 2, 0),
                                         ("terms:x2**7;exp(-x1)*x2;u1", 2, 1)])
def test_the_term_table_evaluates_the_design_matrix_of_any_subset(spec, m, n):
    """The library as data gives the design matrix's numbers (to rounding: XLA may fuse a
    product differently), for the whole library and for subsets, with every padding row the
    constant 1; subsets of one size class share the table's shapes (one program)."""
    x, u = _data(m, n, N=100, seed=2)
    lib = parse_library(spec, m, n)
    rng = np.random.default_rng(3)
    shapes = set()
    for keep in [np.ones(lib.K, bool)] + [rng.random(lib.K) < p for p in (0.1, 0.3, 0.5)]:
        sub = lib.subset(keep)
        table = term_table(sub)
        size = table.family.shape[0]
        assert size == next((s for s in (4, 8, 16, 32, 64, 128, 256) if s >= sub.K), sub.K)
        got = np.asarray(jax.jit(eval_terms)(table, jnp.asarray(x), jnp.asarray(u)))
        np.testing.assert_allclose(got[:, : sub.K], np.asarray(sub(x, u if sub.uses_inputs else None)),
                                   rtol=1e-15, atol=0)
        np.testing.assert_array_equal(got[:, sub.K :], 1.0)
        if sub.K <= 4:  # one program per (rows, largest power) class
            shapes.add(jax.tree.map(np.shape, table))
    assert len(shapes) <= len({s.powers for s in shapes})
    # An exponential that no row selects never overflows into a gradient.
    only_poly = term_table(parse_library("poly:2", 2, 0))
    g = jax.jacfwd(lambda z: eval_terms(only_poly, z))(jnp.array([-800.0, 3.0]))
    assert np.isfinite(np.asarray(g)).all()


def test_monomial_gradients_at_zero():
    # ODE right-hand sides are often differentiated at states that are exactly zero.
    lib = parse_library("poly:4", 2, 0)
    xs, _ = symbols(2, 0)
    at = {xs[0]: 0.0, xs[1]: 0.5}
    want = np.array([[float(sympy.diff(to_sympy(n), s).subs(at)) for s in xs] for n in lib.names])
    x0 = jnp.array([0.0, 0.5])
    np.testing.assert_allclose(jax.jacfwd(lib.eval_single)(x0), want, rtol=1e-15, atol=0)
    np.testing.assert_allclose(jax.jacrev(lib.eval_single)(x0), want, rtol=1e-15, atol=0)


def test_no_inputs_needed():
    lib = parse_library("poly:2,sin", 2, 1)
    x, _ = _data(2, 1, N=5)
    assert lib(x).shape == (5, 6 + 2)
    with pytest.raises(DataError, match="no inputs"):
        parse_library("poly:2,input", 2, 1)(x)
    with pytest.raises(DataError, match=r"\(\.\.\., 2\)"):
        lib(np.zeros((5, 3)))


@pytest.mark.parametrize(
    "spec, n, match",
    [
        ("poly:2,foo", 1, r"unknown library family 'foo' \(known: poly:P, sign, abs, xabs, exp, expx"),
        ("sign:2", 1, "unknown library family 'sign:2'"),
        ("Poly:2", 1, "unknown library family"),
        ("poly", 1, "integer degree"),
        ("poly:", 1, "integer degree"),
        ("poly:x", 1, "integer degree"),
        ("poly:2.5", 1, "integer degree"),
        ("poly:-1", 1, "integer degree"),
        ("poly:0", 1, "degree >= 1"),
        ("", 1, "empty"),
        (" , ", 1, "empty"),
        ("poly:2,,sign", 1, "empty family"),
        ("poly:2,poly:3", 1, "'1' appears twice"),
        ("sign,sign", 1, "'sign\\(x1\\)' appears twice"),
        ("poly:2,input", 0, "library family 'input' needs measured inputs"),
    ],
)
def test_parse_errors(spec, n, match):
    with pytest.raises(DataError, match=match):
        parse_library(spec, 2, n)


def test_parse_misc():
    assert parse_library(" poly:2 , sin ", 1, 0).names == ("1", "x1", "x1**2", "sin(x1)")
    assert parse_library("poly:2,sin", 1, 0).spec == "poly:2,sin"
    assert default_library(2, 0).spec == "poly:6,sign,abs,xabs,exp,expxx,sin,cos"
    with pytest.raises(DataError, match="num_states"):
        parse_library("poly:2", 0, 0)
    with pytest.raises(DataError, match="num_inputs"):
        parse_library("poly:2", 1, -1)
    with pytest.raises(DataError, match="cannot parse"):
        to_sympy("x1 +* )")
    assert isinstance(parse_library("sin", 1, 0), Library)


def test_check_columns_passes_on_random_data():
    x, u = _data(4, 2, N=2000, seed=3)
    lib = default_library(4, 2)
    check_columns(lib(x, u), lib.names)


def test_check_columns_duplicates():
    x, u = _data(3, 1, seed=4)
    x[:, 2] = np.abs(x[:, 2]) + 0.1  # x3 > 0: Abs(x3) == x3 and sign(x3) == 1
    lib = parse_library("poly:1,abs", 3, 1)
    with pytest.raises(DataError, match=r"^library columns 'Abs\(x3\)' and 'x3' are duplicates on these data$"):
        check_columns(lib(x, u), lib.names)
    lib = default_library(3, 1)
    with pytest.raises(DataError, match=r"^library columns 'sign\(x3\)' and '1' are duplicates on these data \(also"):
        check_columns(lib(x, u), lib.names)
    # Duplicate up to a negative factor, and up to rounding.
    L = np.stack([x[:, 0], x[:, 1], -2.5 * x[:, 0] * (1 + 1e-15)], axis=1)
    with pytest.raises(DataError, match="'c' and 'a' are duplicates"):
        check_columns(L, ["a", "b", "c"])
    # Nearly but not exactly proportional columns are fine.
    L[:, 2] = x[:, 0] + 1e-6 * x[:, 1]
    check_columns(L, ["a", "b", "c"])


def test_check_columns_zero_and_nonfinite():
    x, u = _data(2, 1, seed=5)
    lib = parse_library("poly:2,sin", 2, 1)
    x0 = x.copy()
    x0[:, 1] = 0.0
    with pytest.raises(DataError, match=r"^library columns 'x2', 'x1\*x2', 'x2\*\*2', 'sin\(x2\)' are all zero"):
        check_columns(lib(x0, u), lib.names)
    x0[:, 0] = 0.0
    five = r"'x1', 'x2', 'x1\*\*2', 'x1\*x2', 'x2\*\*2'"
    with pytest.raises(DataError, match=rf"^library columns {five} and 2 more are all zero"):
        check_columns(lib(x0, u), lib.names)
    lib1 = parse_library("sin", 2, 0)
    with pytest.raises(DataError, match=r"^library column 'sin\(x1\)' is all zero on these data$"):
        check_columns(lib1(x0 + [0.0, 1.0]), lib1.names)
    L = np.asarray(lib(x, u)).copy()
    L[3, 4] = np.nan
    L[5, 7] = np.inf
    with pytest.raises(DataError, match=r"^library columns 'x1\*x2', 'sin\(x2\)' have non-finite values$"):
        check_columns(L, lib.names)
    # exp overflows for very negative states.
    x[0, 0] = -800.0
    lib = parse_library("exp", 2, 0)
    with pytest.raises(DataError, match=r"^library column 'exp\(-x1\)' has non-finite values$"):
        check_columns(lib(x), lib.names)
    with pytest.raises(DataError, match="shape"):
        check_columns(L, lib.names)


def test_column_scales():
    x, u = _data(3, 1, N=500, seed=6)
    lib = default_library(3, 1)
    L = np.asarray(lib(x, u))
    scales = column_scales(np.diag(L.T @ L), L.shape[0])
    np.testing.assert_allclose(scales, np.sqrt(np.mean(L**2, axis=0)), rtol=1e-12)
    assert scales[lib.names.index("1")] == pytest.approx(1.0, rel=1e-14)


def test_speed():
    lib = default_library(4, 2)
    x, u = _data(4, 2, N=1000, seed=7)
    x, u = jnp.asarray(x), jnp.asarray(u)
    f = jax.jit(lib)
    f(x, u).block_until_ready()
    reps = 20
    t0 = time.perf_counter()
    for _ in range(reps):
        f(x, u).block_until_ready()
    dt = (time.perf_counter() - t0) / reps
    print(f"default library m=4 n=2 N=1000 (K={lib.K}): {dt * 1e3:.2f} ms per call (jitted)")
    assert dt < 0.05


def test_smoothed_nonsmooth_families_are_gaussian_averages():
    """`lib(x, smoothing=c)` is the expectation of the exact columns over x + N(0, c)."""
    lib = parse_library("sign,abs,xabs", 2, 0)
    c = np.array([0.0, 0.3**2])  # x1 exact, x2 smoothed
    x = np.array([[0.1, 0.05], [-0.2, 0.4], [0.3, -0.7]])
    # E[f(Z)], Z ~ N(0, 1), by a fine midpoint rule (the integrands jump, so no Gauss rule).
    z = np.linspace(-9, 9, 90001)
    weights = np.exp(-0.5 * z**2) / np.sqrt(2 * np.pi) * (z[1] - z[0])
    shifted = x[:, None, :] + np.sqrt(c)[None, None, :] * z[None, :, None]  # (3, Z, 2)
    expected = np.einsum("q,pqk->pk", weights, np.asarray(lib(shifted)))
    got = np.asarray(lib(x, None, c))
    np.testing.assert_allclose(got, expected, atol=1e-4)  # the grid weight at a jump is 8e-5
    np.testing.assert_array_equal(np.asarray(lib(x, None, np.zeros(2))), np.asarray(lib(x)))


def test_hermite_polynomials_are_unbiased_for_monomials():
    """E[T_n(x + eps)] = x^n for eps ~ N(0, s^2): the exact errors-in-variables correction."""
    from numpy.polynomial.hermite_e import hermegauss

    from dtwin_jax.output_only.kramers_moyal import _hermite_table

    s2 = np.array([0.04, 0.5])
    x = np.array([[0.3, -1.2], [-0.8, 0.1]])
    nodes, weights = hermegauss(20)  # exact for polynomials of degree < 40
    weights = weights / weights.sum()
    noisy = x[:, None, :] + np.sqrt(s2) * nodes[None, :, None]  # (2, 20, 2)
    T = np.asarray(_hermite_table(noisy.reshape(-1, 2), s2, 12)).reshape(2, 20, 2, 13)
    mean = np.einsum("q,pqjn->pjn", weights, T)
    np.testing.assert_allclose(mean, x[:, :, None] ** np.arange(13), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("m, spec", [(2, "poly:5"), (4, "poly:5"), (3, "poly:3"), (1, "poly:4")])
def test_hermite_sums_by_halves_equal_the_sums_of_the_products(m, spec):
    """The weighted sums of every pair's Hermite product, from one matrix product of the
    two halves' distinct products (or directly for one state), equal the direct sums."""
    from dtwin_jax.output_only.kramers_moyal import (
        _hermite_products,
        _hermite_sums,
        _hermite_table,
        _monomials,
    )

    _, exponents, pairs, _ = _monomials(parse_library(spec, m, 0))
    rng = np.random.default_rng(m)
    x, w = jnp.asarray(rng.normal(size=(500, m))), jnp.asarray(rng.uniform(size=500))
    T = _hermite_table(x, jnp.full(m, 0.01), int(pairs.sum(axis=1).max()))
    want = np.asarray(w @ _hermite_products(T, pairs))
    np.testing.assert_allclose(np.asarray(_hermite_sums(T, pairs, w)), want, rtol=1e-11, atol=1e-11 * np.abs(want).max())


def test_drift_statistics_derivatives_match_differentiation_of_the_whole_library():
    """The drift statistics' `d_j L`, `d_j^2 L` (monomials in closed form, block by block)
    equal forward-over-forward differentiation of the whole library, smoothed columns too."""
    from dtwin_jax.output_only.kramers_moyal import _derivatives, _differentiated

    lib = parse_library("poly:4,sign,abs,xabs,exp,expxx,sin,cos,terms:x1**5*x3;x2*exp(-x1)", 3, 0)
    x = jnp.asarray(np.random.default_rng(2).normal(size=(40, 3)))
    smoothing = jnp.array([0.0, 0.3, 0.05])
    got, want = _derivatives(lib, x, smoothing), _differentiated(lib, x, smoothing)
    for g, w in zip(got, want):
        assert g.shape == (3, 40, lib.K)
        np.testing.assert_allclose(np.asarray(g), np.asarray(w), rtol=1e-12, atol=1e-12)


def test_empty_subset_evaluates_to_no_columns():
    # A sweep level where no term passes the PIP threshold gives a model with no terms.
    lib = parse_library("poly:3,sign", 2, 0)
    empty = lib.subset(np.zeros(len(lib.names), bool))
    assert empty.names == ()
    assert empty(jnp.ones((7, 2))).shape == (7, 0)


def test_listed_terms_match_their_families_and_values():
    lib = parse_library("terms:x1**3;x2*x1**2;sign(x2);x2*Abs(x2);exp(-x1)*x2;1;u1", 2, 1)
    assert lib.names == ("x1**3", "x1**2*x2", "sign(x2)", "x2*Abs(x2)", "x2*exp(-x1)", "1", "u1")
    x = np.random.default_rng(0).normal(size=(50, 2))
    u = np.random.default_rng(1).normal(size=(50, 1))
    expected = np.stack([x[:, 0] ** 3, x[:, 0] ** 2 * x[:, 1], np.sign(x[:, 1]), x[:, 1] * np.abs(x[:, 1]),
                         np.exp(-x[:, 0]) * x[:, 1], np.ones(50), u[:, 0]], axis=1)
    np.testing.assert_allclose(np.asarray(lib(x, u)), expected, rtol=1e-14, atol=1e-15)
    mixed = parse_library("poly:1,terms:x1**3", 2, 0)
    assert mixed.names == ("1", "x1", "x2", "x1**3")
    assert parse_library(mixed.spec, 2, 0).names == mixed.names


@pytest.mark.parametrize("spec, message", [
    ("terms:x3**2", "not one of the states"),
    ("terms:tanh(x1)", "none of the library's functions"),
    ("terms:x1;;x2", "empty term"),
    ("poly:3,terms:x1**3", "appears twice"),
])
def test_listed_terms_errors(spec, message):
    with pytest.raises(DataError, match=message):
        parse_library(spec, 2, 0)
