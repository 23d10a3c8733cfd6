"""Output-error refinement of an input-output twin (after selection, before prediction).

The Gibbs posterior is an equation-error fit: rates regressed on denoised states, one sample
at a time. A lightly damped twin's free run depends on its stiffness far more finely than a
short window's equation error pins it down (example 3: a late-damage stiffness a fraction of a
percent off puts a long prediction visibly off). The free run itself carries that
information, as the phase it accumulates: here the selected terms' coefficients and the
records' initial states are fitted so that the simulated twin matches the measured states
(weighted least squares, Levenberg-Marquardt on the forward-mode Jacobian of the diffrax
simulation), and the Laplace approximation at the optimum, with a covariance robust to
coloured residuals (a Newey-West sandwich), is the refined posterior.

It is conditional on the selected terms (the PIPs stay those of the Gibbs run), and it
assumes the twin is deterministic given the input, as in framework 1.
"""

from __future__ import annotations

import dataclasses

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax.data import check_records
from dtwin_jax.errors import DataError
from dtwin_jax.models.prediction import fixed_substeps, is_nonsmooth
from dtwin_jax.models.systems import simulate
from dtwin_jax.preprocess.estimate import measured_index

__all__ = ["refine_output_error"]


def refine_output_error(result, t, x, u, *, x_names=None, x0=None, noise_std=None, input_noise_std=None,
                        max_iter: int = 30, reweight: int = 2, input_draws: int = 64):
    """The update `result` with its selected coefficients refined by output error.

    The selected terms' coefficients and the records' initial states are fitted so that the
    twin's free run matches the measured states (see the module docstring); the selection
    itself is kept.

    **Arguments:**

    - `result`: an `UpdateResult` of mode `"input-output"` with at least one discovered term.
    - `t`: `(N,)` sample times, s: the data the twin was updated from, or any other window.
    - `x`: `(N, p)` or `(R, N, p)` the measured states `x_names`.
    - `u`: `(N, n)` or `(R, N, n)` the measured inputs.
    - `x_names`: the states of the columns of `x`, or None (default: all `m` in order).
    - `x0`: `(R, m)` starting guesses of the records' initial states, or None (default: the
      first sample, which needs every state measured).
    - `noise_std`: `(p,)` the measurement noise std of each state (the states' units), which
      weighs them, or None (default: from the residuals, re-estimated `reweight` times).
    - `input_noise_std`: `(n,)` the measured inputs' noise std (the update's
      `preprocessing["input_noise_std"]`), whose response through the twin widens the
      covariance, or None (no widening).
    - `max_iter`: the most Levenberg-Marquardt iterations per fit.
    - `reweight`: how many times the noise std is re-estimated from the residuals and the fit
      repeated, when `noise_std` is None.
    - `input_draws`: Monte Carlo draws of the input noise for its response.

    **Returns:** a copy of `result` whose `refinement` dict holds the refined posterior (the
    terms, their mean and covariance, the fitted initial states, the noise std; used by
    `dtwin_jax.models.prediction.posterior_twins` and `result.twin`). Raises a `DataError` for a
    twin that is not input-output or has no terms, for a missing `x0` when only some states
    are measured, and when the free run fails at the posterior mean."""
    if result.mode != "input-output":
        raise DataError("output-error refinement needs an input-output twin (its input is known)")
    nominal = result.nominal
    x_index = measured_index(x_names, nominal)
    rec = check_records(t, x, u, None, nominal, x_columns=len(x_index))
    R, N, p = rec.x.shape
    if x0 is None:
        if len(x_index) != nominal.m:
            raise DataError("output-error refinement from some states needs starting guesses x0 of all states")
        x0 = rec.x[:, 0]
    x0 = np.broadcast_to(np.asarray(x0, np.float64), (R, nominal.m))
    twin = result.twin
    base = np.asarray(twin.coefficients)
    index = np.flatnonzero(base.ravel())
    if index.size == 0:
        raise DataError("the twin has no discovered terms to refine")
    params = jnp.concatenate([jnp.asarray(base.ravel()[index]), jnp.asarray(x0).ravel()])
    xm = jnp.asarray(rec.x)
    residual, jacobian, input_response = _residual_functions(
        twin, index, rec.t, jnp.asarray(rec.u), xm, jnp.asarray(x_index), R)
    if not np.isfinite(_cost(residual, params, jnp.ones(p))):
        raise DataError("output-error refinement: the twin's free run over the data fails (too stiff, or "
                        "unstable) at the posterior mean")
    scale = np.std(rec.x, axis=(0, 1)) if noise_std is None else np.asarray(noise_std, np.float64)
    iterations = 0
    for _ in range(1 + reweight * (noise_std is None)):
        params, its = _levenberg_marquardt(residual, jacobian, params, jnp.asarray(scale), max_iter)
        iterations += its
        if noise_std is None:
            scale = np.sqrt(np.mean(np.asarray(residual(params, jnp.ones(p))).reshape(R, N, p) ** 2, axis=(0, 1)))
    w = jnp.asarray(scale)
    r = np.asarray(residual(params, w)).reshape(R, N, p)
    J = np.asarray(jacobian(params, w)).reshape(R, N, p, -1)
    lags = min(N // 4, _slowest_period_samples(nominal, float(rec.t[1] - rec.t[0]), N))
    cov = _sandwich_covariance(r, J, lags)
    if input_noise_std is not None:
        # The input's noise drives the free run: its response, coherent with the
        # parameters' sensitivities over a short record, by Monte Carlo through the twin.
        du = jnp.asarray(input_noise_std) * jax.random.normal(jax.random.key(0), (input_draws, *rec.u.shape))
        d = np.asarray(input_response(params, w, du))  # (S, R N p)
        cov = cov + _input_noise_covariance(J.reshape(d.shape[1], -1), d)
    s2 = float(np.sum(r**2)) / max(r.size - params.size, 1)
    P = index.size
    names = result.library.names
    states = [e.state for e in result.equations if e.kind == "drift"]
    refinement = {
        "method": "output-error",
        "terms": [{"state": states[i // len(names)], "expr": names[i % len(names)]} for i in index],
        "index": index.tolist(),
        "mean": np.asarray(params[:P]).tolist(),
        "cov": cov[:P, :P].tolist(),
        "x0": np.asarray(params[P:]).reshape(R, nominal.m).tolist(),
        "noise_std": scale.tolist(),
        "residual_scale": float(np.sqrt(s2)),
        "hac_lags": int(lags),
        "iterations": iterations,
        "samples": int(R * N),
    }
    return dataclasses.replace(result, refinement=refinement)


def _residual_functions(twin, index, t, u, xm, x_index, R):
    """Weighted residual `(R N p,)` of parameters `[theta (P,), x0 (R m,)]` and its
    Jacobian, and the weighted measured-state response `(S, R N p)` to `S` input
    perturbations `du (S, R, N, n)`; all jitted."""
    shape = np.asarray(twin.coefficients).shape
    P = index.size
    # A sign/Abs term chatters the adaptive solver (minutes, then out of steps): fixed steps.
    substeps = fixed_substeps(twin.nominal, t) if is_nonsmooth(twin) else None

    def free_run(params, u):
        coef = jnp.zeros(int(np.prod(shape)), params.dtype).at[index].set(params[:P]).reshape(shape)
        model = eqx.tree_at(lambda tw: tw.coefficients, twin, coef)
        x0 = params[P:].reshape(R, -1)
        run = lambda a, b: simulate(model, a, t, b, rtol=1e-8, atol=1e-10, adjoint=diffrax.ForwardMode(),
                                    substeps=substeps)[0]
        return jax.vmap(run)(x0, u)[..., x_index]

    def residual(params, scale):
        return ((xm - free_run(params, u)) / scale).ravel()

    def input_response(params, scale, du):
        base = free_run(params, u)
        return jax.lax.map(lambda d: ((free_run(params, u + d) - base) / scale).ravel(), du)

    return jax.jit(residual), jax.jit(jax.jacfwd(residual)), jax.jit(input_response)


def _cost(residual, params, scale) -> float:
    """`|residual|^2`, inf where the free run fails (a trial step can make the twin
    unstable or too stiff for the solver's step budget)."""
    try:
        r = residual(params, scale)
    except RuntimeError:  # XLA's, or equinox's out-of-steps error (EquinoxRuntimeError)
        return np.inf
    return float(r @ r)


def _levenberg_marquardt(residual, jacobian, params, scale, max_iter):
    """Minimise `|residual(params, scale)|^2` from `params`; returns (params, iterations)."""
    r = residual(params, scale)
    cost = float(r @ r)
    lam = 1e-3
    for it in range(1, max_iter + 1):
        J = jacobian(params, scale)
        g, H = J.T @ r, J.T @ J
        damping = jnp.diag(jnp.maximum(jnp.diag(H), 1e-300))
        while lam < 1e10:
            trial = params + jnp.linalg.solve(H + lam * damping, -g)
            c_trial = _cost(residual, trial, scale)
            if np.isfinite(c_trial) and c_trial < cost:
                break
            lam *= 4.0
        else:
            return params, it  # no step lowers the cost: at the optimum to rounding
        gain = cost - c_trial
        params, r, cost, lam = trial, residual(trial, scale), c_trial, max(lam / 3.0, 1e-12)
        if gain < 1e-10 * cost:
            return params, it
    return params, max_iter


def _slowest_period_samples(nominal, dt: float, N: int) -> int:
    """Samples in one period of the nominal model's slowest mode (N without stiffness)."""
    omega2 = np.real(np.linalg.eigvals(np.linalg.solve(np.asarray(nominal.M), np.asarray(nominal.K))))
    omega = np.sqrt(omega2[omega2 > 0])
    return int(np.ceil(2 * np.pi / (omega.min() * dt))) if omega.size else N


def _sandwich_covariance(r, J, lags: int) -> np.ndarray:
    """Laplace covariance robust to coloured residuals: `H^-1 S H^-1` with `H = J^T J`
    and `S` the Newey-West (Bartlett, `lags`) long-run covariance of the per-sample
    scores `J_t^T r_t`. Residuals `r (R, N, p)`, Jacobian `J (R, N, p, P)`.

    The output residual holds white sensor noise and, through the twin, the response to
    the input's noise: coloured, small in variance but coherent with the parameters'
    sensitivities, so `s2 (J^T J)^-1` made intervals several times too narrow on
    random members (`benchmarks/refine.py`)."""
    norm, Hinv = _normalised_inverse(J.reshape(-1, J.shape[-1]))
    scores = np.einsum("rnpk,rnp->rnk", J, r) / norm  # (R, N, P)
    meat = np.einsum("rnk,rnl->kl", scores, scores)
    for lag in range(1, lags + 1):
        gamma = np.einsum("rnk,rnl->kl", scores[:, lag:], scores[:, :-lag])
        meat += (1.0 - lag / (lags + 1.0)) * (gamma + gamma.T)
    return Hinv @ meat @ Hinv / np.outer(norm, norm)


def _input_noise_covariance(J, d) -> np.ndarray:
    """`H^-1 E[J^T d d^T J] H^-1`: the parameters' spread from input-noise responses
    `d (S, M)` of the weighted residual, `J (M, P)` its Jacobian."""
    norm, Hinv = _normalised_inverse(J)
    scores = d @ (J / norm)  # (S, P)
    return Hinv @ (scores.T @ scores / d.shape[0]) @ Hinv / np.outer(norm, norm)


def _normalised_inverse(J) -> tuple[np.ndarray, np.ndarray]:
    """Column norms of `J (M, P)` and the inverse of the column-normalised `J^T J`:
    coefficients and initial states differ in scale by many orders."""
    norm = np.linalg.norm(J, axis=0)
    norm = np.where(norm > 0, norm, 1.0)
    Jn = J / norm
    return norm, np.linalg.pinv(Jn.T @ Jn, rcond=1e-13)
