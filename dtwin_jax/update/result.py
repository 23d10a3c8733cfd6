"""What an update returns: the sampler's settings and the `UpdateResult`, which holds
every regressed equation's posterior, the updated twin at their means, the run's
diagnostics and warnings, the statistics a re-update adds to, and the update history; it
serializes to the result file of formats.md and to arviz."""

from __future__ import annotations

from dataclasses import dataclass, field

import jax.numpy as jnp
import numpy as np

from dtwin_jax.collinearity import twin_coefficients
from dtwin_jax.library import Library
from dtwin_jax.models.prediction import (
    UpdatedTwin,
    diffusion_terms,
    refined_coefficients,
)
from dtwin_jax.models.systems import LinearSecondOrder
from dtwin_jax.posterior import EquationPosterior, format_coefficient
from dtwin_jax.sampler import SamplerSettings

__all__ = ["SamplerSettings", "UpdateResult"]


@dataclass
class UpdateResult:
    """Posteriors of every regressed equation, the updated twin and run diagnostics."""

    mode: str
    nominal: LinearSecondOrder
    library: Library
    equations: list[EquationPosterior]
    pip_threshold: float
    settings: SamplerSettings
    seconds: float
    preprocessing: dict = field(default_factory=dict)
    # Residual checks (dtwin_jax.checks.residual_checks) keyed by equation label; output-only
    # also "<state> noise correction" (the corrected Gram's definiteness, `correction_margin`).
    checks: dict = field(default_factory=dict)
    # The sufficient statistics the sampler saw, by kind ("drift", "diffusion"), batched over
    # equations, physical units: a re-update adds new data's to them (posterior as prior).
    statistics: dict = field(default_factory=dict)
    # One entry per update of this twin, oldest first (time, data size, prior, equations).
    history: list = field(default_factory=list)
    # The output-error refinement of the selected drift coefficients (update.output_error):
    # their Laplace posterior ("index" into the (q, K) coefficients, "mean", "cov"), or None.
    refinement: dict | None = None

    @property
    def state_names(self) -> tuple[str, ...]:
        """The nominal model's `m` state names."""
        return self.nominal.state_names

    @property
    def input_names(self) -> tuple[str, ...]:
        """The input names, empty when the library has no input terms (output-only)."""
        return self.nominal.input_names if self.library.uses_inputs else ()

    @property
    def twin(self) -> UpdatedTwin:
        """The updated model at the posterior means of the selected terms (with the
        discovered diffusion for an output-only update); the terms of a reported collinearity
        group enter as one (`dtwin_jax.collinearity.group_coefficients`).
        `dtwin_jax.models.prediction.posterior_twins` gives posterior draws of it."""
        drift = [e for e in self.equations if e.kind == "drift"]
        index = tuple(self.state_names.index(e.state) for e in drift)
        coef = twin_coefficients(drift, self.checks) if drift else np.zeros((0, self.library.K))
        if self.refinement is not None:
            coef = refined_coefficients(coef.shape, self.refinement["index"], self.refinement["mean"])
        diffusion = [e for e in self.equations if e.kind == "diffusion"]
        interpolation = self.preprocessing.get("input_interpolation", "held")
        # The measured states' range bounds a prediction (absent from twins saved before it).
        state_range = self.preprocessing.get("state_range")
        state_range = None if state_range is None else jnp.asarray(state_range, dtype=float)
        sd = self.preprocessing.get("model_error_sd")
        sd = None if sd is None else tuple(float(v) for v in sd)
        if not diffusion:
            return UpdatedTwin(self.nominal, self.library, index, jnp.asarray(coef), interpolation=interpolation,
                               state_range=state_range, model_error_sd=sd)
        dcoef = np.stack([e.coefficients for e in diffusion])
        return UpdatedTwin(self.nominal, self.library, index, jnp.asarray(coef), *diffusion_terms(self, dcoef),
                           state_range=state_range)

    def diagnostics(self) -> dict:
        """Convergence over all equations and the run's settings.

        **Returns:** the `diagnostics` dict of the result file: `chains`, `draws`, `burn_in`;
        the worst R-hat of the coefficients (`rhat_max`) and of the inclusion indicators
        (`rhat_gamma_max`), 4 decimals; the smallest bulk ESS (`ess_bulk_min`), a whole
        number; the largest PIP disagreement between chains, overall and per equation
        (`pip_chain_spread_max`, `pip_chain_spread`), 4 decimals; `seconds` of wall time,
        3 decimals. None where nothing is selected."""
        rhat = np.concatenate([e.rhat() for e in self.equations] + [np.zeros(0)])
        ess = np.concatenate([e.ess_bulk() for e in self.equations] + [np.zeros(0)])
        rhat_g = np.concatenate([e.rhat_gamma() for e in self.equations] + [np.zeros(0)])
        rhat, ess = rhat[np.isfinite(rhat)], ess[np.isfinite(ess)]
        # inf (chains never overlap) must not vanish; clipped so that the JSON stays valid.
        rhat_g = np.minimum(rhat_g[~np.isnan(rhat_g)], 1e6)
        # Rounded to what the estimates resolve (an R-hat's 4th decimal, a whole draw).
        spread = {self._label(e): round(e.pip_chain_spread_max, 4) for e in self.equations}
        return {
            "chains": self.settings.num_chains,
            "draws": self.settings.num_draws,
            "burn_in": self.settings.num_burnin,
            "rhat_max": round(float(rhat.max()), 4) if rhat.size else None,
            "rhat_gamma_max": round(float(rhat_g.max()), 4) if rhat_g.size else None,
            "ess_bulk_min": float(round(ess.min())) if ess.size else None,
            "pip_chain_spread_max": max(spread.values(), default=0.0),
            "pip_chain_spread": spread,
            "seconds": round(self.seconds, 3),
        }

    @staticmethod
    def _label(e: EquationPosterior) -> str:
        return e.state if e.kind == "drift" else f"{e.state} [diffusion]"

    def warnings(self) -> list[str]:
        """One line per sign of an unreliable result: failed residual checks, chains that
        disagree on a PIP by more than 0.2, R-hat above 1.01."""
        out = [f"{label}: {w}" for label, c in self.checks.items() for w in c.get("warnings", [])]
        for e in self.equations:
            pips = e.pip_per_chain
            for k in np.flatnonzero(e.pip_chain_spread > 0.2):
                out.append(
                    f"chains disagree on PIP of {e.names[k]} in {self._label(e)} "
                    f"({pips[:, k].min():.2f}..{pips[:, k].max():.2f}): multimodal posterior, run longer"
                )
        diag = self.diagnostics()
        for key in ("rhat_max", "rhat_gamma_max"):
            if diag[key] is not None and diag[key] > 1.01:
                what = "coefficients" if key == "rhat_max" else "inclusion indicators"
                out.append(f"R-hat of the {what} {diag[key]:.3g} > 1.01: chains have not converged, run longer")
        return out

    def to_json(self) -> dict:
        """The result file of formats.md."""
        return {
            "mode": self.mode,
            "state_names": list(self.state_names),
            "input_names": list(self.input_names),
            "pip_threshold": self.pip_threshold,
            "library": self.library.spec,
            "equations": [e.to_json() for e in self.equations],
            "diagnostics": self.diagnostics(),
            "preprocessing": self.preprocessing,
            "checks": self.checks,
            "history": self.history,
            **({"refinement": self.refinement_json()} if self.refinement is not None else {}),
        }

    def refinement_json(self) -> dict:
        """The refined coefficients as the result file gives them (mean, std per term)."""
        ref = self.refinement
        std = np.sqrt(np.diag(np.asarray(ref["cov"]).reshape(len(ref["mean"]), -1)))
        terms = [dict(term, mean=float(m), std=float(s)) for term, m, s in zip(ref["terms"], ref["mean"], std)]
        keep = ("method", "noise_std", "residual_scale", "hac_lags", "iterations", "samples")
        return {"terms": terms, **{k: ref[k] for k in keep}}

    def summary(self) -> str:
        """The discovered perturbation, one equation per line (and the refined coefficients)."""
        lines = [e.equation() for e in self.equations]
        if self.refinement is not None:
            refined = ", ".join(f"{t['state']} {t['expr']}: {format_coefficient(t['mean'], t['std'])}"
                                for t in self.refinement_json()["terms"])
            lines.append(f"output-error refinement: {refined}")
        return "\n".join(lines)

    def to_arviz(self):
        """All equations' draws in one arviz DataTree (variables `theta_<state>_<kind>` etc.)."""
        import arviz_base as az

        posterior, dims, coords = {}, {}, {}
        for e in self.equations:
            tag = f"{e.state}_{e.kind}"
            posterior[f"theta_{tag}"] = e.theta
            posterior[f"gamma_{tag}"] = e.gamma.astype(np.int8)
            posterior[f"sigma2_{tag}"] = e.sigma2
            dims[f"theta_{tag}"] = dims[f"gamma_{tag}"] = [f"term_{tag}"]
            coords[f"term_{tag}"] = list(e.names)
        return az.from_dict({"posterior": posterior}, dims=dims, coords=coords)
