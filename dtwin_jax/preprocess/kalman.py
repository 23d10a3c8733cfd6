"""The one linear-Gaussian Kalman filter and Rauch-Tung-Striebel smoother of the package,
and the Newton fit of noise variances by their likelihood.

    s_{k+1} = F_k s_k + c_k + N(0, Q_k),      z_k = H s_k + e_k + N(0, diag(r)),

states `s (S,)`, measurements `z (p,)`. `F`, `c`, `Q` may be one array for every step or
one per step (a leading axis `N-1`); `e` one per sample. The measurement noise is
independent across channels (`r` diagonal), so the update takes one channel at a time:
scalar innovations, no matrix factorisation, several times faster batched on a CPU.
Users: the partial-state smoother (`dtwin_jax.preprocess.estimate`), the kinematic smoother
(`dtwin_jax.preprocess.denoise`) and the diffusion likelihood (`dtwin_jax.output_only.statespace`).
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax.scipy.linalg import cho_factor, cho_solve

__all__ = ["Filtered", "kalman_filter", "rts_smoother", "newton_log_variances"]


class Filtered(NamedTuple):
    """Filter output for `N` samples of `S` states."""

    mean: jax.Array  # (N, S) filtered means
    cov: jax.Array  # (N, S, S)
    pred_mean: jax.Array  # (N-1, S) one-step predictions of samples 1..N-1
    pred_cov: jax.Array  # (N-1, S, S)
    loglik: jax.Array  # () log p(z_0..z_{N-1}), or of z_1.. given z_0 (update_first=False)


def _steps(a, N: int, ndim: int):
    """`a` per step `(N-1, ...)`, broadcast when one array serves every step."""
    a = jnp.asarray(a)
    return jnp.broadcast_to(a, (N - 1,) + a.shape) if a.ndim == ndim else a


def _update(m, P, z, H, r):
    ll = 0.0
    for i in range(r.shape[0]):  # static: one scalar update per channel
        # H None: channel i measures state i; slicing skips products with a unit row.
        col = P[:, i] if H is None else P @ H[i]
        S = (col[i] if H is None else H[i] @ col) + r[i]
        res = z[i] - (m[i] if H is None else H[i] @ m)
        m = m + col * (res / S)
        P = P - jnp.outer(col, col) / S
        ll = ll - 0.5 * (res * res / S + jnp.log(S) + jnp.log(2 * jnp.pi))
    return m, 0.5 * (P + P.T), ll


def kalman_filter(F, c, Q, H, e, r, z, m0, P0, *, update_first: bool = True) -> Filtered:
    """Kalman-filter the measurements `z` of the model in the module docstring.

    Pure; jit, vmap and differentiate freely.

    **Arguments:**

    - `F`: the transition, `(S, S)` for every step or `(N-1, S, S)` one per step.
    - `c`: the transition's offset, `(S,)` or `(N-1, S)`.
    - `Q`: the process-noise covariance, like `F`; or a pair `(w (d,), Q_unit)` with `Q_unit`
      `(d, S, S)` or `(N-1, d, S, S)`, for `Q_k = sum_v w_v Q_unit[k, v]` (summed inside the
      loop, so differentiating in `w` does not materialize a per-step `Q`).
    - `H`: the measurement matrix, `(p, S)`, or `(N, p, S)` one per sample; None: `p = S`,
      the states measured directly.
    - `e`: known measurement offsets, `(N, p)`, or None for zero.
    - `r`: the measurement noise variances, `(p,)` (independent channels).
    - `z`: the measurements, `(N, p)`.
    - `m0`: the prior mean of `s_0`, `(S,)`.
    - `P0`: the prior covariance of `s_0`, `(S, S)`.
    - `update_first`: True (default): `z_0` updates the prior. False: `m0`, `P0` already
      condition on `z_0` (a filter started at the first measurement), which then enters
      neither the update nor the likelihood.

    **Returns:** `Filtered`: filtered means `(N, S)` and covariances `(N, S, S)`, one-step
    predictions `(N-1, S)`, `(N-1, S, S)` of samples 1..N-1, and the log-likelihood `()`."""
    z = jnp.asarray(z)
    N = z.shape[0]
    r = jnp.asarray(r)
    H = None if H is None else jnp.asarray(H)
    y = z if e is None else z - jnp.asarray(e)
    m0, P0 = jnp.asarray(m0), jnp.asarray(P0)
    varying = H is not None and H.ndim == 3
    H0, Hs = (H[0], H[1:]) if varying else (H, None)
    mf0, Pf0, ll0 = _update(m0, P0, y[0], H0, r) if update_first else (m0, P0, 0.0)

    # Q as weights of unit covariances is summed inside the loop: a per-step Q array built
    # outside would be materialized with its tangents when differentiated in the weights
    # (the diffusion likelihood's Hessian: 20% slower).
    w, Q = (jnp.asarray(Q[0]), _steps(Q[1], N, 3)) if isinstance(Q, tuple) else (None, _steps(Q, N, 2))

    def step(carry, inputs):
        m, P = carry
        Fk, ck, Qk, yk, Hk = inputs
        Qk = Qk if w is None else jnp.einsum("v,vij->ij", w, Qk)
        mp, Pp = Fk @ m + ck, Fk @ P @ Fk.T + Qk
        mn, Pn, ll = _update(mp, Pp, yk, Hk if varying else H, r)
        return (mn, Pn), (mn, Pn, mp, Pp, ll)

    inputs = (_steps(F, N, 2), _steps(c, N, 1), Q, y[1:], Hs)
    _, (mf, Pf, mp, Pp, ll) = jax.lax.scan(step, (mf0, Pf0), inputs)
    return Filtered(
        jnp.concatenate([mf0[None], mf]), jnp.concatenate([Pf0[None], Pf]), mp, Pp, ll0 + jnp.sum(ll)
    )


def rts_smoother(filtered: Filtered, F) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Rauch-Tung-Striebel smoothing of a `kalman_filter` run.

    **Arguments:**

    - `filtered`: `kalman_filter`'s output for `N` samples of `S` states.
    - `F`: the transition that filter used, `(S, S)` or `(N-1, S, S)`.

    **Returns:** `(means, covs, cross)`: smoothed means `(N, S)`, covariances `(N, S, S)` and
    lag-one cross covariances `cov(s_{k+1}, s_k | all)`, `(N-1, S, S)`."""
    mf, Pf, mp, Pp, _ = filtered
    N = mf.shape[0]

    def backward(carry, inputs):
        ms1, Ps1 = carry
        mk, Pk, mpk, Ppk, Fk = inputs
        G = cho_solve(cho_factor(Ppk, lower=True), Fk @ Pk).T  # Pk F^T Pp^-1
        ms = mk + G @ (ms1 - mpk)
        Ps = Pk + G @ (Ps1 - Ppk) @ G.T
        return (ms, Ps), (ms, Ps, Ps1 @ G.T)

    inputs = (mf[:-1], Pf[:-1], mp, Pp, _steps(F, N, 2))
    _, (ms, Ps, C) = jax.lax.scan(backward, (mf[-1], Pf[-1]), inputs, reverse=True)
    return jnp.concatenate([ms, mf[-1:]]), jnp.concatenate([Ps, Pf[-1:]]), C


def newton_log_variances(loglik: Callable, params, floor, iterations: int):
    """Maximize a log-likelihood over log-variances by a fixed number of Newton steps.

    Each step is clipped to a factor e per variance, the best of four step lengths
    (1, 1/2, 1/4, 0) kept (a trial whose likelihood is not finite never wins) and every
    trial floored at `floor`; a scaled ascent step where the Hessian is not negative
    definite. Fixed iterations, so it jits and vmaps.

    **Arguments:**

    - `loglik`: `loglik(params) -> ()`, the log-likelihood of the log-variances.
    - `params`: the starting log-variances, `(P,)`.
    - `floor`: the lowest log-variances allowed, `(P,)`.
    - `iterations`: the number of Newton steps.

    **Returns:** the log-variances `(P,)` after the last step."""


    def newton(_, params):
        # One copy of the gradient: the Hessian's jacfwd returns it as aux (XLA does not
        # merge two copies of a filter's scans).
        H, g = jax.jacfwd(lambda p: (jax.grad(loglik)(p),) * 2, has_aux=True)(params)
        concave = jnp.all(jnp.linalg.eigvalsh(H) < 0)
        safe = jnp.where(concave, H, -jnp.eye(H.shape[0]) * jnp.maximum(jnp.max(jnp.abs(H)), 1.0))
        delta = jnp.clip(-jnp.linalg.solve(safe, g), -1.0, 1.0)
        trials = params[None] + jnp.array([1.0, 0.5, 0.25, 0.0])[:, None] * delta[None]
        trials = jnp.maximum(trials, floor)
        values = jax.vmap(loglik)(trials)
        # A trial whose filter breaks down (NaN) must not win the argmax.
        return trials[jnp.argmax(jnp.where(jnp.isfinite(values), values, -jnp.inf))]

    return jax.lax.fori_loop(0, iterations, newton, params)
