"""Memory a run needs, estimated from its shapes before anything is allocated.

Every estimate is compared with the memory available (:func:`available_bytes`); an
oversize request is refused at once with a one-line :class:`DataError` that names the
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
    """Memory this process may still take: ``MemAvailable`` of ``/proc/meminfo`` (else free
    pages from ``os.sysconf``), lowered to a cgroup's remaining limit.

    **Returns:** bytes (``2**62`` when nothing can be read: no refusal)."""
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
    """``nbytes`` as ``"37 GiB"``, ``"1.5 TiB"``."""
    units = ("bytes", "KiB", "MiB", "GiB", "TiB", "PiB", "EiB")
    value, unit = float(nbytes), 0
    while value >= 1024 and unit < len(units) - 1:
        value, unit = value / 1024, unit + 1
    return f"{value:.2g} {units[unit]}" if value < 10 else f"{value:.0f} {units[unit]}"


def _count(n) -> str:
    """An integer in a message: plain below a million, else ``1e+09``."""
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
    """Number of terms of a library spec (formats.md) for ``m`` states and ``n`` inputs,
    counted without building them (``poly:P`` has ``C(m + P, P)`` monomials), so a huge
    library is refused before its names exist. A token it cannot read counts nothing
    (:func:`dtwin_jax.library.parse_library` says what is wrong with it); a listed term
    met twice counts twice.

    **Arguments:**

    - `spec`: the library spec, e.g. ``"poly:3,sign"``.
    - `num_states`, `num_inputs`: ``m`` and ``n``.

    **Returns:** the number of terms ``K`` (an int, huge for a typo such as ``poly:40``)."""
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
    """Refuse a library of more than :data:`MAX_TERMS` terms (``count``, from
    :func:`dtwin_jax.library.count_terms`) before its names are built."""
    if count > MAX_TERMS:
        raise DataError(f"library '{spec}' has {_count(count)} terms; at most {MAX_TERMS} are supported")


def check_num_inputs(value, inputs: int, where: str) -> None:
    """A saved twin's ``num_inputs`` (``where`` names its file) before a library is built for
    it: 0 (no input terms) or the nominal ``B``'s ``inputs`` columns."""
    if type(value) is not int or value not in (0, inputs):
        raise DataError(f"{where} has num_inputs {value!r}; expected 0 or {inputs} (the nominal B's columns)")


def check_nominal(d: int, extra_states: int, n: int) -> None:
    """The model's ``m = 2d + E`` states: the state-space smoother and the simulators hold
    ``m x m`` matrices (covariances, Jacobians) at every step of a window; ``16 m^2`` floats
    stand for them here."""
    m = 2 * d + extra_states
    _require(16 * m * m * _F64 + 16 * m * max(n, 1) * _F64, f"extra_states {extra_states}",
             f"the nominal model's {_count(m)}-state matrices")


def _lead(values: dict, ratios: dict, names: dict) -> str:
    """``"--draws 1000000000"``: the option furthest above its default."""
    key = max(ratios, key=ratios.get)
    return f"{names[key]} {values[key]}"


def check_sampler(equations: int, terms: int, chains: int, draws: int, burn_in: int, *,
                  library: str = "", names: dict | None = None) -> None:
    """The Gibbs draws of ``equations`` regressions of ``terms`` terms: per sweep and chain
    ``theta`` (float64), ``gamma`` (bool) and four scalars, kept over burn-in and draws in the
    chunks, their concatenation and the stack over equations, plus one key per sweep.

    **Arguments:**

    - `equations`, `terms`: regressions ``q`` and library size ``K``.
    - `chains`, `draws`, `burn_in`: the sampler's settings (sweeps per chain).
    - `library`: the spec, for the message; `names`: how the message calls draws, chains,
      burn_in and library (default the Python names, :data:`API_NAMES`).

    Raises :class:`DataError` naming the option furthest above its default when the
    estimate exceeds :func:`available_bytes`."""
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
    """The design matrix ``samples x terms`` (float64; a few copies: the column checks, the
    statistics, the residuals) and every equation's ``terms x terms`` Gram."""
    names = names or API_NAMES
    need = 4 * samples * terms * _F64 + 2 * equations * terms * terms * _F64
    lead = f"{names['library']} {library}" if terms * 1000 > samples else f"the data's {_count(samples)} samples"
    _require(need, lead.strip(), f"the design matrix ({_count(samples)} samples x {_count(terms)} terms)")


def check_update(samples: int, terms: int, equations: int, chains: int, draws: int, burn_in: int, *,
                 library: str = "", names: dict | None = None) -> None:
    """:func:`check_design` and :func:`check_sampler` of one update, sampler first (the
    common mistake)."""
    check_sampler(equations, terms, chains, draws, burn_in, library=library, names=names)
    check_design(samples, terms, equations, library=library, names=names)


def check_posterior_draws(draws: int, coefficients: int, *, option: str = "num_draws") -> None:
    """Stacked posterior twins: ``draws x coefficients`` floats and their draw indices (a
    few copies)."""
    need = 3 * draws * (coefficients + 2) * _F64
    _require(need, f"{option} {draws}", f"the posterior twins ({_count(draws)} draws x "
             f"{_count(coefficients)} coefficients)")


def check_prediction(draws: int, samples: int, states: int, *, option: str = "num_draws",
                     what: str = "predicted paths", unit: str = "draws") -> None:
    """Simulated paths ``draws x samples x states`` (float64) and the copies the quantiles
    sort (or the solver keeps: ``what`` and ``unit`` name them, e.g. a demo's records)."""
    need = 4 * draws * samples * states * _F64
    _require(need, f"{option} {draws}",
             f"the {what} ({_count(draws)} {unit} x {_count(samples)} samples x {states} states)")


def check_file_arrays(nbytes: int, where: str) -> None:
    """A file's arrays (``nbytes`` as their headers declare them) before they are read: the
    reader holds them and a float64 copy or two."""
    _require(3 * nbytes, where, "its arrays")
