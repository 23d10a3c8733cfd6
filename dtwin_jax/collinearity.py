"""Library terms the measured data cannot tell apart: groups of nearly collinear columns,
found from the Gram `L^T L` the sampler saw, reported as a check of the result, and the
group's joint coefficient that the posterior-mean twin uses in place of each term's own.

A positioning stage whose position never changes sign has `x1*x2` and `x2*Abs(x1)` as
one column: the sampler selects both, each with the whole effect given its inclusion, and
a twin at the conditional means counts the term twice."""

from __future__ import annotations

import numpy as np

from dtwin_jax.errors import DataError

__all__ = ["COSINE_MIN", "PIP_MIN", "collinear_groups", "collinearity_checks", "group_coefficients", "twin_coefficients"]

# Uncentred cosine (the library has a constant column '1': centring would hide a column that
# is a constant plus a small ripple). 1 - 1e-4 leaves a distinguishing component of
# sqrt(1 - cos^2) = 1.4% of the column's norm, below the noise and model error the residual
# carries, while example 1's closest library pair sits far below it (tests/test_collinearity.py).
COSINE_MIN = 1.0 - 1e-4
# A group is reported when one of its terms has this PIP: below, neither enters the twin.
PIP_MIN = 0.1


def collinear_groups(gram, *, cosine_min: float = COSINE_MIN) -> list[tuple[list[int], float]]:
    """Connected components of the graph `|cos(L_i, L_j)| > cosine_min` of a Gram.

    **Arguments:**

    - `gram`: `L^T L` of one equation, shape `(K, K)`, any units.
    - `cosine_min`: the uncentred cosine above which two columns are joined.

    **Returns:** `[(indices, cosine), ...]`, every component of two or more columns, each
    with its sorted column indices and the smallest `|cos|` of the edges joining it (the
    weakest link), in order of their first column. Columns with a non-positive diagonal (a
    noise-corrected Gram can have one) join nothing.
    """
    g = np.asarray(gram, dtype=np.float64)
    if g.ndim != 2 or g.shape[0] != g.shape[1]:
        raise DataError(f"Gram has shape {g.shape}, expected (K, K)")
    diag = np.diag(g)
    ok = np.isfinite(diag) & (diag > 0)
    norm = np.sqrt(np.where(ok, diag, 1.0))
    with np.errstate(invalid="ignore"):
        cos = np.abs(g / np.outer(norm, norm))
    edge = (cos > cosine_min) & np.outer(ok, ok)
    np.fill_diagonal(edge, False)
    label = np.arange(len(g))
    for i, j in zip(*np.nonzero(np.triu(edge))):  # union-find, a few edges at most
        a, b = _root(label, i), _root(label, j)
        label[max(a, b)] = min(a, b)
    roots = np.array([_root(label, k) for k in range(len(g))])
    groups = []
    for r in np.unique(roots):
        idx = np.flatnonzero(roots == r)
        if idx.size > 1:
            sub = np.where(edge[np.ix_(idx, idx)], cos[np.ix_(idx, idx)], np.inf)
            groups.append((idx.tolist(), float(sub.min())))
    return groups


def _root(label, k):
    while label[k] != k:
        k = label[k]
    return k


def collinearity_checks(statistics, equations) -> dict:
    """The result's checks `"<state> collinearity"`, one per drift equation with a group
    of nearly collinear columns in which some term has PIP above `PIP_MIN`.

    **Arguments:**

    - `statistics`: the drift `sampler.SuffStats` batched over the
      `q` regressed equations (`gram (q, K, K)`), as the sampler saw them.
    - `equations`: the `q` drift `posterior.EquationPosterior`, same order.

    **Returns:** `{label: {"ok": False, "groups": [[name, ...], ...], "cosines": [float, ...],
    "warnings": [str, ...]}}`; empty when no equation has such a group.
    """
    gram = np.asarray(statistics.gram)
    out = {}
    for g, e in zip(gram, equations):
        pip = e.pip
        found = [(idx, c) for idx, c in collinear_groups(g) if pip[idx].max() > PIP_MIN]
        if not found:
            continue
        names = [[e.names[k] for k in idx] for idx, _ in found]
        out[f"{e.state} collinearity"] = {
            "ok": False,
            "groups": names,
            "cosines": [round(c, 8) for _, c in found],
            "warnings": [
                f"terms {', '.join(n)} are nearly the same column on these data (cosine {c:.10g}): the data "
                "cannot tell them apart; the twin uses their joint posterior"
                for n, (_, c) in zip(names, found)
            ],
        }
    return out


def group_coefficients(equation, groups, coefficients) -> np.ndarray:
    """An equation's twin coefficients with each group as one term.

    A group enters the twin when the posterior probability that any of its terms is
    included exceeds the equation's PIP threshold; its terms then take their posterior means
    given that (zeros where a term is excluded), so that the twin's combined effect is the
    mean of the group's sum, not the sum of each term's mean given its own inclusion. A
    group that enters less often is zero, as a term below the threshold is.

    **Arguments:**

    - `equation`: the `posterior.EquationPosterior`.
    - `groups`: lists of term names (a collinearity check's `"groups"`).
    - `coefficients`: the equation's twin coefficients, shape `(K,)`.

    **Returns:** the coefficients with the groups' entries replaced, shape `(K,)`, float64.
    """
    coef = np.array(coefficients, dtype=np.float64)
    index = {n: k for k, n in enumerate(equation.names)}
    theta = equation.theta.reshape(-1, len(equation.names))
    gamma = equation.gamma.reshape(-1, len(equation.names))
    for group in groups:
        idx = [index[n] for n in group if n in index]
        if len(idx) != len(group):
            raise DataError(f"collinearity group {group} names terms not in equation {equation.state}'s library")
        anyin = gamma[:, idx].any(axis=1)
        coef[idx] = theta[anyin][:, idx].mean(axis=0) if anyin.mean() > equation.pip_threshold else 0.0
    return coef


def twin_coefficients(equations, checks) -> np.ndarray:
    """The twin's coefficients of drift `equations`, each collinearity group entering once.

    Each equation's coefficients are the posterior means of its selected terms; an equation
    with a collinearity group in `checks` has the group as one term (`group_coefficients`).

    **Arguments:**

    - `equations`: the `q` drift `posterior.EquationPosterior`, each over the same `K` terms.
    - `checks`: the result's checks, keyed by label; only the `"<state> collinearity"`
      entries (`collinearity_checks`) are used.

    **Returns:** the coefficients, shape `(q, K)`, one row per equation.
    """
    def one(e):
        check = checks.get(f"{e.state} collinearity")
        return e.coefficients if check is None else group_coefficients(e, check["groups"], e.coefficients)

    return np.stack([one(e) for e in equations])
