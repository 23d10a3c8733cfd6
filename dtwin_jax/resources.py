"""Memory a run needs, estimated from its shapes before anything is allocated.

Every estimate is compared with the memory available (`available_bytes`); an
oversize request is refused at once with a one-line `DataError` that names the
option and the estimate, instead of a run that allocates for minutes and is killed.
The estimates are peaks to within a small factor (the copies each stage makes), not exact.

Imports nothing heavy, so the command line checks before it imports JAX's programs.
"""

from __future__ import annotations

import math
import os

from dtwin_jax.errors import DataError

__all__ = [
    "MAX_TERMS", "available_bytes", "count_terms", "check_terms", "check_num_inputs", "check_nominal", "check_update", "check_sampler",
    "check_design", "check_prediction", "check_posterior_draws", "check_file_arrays",
]

# A library this large is a typo (poly:40), not a model: its Gram alone is 800 MB per equation.
MAX_TERMS = 10_000

# Labels of the sampler's settings in messages: the Python names (the command line passes its own).
API_NAMES = {"draws": "num_draws", "chains": "num_chains", "burn_in": "num_burnin", "library": "library"}

_F64 = 8
_KEY = 8  # one threefry key: two uint32


def available_bytes() -> int:
    """Memory this process may still take, in bytes.

    `MemAvailable` of `/proc/meminfo` (else free pages from `os.sysconf`), lowered to a
    cgroup's remaining limit.

    **Returns:** the bytes available, an int (`2**62` when nothing can be read: no refusal).
    """
    avail = None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    avail = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError):
        pass
    if avail is None:
        try:
            avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (OSError, ValueError, AttributeError):
            return 2**62  # unknown: do not refuse
    try:  # a container's limit (cgroup v2) can be far below the machine's free memory
        with open("/sys/fs/cgroup/memory.max") as f:
            limit = f.read().strip()
        if limit != "max":
            with open("/sys/fs/cgroup/memory.current") as f:
                avail = min(avail, int(limit) - int(f.read()))
    except (OSError, ValueError):
        pass
    return max(int(avail), 0)


def size_text(nbytes: float) -> str:
    """A byte count as a reader's text, such as `"37 GiB"` or `"1.5 TiB"`.

    **Arguments:**

    - `nbytes`: the size in bytes.

    **Returns:** the text: two significant digits below 10 of the unit, else a whole number.
    """
    units = ("bytes", "KiB", "MiB", "GiB", "TiB", "PiB", "EiB")
    value, unit = float(nbytes), 0
    while value >= 1024 and unit < len(units) - 1:
        value, unit = value / 1024, unit + 1
    return f"{value:.2g} {units[unit]}" if value < 10 else f"{value:.0f} {units[unit]}"


def _count(n) -> str:
    """An integer in a message: plain below a million, else `1e+09`."""
    if n > 1e300:
        return "more than 1e+300"
    return str(int(n)) if n < 1_000_000 else f"{float(n):.3g}"


def _plural(n, word: str) -> str:
    return f"{_count(n)} {word}{'' if n == 1 else 's'}"


def _require(need: float, lead: str, what: str) -> None:
    avail = available_bytes()
    if need > avail:
        raise DataError(f"{lead} needs about {size_text(need)} for {what}; {size_text(avail)} is available")


def count_terms(spec: str, num_states: int, num_inputs: int) -> int:
    """Number of terms of a library spec (formats.md) for `m` states and `n` inputs.

    Counted without building them (`poly:P` has `C(m + P, P)` monomials), so a huge library is
    refused before its names exist. A token it cannot read counts nothing
    (`dtwin_jax.library.parse_library` says what is wrong with it); a listed term met twice
    counts twice.

    **Arguments:**

    - `spec`: the library spec, e.g. `"poly:3,sign"`.
    - `num_states`: the number of states `m`.
    - `num_inputs`: the number of inputs `n` (the `input` family's terms).

    **Returns:** the number of terms `K` (an int, huge for a typo such as `poly:40`).
    """
    m, total = int(num_states), 0
    for token in (t.strip() for t in str(spec).split(",")):
        name, _, arg = token.partition(":")
        if name == "terms":
            total += arg.count(";") + 1
        elif name == "poly":
            degree = int(arg) if arg.strip().lstrip("+").isdigit() else 0
            k = min(m, degree)  # both past 1000: astronomically many, and math.comb would be slow
            total += math.comb(m + degree, k) if k <= 1000 else 2**1000
        else:
            total += {"xabs": m * m, "expx": m * m, "expxx": m * (m + 1) // 2, "input": int(num_inputs),
                      "sign": m, "abs": m, "exp": m, "sin": m, "cos": m}.get(token, 0)
    return total


def check_terms(count: int, spec: str) -> None:
    """Refuse a library of more than `MAX_TERMS` terms before its names are built.

    **Arguments:**

    - `count`: the library's number of terms, from `dtwin_jax.library.count_terms`.
    - `spec`: the library spec, for the message.

    Raises `DataError` when `count` exceeds `MAX_TERMS`.
    """
    if count > MAX_TERMS:
        raise DataError(f"library '{spec}' has {_count(count)} terms; at most {MAX_TERMS} are supported")


def check_num_inputs(value, inputs: int, where: str) -> None:
    """Check a saved twin's `num_inputs` before a library is built for it.

    It must be 0 (no input terms) or the nominal `B`'s number of columns.

    **Arguments:**

    - `value`: the twin's `num_inputs`, as read from its file.
    - `inputs`: the number of columns of the nominal `B` (the model's inputs `n`).
    - `where`: names the twin's file in the message.

    Raises `DataError` for any other value (or a non-int).
    """
    if type(value) is not int or value not in (0, inputs):
        raise DataError(f"{where} has num_inputs {value!r}; expected 0 or {inputs} (the nominal B's columns)")


def check_nominal(d: int, extra_states: int, n: int) -> None:
    """Refuse a nominal model whose `m = 2d + E` states do not fit in memory.

    The state-space smoother and the simulators hold `m x m` matrices (covariances, Jacobians)
    at every step of a window; `16 m^2` floats stand for them here.

    **Arguments:**

    - `d`: the degrees of freedom (the size of `M`, `C` and `K`).
    - `extra_states`: the extra states `E` beyond the `2d` displacements and velocities.
    - `n`: the number of inputs (columns of `B`).

    Raises `DataError` naming `extra_states` when the estimate exceeds `available_bytes`.
    """
    m = 2 * d + extra_states
    _require(16 * m * m * _F64 + 16 * m * max(n, 1) * _F64, f"extra_states {extra_states}",
             f"the nominal model's {_count(m)}-state matrices")


def _lead(values: dict, ratios: dict, names: dict) -> str:
    """`"--draws 1000000000"`: the option furthest above its default."""
    key = max(ratios, key=ratios.get)
    return f"{names[key]} {values[key]}"


def check_sampler(equations: int, terms: int, chains: int, draws: int, burn_in: int, *,
                  library: str = "", names: dict | None = None) -> None:
    """Refuse Gibbs draws that do not fit in memory.

    The draws of `equations` regressions of `terms` terms: per sweep and chain `theta`
    (float64), `gamma` (bool) and four scalars, kept over burn-in and draws in the chunks,
    their concatenation and the stack over equations, plus one key per sweep.

    **Arguments:**

    - `equations`: the number of regressions `q`.
    - `terms`: the library size `K`.
    - `chains`: the number of chains.
    - `draws`: the draws kept per chain.
    - `burn_in`: the burn-in sweeps per chain.
    - `library`: the library spec, for the message (default: the number of terms stands for it).
    - `names`: how the message calls draws, chains, `burn_in` and library (keys `"draws"`,
      `"chains"`, `"burn_in"`, `"library"`), e.g. the command line's options; None (default)
      for the Python names, `API_NAMES`.

    Raises `DataError` naming the option furthest above its default when the
    estimate exceeds `available_bytes`.
    """
    names = names or API_NAMES
    per_draw = terms * (_F64 + 1) + 4 * _F64
    sweeps = burn_in + draws
    need = (2 * equations + 2) * chains * sweeps * per_draw + 2 * chains * (sweeps + 250) * _KEY
    values = {"draws": draws, "chains": chains, "burn_in": burn_in, "library": library or f"({terms} terms)"}
    ratios = {"draws": draws / 2000, "chains": chains / 4, "burn_in": burn_in / 1000, "library": terms / 100}
    _require(need, _lead(values, ratios, names),
             f"the posterior draws ({_plural(equations, 'equation')} x {_plural(chains, 'chain')} x "
             f"{_count(sweeps)} sweeps (burn-in and draws) x {_plural(terms, 'term')})")


def check_design(samples: int, terms: int, equations: int, *, library: str = "", names: dict | None = None) -> None:
    """Refuse a design matrix that does not fit in memory.

    The design matrix `samples x terms` (float64; a few copies: the column checks, the
    statistics, the residuals) and every equation's `terms x terms` Gram.

    **Arguments:**

    - `samples`: the number of samples (rows of the design matrix).
    - `terms`: the library size `K`.
    - `equations`: the number of regressions `q`.
    - `library`: the library spec, for the message.
    - `names`: how the message calls the library option (key `"library"`); None (default) for
      the Python names, `API_NAMES`.

    Raises `DataError` naming the library (or the data's samples, when they dominate) when the
    estimate exceeds `available_bytes`.
    """
    names = names or API_NAMES
    need = 4 * samples * terms * _F64 + 2 * equations * terms * terms * _F64
    lead = f"{names['library']} {library}" if terms * 1000 > samples else f"the data's {_count(samples)} samples"
    _require(need, lead.strip(), f"the design matrix ({_count(samples)} samples x {_count(terms)} terms)")


def check_update(samples: int, terms: int, equations: int, chains: int, draws: int, burn_in: int, *,
                 library: str = "", names: dict | None = None) -> None:
    """`check_design` and `check_sampler` of one update, sampler first (the common mistake).

    **Arguments:**

    - `samples`: the number of samples (rows of the design matrix).
    - `terms`: the library size `K`.
    - `equations`: the number of regressions `q`.
    - `chains`: the number of chains.
    - `draws`: the draws kept per chain.
    - `burn_in`: the burn-in sweeps per chain.
    - `library`: the library spec, for the message.
    - `names`: how the messages call the options, as for `check_sampler`; None (default) for
      `API_NAMES`.
    """
    check_sampler(equations, terms, chains, draws, burn_in, library=library, names=names)
    check_design(samples, terms, equations, library=library, names=names)


def check_posterior_draws(draws: int, coefficients: int, *, option: str = "num_draws") -> None:
    """Refuse stacked posterior twins that do not fit in memory.

    `draws x coefficients` floats and their draw indices (a few copies).

    **Arguments:**

    - `draws`: the number of posterior draws.
    - `coefficients`: the number of coefficients per draw (all equations' terms together).
    - `option`: how the message calls the number of draws (default `"num_draws"`; `"--draws"`
      on the command line).
    """
    need = 3 * draws * (coefficients + 2) * _F64
    _require(need, f"{option} {draws}", f"the posterior twins ({_count(draws)} draws x "
             f"{_count(coefficients)} coefficients)")


def check_prediction(draws: int, samples: int, states: int, *, option: str = "num_draws",
                     what: str = "predicted paths", unit: str = "draws") -> None:
    """Refuse simulated paths that do not fit in memory.

    Paths `draws x samples x states` (float64) and the copies the quantiles sort (or the
    solver keeps).

    **Arguments:**

    - `draws`: the number of paths (posterior draws, or a demo's records).
    - `samples`: the time samples per path.
    - `states`: the states per sample `m`.
    - `option`: how the message calls the number of paths (default `"num_draws"`).
    - `what`: what the message calls the paths (default `"predicted paths"`).
    - `unit`: what the message calls one path (default `"draws"`; a demo's `"records"`, say).
    """
    need = 4 * draws * samples * states * _F64
    _require(need, f"{option} {draws}",
             f"the {what} ({_count(draws)} {unit} x {_count(samples)} samples x {states} states)")


def check_file_arrays(nbytes: int, where: str) -> None:
    """Refuse a file's arrays that do not fit in memory, before they are read.

    The reader holds them and a float64 copy or two.

    **Arguments:**

    - `nbytes`: the arrays' size in bytes, as their headers declare them (or the file's size).
    - `where`: names the file in the message.
    """
    _require(3 * nbytes, where, "its arrays")
