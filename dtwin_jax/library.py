"""Candidate library: named terms evaluated on states (and inputs) to form the design matrix.

States are `x1..xm`, inputs `u1..un`. A library spec is a comma-separated list of families:

| family   | terms                                                  |
|----------|--------------------------------------------------------|
| `poly:P` | `1` and every monomial of total degree 1..P in states  |
| `sign`   | `sign(xi)`                                             |
| `abs`    | `Abs(xi)`                                              |
| `xabs`   | `xi*Abs(xj)` (all i, j)                                |
| `exp`    | `exp(-xi)`                                             |
| `expx`   | `xj*exp(-xi)` (all i, j)                               |
| `expxx`  | `exp(-xi*xj)` (i <= j)                                 |
| `sin`    | `sin(xi)`                                              |
| `cos`    | `cos(xi)`                                              |
| `input`  | `u1..un`                                               |
| `terms:E1;E2;...` | exactly the listed expressions, each one of the terms above |

Every term name is the canonical SymPy string of the term: `str(sympy.sympify(name)) == name`.
Names from outside are parsed by `dtwin_jax.expressions.parse_term`, which runs no
code; nothing here calls `sympify`.
"""

import functools
import itertools
import re
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import sympy

from dtwin_jax._compile.buckets import TABLE_BUCKETS, bucket
from dtwin_jax.errors import DataError
from dtwin_jax.expressions import parse_term
from dtwin_jax.resources import MAX_TERMS, check_terms, count_terms  # noqa: F401 (count_terms: public here too)

DEFAULT_LIBRARY = "poly:6,sign,abs,xabs,exp,expxx,sin,cos,input"
FAMILIES = ("poly", "sign", "abs", "xabs", "exp", "expx", "expxx", "sin", "cos", "input")
_KNOWN = "poly:P, " + ", ".join(FAMILIES[1:])

def symbols(num_states: int, num_inputs: int) -> tuple[tuple[sympy.Symbol, ...], tuple[sympy.Symbol, ...]]:
    """The state and input symbols as plain SymPy symbols (no assumptions, so they equal `sympify`'s).

    **Arguments:**

    - `num_states`: the number of states `m`.
    - `num_inputs`: the number of inputs `n`.

    **Returns:** `(xs, us)`: the symbols `(x1..xm)` and `(u1..un)`.
    """
    xs = tuple(sympy.Symbol(f"x{i + 1}") for i in range(num_states))
    us = tuple(sympy.Symbol(f"u{i + 1}") for i in range(num_inputs))
    return xs, us


def to_sympy(name: str) -> sympy.Expr:
    """Parse a term name into a SymPy expression in `x1..xm`, `u1..un`, without running code.

    Uses `dtwin_jax.expressions.parse_term`.

    **Arguments:**

    - `name`: a term name, e.g. `"x1*Abs(x2)"`.

    **Returns:** the SymPy expression.
    """
    return parse_term(name)


class Library(eqx.Module):
    """A fixed list of named candidate terms; `lib(x, u)` is the design matrix.

    Only static (hashable) fields, so a `Library` can be closed over or passed as a
    static argument to `jax.jit`.

    **Fields:**

    - `names`: the `K` term names, canonical SymPy strings.
    - `num_states`, `num_inputs`: `m` and `n`.
    - `spec`: the library spec this was parsed from.
    - `blocks`: one `(family, indices)` per family in spec order; `indices[k]` is the
      exponent tuple (length `m`) of a monomial for `poly`, else the 0-based state
      (or input) indices `(i,)` or `(i, j)` of the term.
    """

    names: tuple[str, ...] = eqx.field(static=True)
    num_states: int = eqx.field(static=True)
    num_inputs: int = eqx.field(static=True)
    spec: str = eqx.field(static=True)
    blocks: tuple[tuple[str, tuple[tuple[int, ...], ...]], ...] = eqx.field(static=True)

    @property
    def K(self) -> int:
        """Number of terms."""
        return len(self.names)

    @property
    def uses_inputs(self) -> bool:
        return any(family == "input" for family, _ in self.blocks)

    def __call__(self, x, u=None, smoothing=None):
        """Design matrix.

        **Arguments:**

        - `x`: states, shape `(..., m)`.
        - `u`: inputs, shape `(..., n)`; needed only if the library has the `input` family.
        - `smoothing`: optional variances `(m,)`: the non-smooth families (`sign`, `Abs`,
          `x*Abs(y)`) are then their expectations over `x_j + N(0, smoothing_j)` (the
          Gaussian-smoothed `sign(x) -> erf(x / sqrt(2 c))`); zero keeps them exact.

        **Returns:** `L`, shape `(..., K)`, float64.
        """
        x = jnp.asarray(x, dtype=jnp.float64)
        if x.ndim < 1 or x.shape[-1] != self.num_states:
            raise DataError(f"library expects states of shape (..., {self.num_states}), got {x.shape}")
        if self.uses_inputs:
            if u is None:
                raise DataError("library has input terms but no inputs u were given")
            u = jnp.asarray(u, dtype=jnp.float64)
            if u.ndim < 1 or u.shape[-1] != self.num_inputs:
                raise DataError(f"library expects inputs of shape (..., {self.num_inputs}), got {u.shape}")
        if smoothing is not None:
            smoothing = jnp.broadcast_to(jnp.asarray(smoothing, dtype=jnp.float64), (self.num_states,))
        return _design(self, x, u, smoothing)

    def eval_single(self, x, u=None, smoothing=None):
        """The design matrix's row at one sample (the same as calling the library).

        **Arguments:**

        - `x`: states, shape `(m,)`.
        - `u`: inputs, shape `(n,)`, or None; needed only if the library has the `input` family.
        - `smoothing`: variances `(m,)` of Gaussian-smoothed non-smooth terms, or None (default)
          for exact terms (see `Library.__call__`).

        **Returns:** the terms' values, shape `(K,)`, float64.
        """
        return self(x, u, smoothing)

    def subset(self, keep) -> "Library":
        """The library of the columns `keep`, in library order.

        Evaluating only the selected terms keeps an updated model cheap inside a solver.

        **Arguments:**

        - `keep`: the columns to keep, integer indices or a boolean mask `(K,)`.

        **Returns:** a `Library` of those terms, with the same `spec`, `num_states` and
        `num_inputs`.
        """
        keep = np.asarray(keep)
        index = np.flatnonzero(keep) if keep.dtype == bool else keep.astype(int)
        chosen = set(index.tolist())
        blocks, names, start = [], [], 0
        for family, idx in self.blocks:
            sel = [k for k in range(len(idx)) if start + k in chosen]
            if sel:
                blocks.append((family, tuple(idx[k] for k in sel)))
                names.extend(self.names[start + k] for k in sel)
            start += len(idx)
        return Library(tuple(names), self.num_states, self.num_inputs, self.spec, tuple(blocks))


class TermTable(NamedTuple):
    """A library's terms as arrays (data, not program structure): one compiled program
    evaluates any set of terms of the same size (`term_table`, `eval_terms`).

    **Fields:**

    - `family`: `(k,)` int, each term's family, an index into `FAMILIES`.
    - `exponents`: `(k, m)` int, a `poly` term's monomial exponents (zeros otherwise).
    - `index`: `(k, 2)` int, the state (or, for `input`, input) indices `i, j` of the others.
    - `powers`: `(P + 1,)` the powers `0..P` evaluated for the monomials: its length is
      the program's (static), the largest exponent's size class.

    Rows past the library's terms are padding: the monomial `1`, which a zero coefficient
    multiplies.
    """

    family: jax.Array
    exponents: jax.Array
    index: jax.Array
    powers: jax.Array


# A table's largest power is rounded up to these (one program per class).
_POWER_SIZES = (3, 6)


def term_table(lib: Library) -> TermTable:
    """A library's terms as a `TermTable`, padded to its size class.

    The rows are padded to `dtwin_jax._compile.buckets.TABLE_BUCKETS` (4, 8, 16, ... 256
    rows, the library's own size above them), the powers to 3, 6 or the largest exponent.

    **Arguments:**

    - `lib`: the library.

    **Returns:** the `TermTable`, with as many rows as the size class.
    """
    size = bucket(lib.K, TABLE_BUCKETS)
    family = np.zeros(size, dtype=np.int32)
    exponents = np.zeros((size, lib.num_states), dtype=np.int32)
    index = np.zeros((size, 2), dtype=np.int32)
    row = 0
    for name, idx in lib.blocks:
        for t in idx:
            family[row] = FAMILIES.index(name)
            if name == "poly":
                exponents[row] = t
            else:
                index[row] = (t[0], t[-1])
            row += 1
    top = int(exponents.max(initial=1))
    P = next((p for p in _POWER_SIZES if p >= top), top)
    return TermTable(jnp.asarray(family), jnp.asarray(exponents), jnp.asarray(index), jnp.arange(P + 1))


def eval_terms(table: TermTable, x, u=None):
    """The table's terms at states and inputs: the library's design matrix (unsmoothed) to rounding.

    Every family is evaluated at every row and the row's own selected (the others' arguments
    are replaced by zero first, so an exponential that no row uses cannot overflow into a
    gradient).

    **Arguments:**

    - `table`: the terms, from `term_table`.
    - `x`: states, shape `(..., m)`.
    - `u`: inputs, shape `(..., n)`, or None (no inputs), which leaves `input` rows at 1: pass
      `u` whenever the table has them.

    **Returns:** the terms' values, shape `(..., k)` (`k` the table's rows, padding included).
    """
    code = {name: FAMILIES.index(name) for name in FAMILIES}
    f, i, j = table.family, table.index[:, 0], table.index[:, 1]
    P = table.powers.shape[0] - 1
    powers = [jnp.ones_like(x), x]
    for _ in range(P - 1):
        powers.append(powers[-1] * x)
    powers = jnp.stack(powers, axis=-1)  # (..., m, P + 1)
    m = x.shape[-1]
    values = jnp.prod(powers[..., np.arange(m)[None, :], table.exponents], axis=-1)
    on_input = f == code["input"]
    xi, xj = x[..., jnp.where(on_input, 0, i)], x[..., j]
    exp_i = jnp.exp(-jnp.where((f == code["exp"]) | (f == code["expx"]), xi, 0.0))
    exp_ij = jnp.exp(-jnp.where(f == code["expxx"], xi * xj, 0.0))
    others = {"sign": jnp.sign(xi), "abs": jnp.abs(xi), "xabs": xi * jnp.abs(xj), "exp": exp_i, "expx": exp_i * xj,
              "expxx": exp_ij, "sin": jnp.sin(xi), "cos": jnp.cos(xi)}
    if u is not None and u.shape[-1] > 0:
        others["input"] = u[..., jnp.where(on_input, i, 0)]
    for name, value in others.items():
        values = jnp.where(f == code[name], value, values)
    return values


# Jitted so eager calls compile once per library and shape, not once per primitive.
@functools.partial(jax.jit, static_argnums=0)
def _design(lib, x, u, smoothing=None):
    cols = [_eval_block(family, np.asarray(idx, dtype=np.intp), x, u, smoothing) for family, idx in lib.blocks]
    if not cols:  # an empty subset: a model with no discovered terms
        return jnp.zeros(x.shape[:-1] + (0,), x.dtype)
    return jnp.concatenate(cols, axis=-1)


def _smoothed_sign(x, c):
    """`E[sign(x + sqrt(c) Z)] = erf(x / sqrt(2 c))`; `sign(x)` where `c == 0`."""
    safe = jnp.where(c > 0, c, 1.0)
    return jnp.where(c > 0, jax.scipy.special.erf(x / jnp.sqrt(2 * safe)), jnp.sign(x))


def _smoothed_abs(x, c):
    """`E|x + sqrt(c) Z| = x erf(x / sqrt(2c)) + sqrt(2c / pi) exp(-x^2 / 2c)`."""
    safe = jnp.where(c > 0, c, 1.0)
    bump = jnp.where(c > 0, jnp.sqrt(2 * safe / jnp.pi) * jnp.exp(-(x**2) / (2 * safe)), 0.0)
    return x * _smoothed_sign(x, c) + bump


def _smoothed_xabs(x, c):
    """`E[y |y|]` for `y = x + sqrt(c) Z`: `(x^2 + c) erf(x / sqrt(2c)) + x sqrt(2c / pi) exp(-x^2 / 2c)`."""
    safe = jnp.where(c > 0, c, 1.0)
    bump = jnp.where(c > 0, jnp.sqrt(2 * safe / jnp.pi) * jnp.exp(-(x**2) / (2 * safe)), 0.0)
    return (x**2 + c) * _smoothed_sign(x, c) + x * bump


def monomials(x, exponents):
    """Monomials `prod_j x_j**e_j` of the states, by repeated products.

    Powers are formed by repeated products (exact `x**0 == 1`, no `pow()` calls), then gathered.

    **Arguments:**

    - `x`: states, shape `(..., m)`.
    - `exponents`: the monomials' exponents, shape `(k, m)`, non-negative integers.

    **Returns:** the monomials, shape `(..., k)`.
    """
    exponents = np.asarray(exponents, dtype=int)
    powers = [jnp.ones_like(x), x]
    for _ in range(int(exponents.max(initial=1)) - 1):
        powers.append(powers[-1] * x)
    powers = jnp.stack(powers, axis=-1)  # (..., m, P + 1)
    m = x.shape[-1]
    return jnp.prod(powers[..., np.arange(m)[None, :], exponents], axis=-1)


def _eval_block(family, idx, x, u, smoothing=None):
    """Columns of one family; `idx` as in `Library.blocks`, shape `(k, m)` or `(k, 1|2)`.
    `smoothing (m,)` variances replace the non-smooth families by their Gaussian averages."""
    if smoothing is not None and family in ("sign", "abs", "xabs"):
        i, j = idx[:, 0], idx[:, -1]
        c = smoothing[j]
        if family == "sign":
            return _smoothed_sign(x[..., i], c)
        if family == "abs":
            return _smoothed_abs(x[..., i], c)
        same = jnp.asarray(idx[:, 0] == idx[:, 1])
        # x_i |x_j| with i != j: independent increments (smoothing acts on velocities only).
        return jnp.where(same, _smoothed_xabs(x[..., j], c), x[..., i] * _smoothed_abs(x[..., j], c))
    if family == "poly":
        return monomials(x, idx)
    i = idx[:, 0]
    if family == "sign":
        return jnp.sign(x[..., i])
    if family == "abs":
        return jnp.abs(x[..., i])
    if family == "exp":
        return jnp.exp(-x[..., i])
    if family == "sin":
        return jnp.sin(x[..., i])
    if family == "cos":
        return jnp.cos(x[..., i])
    if family == "input":
        return u[..., i]
    j = idx[:, 1]
    if family == "xabs":
        return x[..., i] * jnp.abs(x[..., j])
    if family == "expx":
        return jnp.exp(-x[..., i]) * x[..., j]
    if family == "expxx":
        return jnp.exp(-x[..., i] * x[..., j])
    raise AssertionError(family)


def _family_terms(family, degree, xs, us):
    """`(indices, raw names)` of one family; names are canonicalised by the caller."""
    m = len(xs)
    if family == "poly":
        idx, raw = [(0,) * m], ["1"]
        for d in range(1, degree + 1):
            for combo in itertools.combinations_with_replacement(range(m), d):
                e = tuple(combo.count(k) for k in range(m))
                idx.append(e)
                raw.append(str(sympy.Mul(*(xs[k] ** e[k] for k in range(m)))))
        return idx, raw
    ii = [(i,) for i in range(m)]
    pairs = [(i, j) for i in range(m) for j in range(m)]
    upper = [(i, j) for i in range(m) for j in range(i, m)]
    table = {
        "sign": (ii, "sign(x{i})"),
        "abs": (ii, "Abs(x{i})"),
        "xabs": (pairs, "x{i}*Abs(x{j})"),
        "exp": (ii, "exp(-x{i})"),
        "expx": (pairs, "exp(-x{i})*x{j}"),
        "expxx": (upper, "exp(-x{i}*x{j})"),
        "sin": (ii, "sin(x{i})"),
        "cos": (ii, "cos(x{i})"),
        "input": ([(i,) for i in range(len(us))], "u{i}"),
    }
    idx, fmt = table[family]
    return idx, [fmt.format(i=t[0] + 1, j=t[-1] + 1) for t in idx]


def _parse_family(token):
    """`(family, degree)` of one spec token; degree is None except for poly."""
    name, sep, arg = token.partition(":")
    if name == "poly":
        if not sep or not re.fullmatch(r"\+?\d+", arg.strip()):
            raise DataError(f"library family {token!r} needs an integer degree, e.g. 'poly:3'")
        degree = int(arg)
        if degree < 1:
            raise DataError(f"library family {token!r} needs a degree >= 1")
        return "poly", degree
    if sep or name not in FAMILIES:
        raise DataError(f"unknown library family {token!r} (known: {_KNOWN})")
    return name, None


def _monomial_exponents(expr, xs):
    """The exponents `(m,)` of `expr` when it is a monomial in the states with coefficient 1
    (SymPy's canonical `1`, `x`, `x**p` or a product of those), else None. Read from the
    expression's structure: nothing is expanded."""
    factors = expr.args if isinstance(expr, sympy.Mul) else (expr,)
    exponents = [0] * len(xs)
    for f in factors:
        base, power = f.as_base_exp()
        if base not in xs or not (power.is_Integer and power > 0):
            return None if f != 1 else exponents
        exponents[xs.index(base)] += int(power)
    return exponents


def _listed_terms(token, xs, us):
    """`[(family, index, name)]` of a `terms:E1;E2;...` token: each expression is matched,
    after SymPy's canonical printing, to the family term that evaluates it."""
    exprs = [e.strip() for e in token.partition(":")[2].split(";")]
    if not all(exprs):
        raise DataError(f"library family {token!r} lists an empty term")
    known = {s_.name for s_ in xs + us}
    families = {}  # the other families' names, generated once per token
    out = []
    for e in exprs:
        expr = to_sympy(e)
        unknown = sorted(str(f) for f in expr.free_symbols if f.name not in known)
        if unknown:
            raise DataError(f"library term {e!r} uses {unknown[0]!r}, not one of the states x1..x{len(xs)}"
                            + (f" or inputs u1..u{len(us)}" if us else ""))
        name = str(expr)
        exponents = _monomial_exponents(expr, xs)
        if exponents is not None:
            out.append(("poly", tuple(exponents), name))
            continue
        for family in FAMILIES[1:]:
            if family == "input" and not us:
                continue
            if family not in families:
                idx, raw = _family_terms(family, None, xs, us)
                families[family] = idx, [str(to_sympy(r)) for r in raw]
            idx, names = families[family]
            if name in names:
                out.append((family, tuple(idx[names.index(name)]), name))
                break
        else:
            raise DataError(
                f"library term {e!r} is none of the library's functions (monomials, sign, Abs, x*Abs(y), "
                "exp(-x), exp(-x)*y, exp(-x*y), sin, cos, u)"
            )
    return out


def parse_library(spec: str, num_states: int, num_inputs: int) -> Library:
    """Build the library of a spec such as `"poly:3,sign,abs"`.

    A malformed spec, an unknown family, a term listed twice or too many terms raise a
    one-line `DataError`.

    **Arguments:**

    - `spec`: the library spec, a comma-separated list of families (module docstring).
    - `num_states`: the number of states `m`, at least 1.
    - `num_inputs`: the number of inputs `n`, at least 0; the `input` family needs one.

    **Returns:** the `Library`.
    """
    if not isinstance(num_states, (int, np.integer)) or num_states < 1:
        raise DataError(f"library needs num_states >= 1, got {num_states!r}")
    if not isinstance(num_inputs, (int, np.integer)) or num_inputs < 0:
        raise DataError(f"library needs num_inputs >= 0, got {num_inputs!r}")
    tokens = [t.strip() for t in str(spec).split(",")]
    if not any(tokens):
        raise DataError("library spec is empty")
    if not all(tokens):
        raise DataError(f"library spec {spec!r} has an empty family")
    for name, value in (("num_states", num_states), ("num_inputs", num_inputs)):
        if value > MAX_TERMS:  # each is a SymPy symbol below, used or not
            raise DataError(f"library needs {name} <= {MAX_TERMS}, got {value}")
    check_terms(count_terms(spec, num_states, num_inputs), spec)
    xs, us = symbols(int(num_states), int(num_inputs))
    blocks, names, seen = [], [], set()
    for token in tokens:
        if token.startswith("terms:"):
            listed = _listed_terms(token, xs, us)
            parts = [(family, [idx], [name]) for family, idx, name in listed]
        else:
            family, degree = _parse_family(token)
            if family == "input" and num_inputs == 0:
                raise DataError("library family 'input' needs measured inputs")
            idx, raw = _family_terms(family, degree, xs, us)
            # Monomials are already str(sympy.Mul); the rest go through SymPy's printer.
            parts = [(family, idx, [r if family == "poly" else str(to_sympy(r)) for r in raw])]
        for family, idx, part_names in parts:
            for name in part_names:
                if name in seen:
                    raise DataError(f"library term {name!r} appears twice in spec {spec!r}")
                seen.add(name)
                names.append(name)
            blocks.append((family, tuple(tuple(t) for t in idx)))
    return Library(
        names=tuple(names),
        num_states=int(num_states),
        num_inputs=int(num_inputs),
        spec=",".join(tokens),
        blocks=tuple(blocks),
    )


def default_library(num_states: int, num_inputs: int) -> Library:
    """The paper's library `DEFAULT_LIBRARY`, without `input` when there are no inputs.

    **Arguments:**

    - `num_states`: the number of states `m`.
    - `num_inputs`: the number of inputs `n`; 0 drops the `input` family.

    **Returns:** the `Library`.
    """
    spec = DEFAULT_LIBRARY
    if num_inputs == 0:
        spec = ",".join(t for t in spec.split(",") if t != "input")
    return parse_library(spec, num_states, num_inputs)


def column_scales(gram_diag, n):
    """RMS of each library column, `sqrt(diag(L^T L) / N)`, from sufficient statistics.

    The sampler standardises columns by these scales internally (`L / scale`), so every
    reported coefficient is divided back into physical units:
    `theta_physical = beta_scaled / scale`.

    **Arguments:**

    - `gram_diag`: `diag(L^T L)`, shape `(K,)`.
    - `n`: number of rows `N` summed into it.

    **Returns:** scales, shape `(K,)`, in the physical units of each column.
    """
    return jnp.sqrt(jnp.asarray(gram_diag, dtype=jnp.float64) / n)


def _columns(names, plural, singular, limit=5):
    """`"library columns 'a', 'b' <plural>"`, or the singular form for one name."""
    if len(names) == 1:
        return f"library column {names[0]!r} {singular}"
    shown = ", ".join(repr(n) for n in names[:limit])
    if len(names) > limit:
        shown += f" and {len(names) - limit} more"
    return f"library columns {shown} {plural}"


def check_columns(L, names, *, rtol: float = 1e-10) -> None:
    """Raise `DataError` if the design matrix cannot identify its terms.

    Checks, in order: non-finite entries; all-zero columns (max |col| == 0); pairs of
    columns equal up to a nonzero factor, i.e. after scaling each to unit RMS,
    `max|c_i - c_j| <= rtol` or `max|c_i + c_j| <= rtol`.

    **Arguments:**

    - `L`: design matrix, shape `(N, K)`.
    - `names`: the `K` term names.
    - `rtol`: duplicate tolerance on unit-RMS columns.
    """
    names = tuple(names)
    zero, pairs = degenerate_columns(L, names, rtol=rtol)
    if zero:
        raise DataError(_columns([names[i] for i in zero], "are all zero on these data", "is all zero on these data"))
    if pairs:
        text = [f"{names[j]!r} and {names[i]!r}" for i, j in pairs]
        more = f" (also {'; '.join(text[1:4])}{'; ...' if len(text) > 4 else ''})" if len(text) > 1 else ""
        raise DataError(f"library columns {text[0]} are duplicates on these data{more}")


def degenerate_columns(L, names, *, rtol: float = 1e-10) -> tuple[list[int], list[tuple[int, int]]]:
    """The columns of a design matrix that cannot be identified on these data.

    These are all-zero columns, and pairs `(i, j)`, `i < j`, equal up to a nonzero factor (as
    `check_columns` defines it). Raises `DataError` for a shape mismatch, no rows or
    non-finite entries.

    **Arguments:**

    - `L`: design matrix, shape `(N, K)`.
    - `names`: the `K` term names (for error messages).
    - `rtol`: duplicate tolerance on unit-RMS columns.

    **Returns:** `(zero, pairs)`: indices of the all-zero columns, and the duplicate pairs
    ordered by `j`."""
    L = np.asarray(L, dtype=np.float64)
    names = tuple(names)
    if L.ndim != 2 or L.shape[1] != len(names):
        raise DataError(f"library matrix has shape {L.shape}, expected (N, {len(names)})")
    n, k = L.shape
    if n == 0:
        raise DataError("library matrix has no rows")
    bad = np.flatnonzero(~np.isfinite(L).all(axis=0))
    if bad.size:
        raise DataError(_columns([names[i] for i in bad], "have non-finite values", "has non-finite values"))
    maxabs = np.maximum(L.max(axis=0), -L.min(axis=0))  # no |L| temporary
    zero = np.flatnonzero(maxabs == 0.0).tolist()
    live = np.flatnonzero(maxabs > 0.0)
    # Cosine similarity of columns, accumulated in row chunks of L / maxabs (no overflow,
    # no full copy). max|c_i -+ c_j| <= rtol implies 1 - |cos| <= rtol**2 / 2, so the
    # Gram only short-lists candidates (with slack for its rounding); each is then
    # confirmed with the exact max-abs test.
    Ll, scale = L[:, live], maxabs[live]
    kl = live.size
    gram = np.zeros((kl, kl))
    chunk = max(1, 2**20 // max(kl, 1))
    for start in range(0, n, chunk):
        block = Ll[start : start + chunk] / scale
        gram += block.T @ block
    norm = np.sqrt(np.diag(gram))
    cos = gram / np.outer(norm, norm)
    slack = max(rtol**2, 1e-9)
    cand_i, cand_j = np.nonzero(np.triu(np.abs(cos) >= 1.0 - slack, k=1))
    rms = norm / np.sqrt(n) * scale
    pairs = []
    for i, j in sorted(zip(cand_i.tolist(), cand_j.tolist()), key=lambda p: (p[1], p[0])):
        ci, cj = Ll[:, i] / rms[i], Ll[:, j] / rms[j]
        if np.max(np.abs(ci - np.sign(cos[i, j]) * cj)) <= rtol:
            pairs.append((int(live[i]), int(live[j])))
    return zero, pairs


def without_degenerate_columns(lib: Library, L) -> tuple[Library, list[str]]:
    """A library without the columns these data cannot identify (`degenerate_columns`).

    Dropped are all-zero columns and, of each duplicate pair, the later term (the simpler
    term, listed first by the families, stays: `1` over `sign(x1)` when `x1 > 0` throughout).

    **Arguments:**

    - `lib`: the library.
    - `L`: its design matrix on the data, shape `(N, K)`.

    **Returns:** `(library, dropped)`: the reduced library (spec `terms:...` of the kept
    names, so that it saves and reloads; `lib` itself when nothing is dropped) and one text
    per dropped term, e.g. `"sign(x1) (= 1)"`.
    """
    zero, pairs = degenerate_columns(L, lib.names)
    drop = {k: "all zero" for k in zero}
    for i, j in pairs:
        if i not in drop:
            drop.setdefault(j, f"= {lib.names[i]}")
    if not drop:
        return lib, []
    kept = [name for k, name in enumerate(lib.names) if k not in drop]
    if not kept:
        raise DataError("every library column is all zero or a duplicate on these data")
    reduced = parse_library("terms:" + ";".join(kept), lib.num_states, lib.num_inputs)
    return reduced, [f"{lib.names[k]} ({why})" for k, why in sorted(drop.items())]
