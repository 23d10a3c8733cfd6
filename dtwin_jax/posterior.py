"""Posterior summaries of spike-and-slab draws: inclusion probabilities, coefficients,
diagnostics (via arviz) and equations."""

from __future__ import annotations

import math
from decimal import Decimal
from dataclasses import dataclass, field

import numpy as np

__all__ = ["EquationPosterior", "format_equation", "format_coefficient"]


def _arviz_stats():
    """arviz's statistics (without its plotting import), loaded on first use: a study or a
    kernel run that never asks for R-hat, ESS or an HDI does not pay for (or need) it."""
    import arviz_stats

    return arviz_stats


@dataclass(frozen=True)
class EquationPosterior:
    """Draws for one regressed equation, in physical units.

    `theta` is `(chains, draws, K)` with zeros where a term is excluded, `gamma` the
    matching inclusion indicators, `sigma2` `(chains, draws)` the residual variance.
    Coefficient statistics of a term are conditional on its inclusion (the coefficient of the
    discovered term); for a term with PIP near 1 they equal the marginal ones.
    """

    state: str
    kind: str  # "drift" or "diffusion"
    names: tuple[str, ...]
    gamma: np.ndarray
    theta: np.ndarray
    sigma2: np.ndarray
    pip_threshold: float = 0.5
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def pip(self) -> np.ndarray:
        """Posterior inclusion probability of every term, `(K,)`."""
        return self.gamma.mean(axis=(0, 1))

    @property
    def selected(self) -> np.ndarray:
        """Terms with PIP above the threshold, `(K,)` bool."""
        return self.pip > self.pip_threshold

    @property
    def pip_per_chain(self) -> np.ndarray:
        """Inclusion probability of every term within each chain, `(chains, K)`."""
        return self.gamma.mean(axis=1)

    @property
    def pip_chain_spread(self) -> np.ndarray:
        """`max_c pip_ck - min_c pip_ck` of every term, `(K,)`: chains that start apart and
        stay in different modes disagree here (0 with one chain)."""
        return np.ptp(self.pip_per_chain, axis=0)

    @property
    def pip_chain_spread_max(self) -> float:
        """The largest disagreement between chains on any term's PIP."""
        return float(self.pip_chain_spread.max()) if len(self.names) else 0.0

    def rhat_gamma(self) -> np.ndarray:
        """Rank-normalised split R-hat of the indicators of every term some chain selects
        (per-chain PIP above the threshold), `(n,)`; NaN where the indicator never changes.
        The order is that of `chain_selected`. Chains each constant at different values
        (one always includes the term, another never) give `inf`."""
        with np.errstate(divide="ignore", invalid="ignore"):
            rhat = _arviz_stats().rhat
            return np.array([_diag(rhat, self.gamma[..., k].astype(float)) for k in self.chain_selected()])

    def chain_selected(self) -> np.ndarray:
        """Indices of the terms selected by at least one chain."""
        return np.flatnonzero((self.pip_per_chain > self.pip_threshold).any(axis=0))

    def _conditional(self, k: int) -> np.ndarray:
        draws = self.theta[..., k].ravel()
        return draws[self.gamma[..., k].ravel()]

    @property
    def mean(self) -> np.ndarray:
        """Posterior mean of each coefficient given inclusion (0 for never-included terms)."""
        return np.array([_safe(np.mean, self._conditional(k)) for k in range(len(self.names))])

    @property
    def std(self) -> np.ndarray:
        return np.array([_safe(np.std, self._conditional(k)) for k in range(len(self.names))])

    @property
    def hdi_95(self) -> np.ndarray:
        """95% highest-density interval of each coefficient given inclusion, `(K, 2)`."""
        if "hdi" not in self._cache:
            out = np.full((len(self.names), 2), np.nan)
            for k in np.flatnonzero(self.gamma.any(axis=(0, 1))):
                draws = self._conditional(k)
                if draws.size > 2:
                    out[k] = np.asarray(_arviz_stats().hdi(draws, prob=0.95))
            self._cache["hdi"] = out
        return self._cache["hdi"]

    @property
    def coefficients(self) -> np.ndarray:
        """Point estimate of the discovered perturbation: mean of selected terms, 0 elsewhere."""
        return np.where(self.selected, self.mean, 0.0)

    def rhat(self) -> np.ndarray:
        """Rank-normalised split R-hat of each selected coefficient (arviz), `(n_selected,)`."""
        rhat = _arviz_stats().rhat
        return np.array([_diag(rhat, self.theta[..., k]) for k in np.flatnonzero(self.selected)])

    def ess_bulk(self) -> np.ndarray:
        ess = _arviz_stats().ess
        return np.array([_diag(ess, self.theta[..., k]) for k in np.flatnonzero(self.selected)])

    def terms(self) -> list[dict]:
        """Selected terms as formats.md writes them."""
        pip, mean, std, hdi = self.pip, self.mean, self.std, self.hdi_95
        return [
            {
                "expr": self.names[k],
                "mean": float(mean[k]),
                "std": float(std[k]),
                "pip": float(pip[k]),
                "hdi_95": [float(hdi[k, 0]), float(hdi[k, 1])],
            }
            for k in np.flatnonzero(self.selected)
        ]

    def to_json(self) -> dict:
        return {
            "state": self.state,
            "kind": self.kind,
            "terms": self.terms(),
            "pip": {name: float(p) for name, p in zip(self.names, self.pip)},
        }

    def equation(self) -> str:
        """`x2: -100.0e3(±0.6e3) x1**3 + ...` (see `format_coefficient`)."""
        return format_equation(self.state, self.terms(), self.kind)

    def to_arviz(self):
        """The draws as an arviz DataTree (`theta` and `gamma` over `term`, `sigma2`)."""
        import arviz_base

        return arviz_base.from_dict(
            {
                "posterior": {
                    "theta": self.theta,
                    "gamma": self.gamma.astype(np.int8),
                    "sigma2": self.sigma2,
                }
            },
            dims={"theta": ["term"], "gamma": ["term"]},
            coords={"term": list(self.names)},
        )


def _safe(fn, draws):
    return float(fn(draws)) if draws.size else 0.0


def _diag(fn, draws):
    """An arviz diagnostic on `(chains, draws)`; NaN where it is undefined (constant draws)."""
    if np.ptp(draws) == 0.0:
        return float("nan")
    return float(fn(np.asarray(draws)))


def format_coefficient(mean: float, std: float) -> str:
    """A coefficient and its posterior std in engineering notation.

    The mean to 4 significant digits as `mantissa` + `e<exponent>`, the exponent a multiple
    of 3 (none when it is 0) and the mantissa in [1, 1000); the std in the same exponent with
    the same number of decimals. A zero mean takes the std's exponent.

    **Arguments:**

    - `mean`: the coefficient.
    - `std`: its posterior standard deviation; left out of the text when it is zero,
      negative or not finite.

    **Returns:** the text, e.g. `-99.82e3(±0.51e3)`, `2.000(±0.007)`, `-123.5e-15(±5.0e-15)`;
    `"0"` for a zero mean without a std, and `nan`, `inf` or `-inf` for a non-finite mean.
    """
    mean, std = float(mean), float(std)
    if not math.isfinite(mean):
        return str(mean)
    show_std = math.isfinite(std) and std > 0
    scale = abs(mean) if mean != 0 else (std if show_std else 0.0)
    if scale == 0:
        return "0"
    # The exponent of the value rounded to 4 digits (999.96 -> 1.000e3, not 999.96).
    digits = int(f"{scale:.3e}".split("e")[1])
    eng = 3 * (digits // 3)
    decimals = 3 - (digits - eng)
    suffix = f"e{eng}" if eng else ""
    # Decimal shifts the exponent exactly, also where 10.0**-eng would overflow (denormals).
    text = f"{Decimal(mean).scaleb(-eng):.{decimals}f}{suffix}"
    if text.startswith("-") and float(text[1:].split("e")[0]) == 0:
        text = text[1:]  # no "-0.000"
    if show_std:
        text += f"(±{Decimal(std).scaleb(-eng):.{decimals}f}{suffix})"
    return text


def format_equation(state: str, terms: list[dict], kind: str = "drift") -> str:
    """One discovered equation as a line of text, e.g. `x2: -100.0e3(±0.6e3) x1**3 + 2.000(±0.007) x2`.

    Each coefficient is written by `format_coefficient`; a constant term (`"1"`) shows its
    coefficient alone.

    **Arguments:**

    - `state`: the equation's state, e.g. `"x2"`.
    - `terms`: the selected terms as `EquationPosterior.terms` gives them (dicts with
      `"expr"`, `"mean"` and `"std"`), in order.
    - `kind`: `"drift"` (default) or `"diffusion"` (labelled `x2 [diffusion]`).

    **Returns:** the line, `"<label>: 0"` when no term is selected.
    """
    label = f"{state}" if kind == "drift" else f"{state} [diffusion]"
    if not terms:
        return f"{label}: 0"
    parts = []
    for i, t in enumerate(terms):
        coef = format_coefficient(t["mean"], t["std"])
        if i and not coef.startswith("-"):
            coef = "+ " + coef
        elif i:
            coef = "- " + coef[1:]
        expr = "" if t["expr"] == "1" else f" {t['expr']}"
        parts.append(f"{coef}{expr}")
    return f"{label}: " + " ".join(parts)
