"""The updated twin as a simulator, and its posterior predictive (paper Section 5.6).

:class:`UpdatedTwin` is the nominal model plus the discovered drift terms (and, for an
output-only twin, the discovered diffusion): an equinox module, so its coefficient arrays
may carry a leading axis of posterior draws and the twin vmaps over them.
:func:`posterior_twins` stacks draws of an update's posterior; :func:`predict` simulates
them (an ODE under a given input, or an SDE under Brownian forcing, both with diffrax
through :mod:`dtwin_jax.systems`) and returns the mean and the 2.5% and 97.5% quantiles of
every state.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax import systems
from dtwin_jax.errors import DataError
from dtwin_jax.library import Library, parse_library
from dtwin_jax.resources import check_posterior_draws, check_prediction
from dtwin_jax.systems import LinearSecondOrder

__all__ = ["UpdatedTwin", "posterior_twins", "predict", "simulation_error", "with_model_error", "effective_stiffness",
           "degradation_forecast"]


class UpdatedTwin(eqx.Module):
    """Nominal model plus discovered terms: `dx/dt = f(x, u) + S Theta L(x, u)`, and for an
    output-only twin `dx = ... dt + G(x) dB` with the discovered diffusion.

    `coefficients (q, K)` of `library` for the states `regressed` (indices into the state);
    `diffusion_coefficients (d, Kd)` of `diffusion_library` give `Gamma_vv(x)` (velocity^2/s)
    of every velocity, or are None for an input-output twin. Arrays may carry a leading
    batch axis (posterior draws): vmap over it with `eqx.filter_vmap`. `interpolation`:
    how the input behaves between samples (:func:`systems.check_interpolation`), as in the
    data the twin was updated from.
    """

    nominal: LinearSecondOrder
    library: Library = eqx.field(static=True)
    regressed: tuple[int, ...] = eqx.field(static=True)
    coefficients: jax.Array
    diffusion_library: Library | None = eqx.field(static=True, default=None)
    diffusion_coefficients: jax.Array | None = None
    interpolation: str = eqx.field(static=True, default="held")

    def perturbation(self, x, u):
        """Discovered extra rate `(m,)` at one sample `x (m,)`, `u (n,)`."""
        h = jnp.asarray(self.coefficients) @ self.library.eval_single(x, u)
        return jnp.zeros(self.nominal.m, h.dtype).at[jnp.asarray(self.regressed)].set(h)

    def rate(self, x, u):
        """Updated state rate `(m,)` at one sample `x (m,)`, `u (n,)`."""
        return self.nominal.rate(x, u) + self.perturbation(x, u)

    @property
    def stochastic(self) -> bool:
        return self.diffusion_coefficients is not None

    @property
    def additive_noise(self) -> bool:
        """True when the diffusion has no state-dependent term (ShARK applies)."""
        return self.diffusion_library is None or set(self.diffusion_library.names) <= {"1"}

    def diffusion_variance(self, x):
        """Discovered `Gamma_vv(x) (d,)` of every velocity at `x (m,)`, floored at zero."""
        gamma = jnp.asarray(self.diffusion_coefficients) @ self.diffusion_library.eval_single(x)
        return jnp.maximum(gamma, 0.0)

    def diffusion(self, x):
        """`G(x) (m, n)` of the SDE: the nominal force path `M^-1 B` with each velocity row
        rescaled so that `(G G^T)_vv = Gamma_vv(x)`.

        The unknown force keeps the nominal model's input structure (so one Brownian path
        drives the truth and the twin alike); a velocity the nominal `B` does not force
        gets no noise.
        """
        G = systems.diffusion_matrix(self.nominal)
        vel = jnp.asarray(self.nominal.velocity_index)
        nominal_var = jnp.sum(G[vel] ** 2, axis=1)
        scale = jnp.where(nominal_var > 0, jnp.sqrt(self.diffusion_variance(x) / jnp.where(nominal_var > 0, nominal_var, 1.0)), 0.0)
        return G * jnp.ones(G.shape[0], G.dtype).at[vel].set(scale)[:, None]


def _draw_index(result, num_draws: int, key) -> tuple[np.ndarray, np.ndarray]:
    chains, draws = result.equations[0].theta.shape[:2]
    flat = jax.random.choice(key, chains * draws, (num_draws,), replace=num_draws > chains * draws)
    flat = np.asarray(flat)
    return flat // draws, flat % draws


def posterior_twins(result, num_draws: int = 100, key=None) -> UpdatedTwin:
    """`num_draws` joint posterior draws of an update's twin, stacked on a leading axis.

    Every draw takes all equations' coefficients from one (chain, draw) of the Gibbs run:
    the twin's parameter uncertainty, inclusion included (an excluded term is zero). A
    refined update (:func:`dtwin_jax.update.refine_output_error`) draws the selected terms'
    coefficients from their refined Gaussian posterior instead (the others are zero).
    """
    if num_draws < 1:
        raise DataError(f"num_draws must be positive, got {num_draws}")
    check_posterior_draws(num_draws, sum(e.theta.shape[-1] for e in result.equations))
    key = jax.random.key(0) if key is None else key
    c, k = _draw_index(result, num_draws, key)
    drift = [e for e in result.equations if e.kind == "drift"]
    diffusion = [e for e in result.equations if e.kind == "diffusion"]
    names = result.nominal.state_names
    twin = result.twin
    if result.refinement is not None:
        ref = result.refinement
        mean, cov = np.asarray(ref["mean"]), np.asarray(ref["cov"]).reshape(len(ref["mean"]), -1)
        draws = np.asarray(jax.random.multivariate_normal(jax.random.fold_in(key, 1), mean, cov, (num_draws,),
                                                          method="svd"))
        coef = refined_coefficients((num_draws, *twin.coefficients.shape), ref["index"], draws)
    else:
        coef = np.stack([e.theta[c, k] for e in drift], axis=1)  # (S, q, K)
    if not diffusion:
        return eqx.tree_at(lambda t: t.coefficients, twin, jnp.asarray(coef))
    dcoef = np.stack([e.theta[c, k] for e in diffusion], axis=1)  # (S, d, Kd)
    assert [e.state for e in diffusion] == [names[v] for v in result.nominal.velocity_index]
    return UpdatedTwin(twin.nominal, twin.library, twin.regressed, jnp.asarray(coef), *diffusion_terms(result, dcoef),
                       twin.interpolation)


def refined_coefficients(shape, index, values) -> np.ndarray:
    """Coefficients of `shape (..., q, K)`: the flat entries `index (P,)` of each `(q, K)`
    block are `values (..., P)`, all others zero (an output-error refinement's terms)."""
    flat = np.zeros(tuple(shape[:-2]) + (shape[-2] * shape[-1],))
    flat[..., np.asarray(index, int)] = values
    return flat.reshape(shape)


def diffusion_terms(result, dcoef) -> tuple[Library, jax.Array]:
    """An output-only update's diffusion library, kept to the terms that some row of
    `dcoef (..., d, Kd)` uses (a constant-only diffusion stays additive noise, for ShARK),
    and those coefficients."""
    dcoef = np.asarray(dcoef)
    used = np.any(dcoef != 0, axis=tuple(range(dcoef.ndim - 1)))
    dlib = parse_library(result.preprocessing["diffusion_library"], result.nominal.m, 0).subset(used)
    return dlib, jnp.asarray(dcoef[..., used])


def _one(twins: UpdatedTwin, coef, dcoef) -> UpdatedTwin:
    """The twin of one draw: `twins` with its batched coefficient arrays replaced."""
    if dcoef is None:
        return eqx.tree_at(lambda t: t.coefficients, twins, coef)
    return eqx.tree_at(lambda t: (t.coefficients, t.diffusion_coefficients), twins, (coef, dcoef))


@eqx.filter_jit
def _paths(twins: UpdatedTwin, x0, t, u, keys):
    if twins.stochastic:
        run = lambda c, dc, k: systems.simulate_sde(_one(twins, c, dc), x0, t, k)
        return jax.vmap(run)(twins.coefficients, twins.diffusion_coefficients, keys)
    run = lambda c, uu: systems.simulate(
        _one(twins, c, None), x0, t, uu, rtol=1e-8, atol=1e-10, interpolation=twins.interpolation
    )[0]
    return jax.vmap(run, (0, 0 if u.ndim == 3 else None))(twins.coefficients, u)


def predict(twins: UpdatedTwin, x0, t, u=None, *, key=None, shared_path: bool = False) -> dict:
    """Posterior-predictive simulation of stacked twins (:func:`posterior_twins`).

    `x0 (m,)`, `t (N,)` s; `u (N, n)` the input of an input-output twin (held over each
    step or interpolated linearly, as `twins.interpolation`), or `(S, N, n)` one input per draw (future loads that are themselves uncertain). An output-only twin is driven by Brownian forcing: an independent path per draw
    from `key` (the band holds the process noise too), or with `shared_path` one path for
    all (the band holds the parameter uncertainty only; the truth driven by
    `systems.simulate_sde(..., key)` sees the same path). Returns `t`, `mean`, `lower`,
    `upper` (2.5% and 97.5% quantiles) `(N, m)`, and the `paths (S, N, m)`.
    """
    S = jnp.shape(twins.coefficients)[0]
    check_prediction(S, np.shape(t)[0], twins.nominal.m, option="draws")
    t = jnp.asarray(t, dtype=float)
    x0 = jnp.asarray(x0, dtype=float)
    if twins.stochastic:
        key = jax.random.key(0) if key is None else key
        keys = jnp.stack([key] * S) if shared_path else jax.random.split(key, S)
        paths = _paths(twins, x0, t, None, keys)
    else:
        if u is None:
            raise DataError("an input-output twin needs the input u (N, n) to predict")
        u = jnp.asarray(u, dtype=float)
        u = u.reshape((S, t.shape[0], -1) if u.ndim == 3 else (t.shape[0], -1))
        paths = _paths(twins, x0, t, u, None)
    lower, upper = jnp.quantile(paths, jnp.array([0.025, 0.975]), axis=0)
    return {"t": t, "mean": paths.mean(axis=0), "lower": lower, "upper": upper, "paths": paths}


def simulation_error(predicted, measured) -> dict:
    """Free-run simulation errors of `predicted (N, m)` against `measured (N, m)` per state:
    RMS error (the signal's units) and normalised RMS error (RMS error / std of measured)."""
    predicted, measured = np.asarray(predicted), np.asarray(measured)
    rms = np.sqrt(np.mean((predicted - measured) ** 2, axis=0))
    return {"rmse": rms, "nrmse": rms / np.std(measured, axis=0)}


def with_model_error(prediction: dict, model_sd) -> dict:
    """`prediction` (from :func:`predict`) with its 95% band widened by a Gaussian model
    error of std `model_sd` (`(m,)` or scalar, the states' units), which a posterior over
    the library's coefficients does not carry: the half-widths add in quadrature,
    `sqrt(((upper - lower) / 2)^2 + (1.96 model_sd)^2)` around the mean.

    `model_sd` is typically the twin's free-run error on its own training data
    (:func:`simulation_error`'s `rmse`, after the start transient): on the Silverbox
    0.35 mV, and the band then covers 95.4% of the arrow within the training amplitude
    where the parameter band alone covers 15%."""
    mean, lower, upper = (jnp.asarray(prediction[k]) for k in ("mean", "lower", "upper"))
    half = jnp.sqrt(((upper - lower) / 2) ** 2 + (1.96 * jnp.asarray(model_sd)) ** 2)
    return {**prediction, "lower": mean - half, "upper": mean + half}


def effective_stiffness(twins: UpdatedTwin, x) -> jax.Array:
    """`K_eff (S, d, d)`: the linear stiffness of each twin draw at state `x (m,)` or
    `(S, m)`, `-M d(acceleration)/d(displacement)` (force per displacement); equals the
    nominal `K` where the perturbation adds no stiffness."""
    nominal = twins.nominal
    d = nominal.d
    x = jnp.broadcast_to(jnp.asarray(x, dtype=float), (jnp.shape(twins.coefficients)[0], nominal.m))
    u = jnp.zeros(nominal.n)

    def one(c, dc, xx):
        twin = _one(twins, c, dc if twins.stochastic else None)
        jac = jax.jacfwd(lambda z: twin.rate(z, u))(xx)
        return -nominal.M @ jac[d : 2 * d, :d]

    return jax.vmap(one)(twins.coefficients, _diffusion_or_zeros(twins), x)


def _diffusion_or_zeros(twins):
    S = jnp.shape(twins.coefficients)[0]
    return twins.diffusion_coefficients if twins.stochastic else jnp.zeros((S, 0))


def degradation_forecast(twins: UpdatedTwin, prediction: dict, damage: int, critical: float,
                         *, every: int = 10) -> dict:
    """Damage, stiffness loss and failure probability over a long prediction.

    `prediction` from :func:`predict` (its `paths (S, N, m)` from the stacked `twins`);
    `damage` the index of the damage state, `critical` its failure level. Returns `t`;
    `damage_mean`, `damage_lower`, `damage_upper` `(N,)` (2.5% and 97.5% over draws);
    `probability (N,)`, the fraction of draws whose damage has passed `critical` by each
    time, with a 95% Jeffreys interval for its Monte Carlo error (`probability_lower`,
    `_upper`); and every `every`-th sample's relative stiffness loss `1 - K_eff / K`
    (diagonal, `(N', d)`, `loss_t`) at zero displacement and velocity, mean and band.
    """
    from scipy.stats import beta

    paths = np.asarray(prediction["paths"])
    S = paths.shape[0]
    dmg = paths[:, :, damage]
    passed = np.maximum.accumulate(dmg, axis=1) > critical
    k = passed.sum(axis=0)
    lower = np.where(k > 0, beta.ppf(0.025, k + 0.5, S - k + 0.5), 0.0)
    upper = np.where(k < S, beta.ppf(0.975, k + 0.5, S - k + 0.5), 1.0)
    # Stiffness along each draw's own damage path (the other states at zero).
    nominal = twins.nominal
    idx = np.arange(0, paths.shape[1], every)
    states = np.zeros((idx.size, S, nominal.m))
    states[:, :, damage] = dmg[:, idx].T
    K0 = np.diagonal(np.asarray(nominal.K))
    stiff = jax.lax.map(lambda xs: effective_stiffness(twins, xs), jnp.asarray(states))  # (N', S, d, d)
    loss = 1.0 - np.diagonal(np.asarray(stiff), axis1=-2, axis2=-1) / K0  # (N', S, d)
    q = lambda a, p: np.quantile(a, p, axis=0)
    return {
        "t": np.asarray(prediction["t"]),
        "critical": float(critical),
        "damage_mean": dmg.mean(axis=0), "damage_lower": q(dmg, 0.025), "damage_upper": q(dmg, 0.975),
        "probability": k / S, "probability_lower": lower, "probability_upper": upper,
        "loss_t": np.asarray(prediction["t"])[idx],
        "loss_mean": loss.mean(axis=1), "loss_lower": np.quantile(loss, 0.025, axis=1),
        "loss_upper": np.quantile(loss, 0.975, axis=1),
    }
