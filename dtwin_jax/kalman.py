"""One linear-Gaussian Kalman filter and Rauch-Tung-Striebel smoother.

    s_{k+1} = F_k s_k + c_k + N(0, Q_k),      z_k = H s_k + e_k + N(0, diag(r)),

states `s (S,)`, measurements `z (p,)`. `F`, `c`, `Q` may be one array for every step or
one per step (a leading axis `N-1`); `e` one per sample. The measurement noise is
independent across channels (`r` diagonal), so the update takes one channel at a time:
scalar innovations, no matrix factorisation, several times faster batched on a CPU.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.scipy.linalg import cho_factor, cho_solve

__all__ = ["Filtered", "kalman_filter", "rts_smoother"]


class Filtered(NamedTuple):
    """Filter output for `N` samples of `S` states."""

    mean: jax.Array  # (N, S) filtered means
    cov: jax.Array  # (N, S, S)
    pred_mean: jax.Array  # (N-1, S) one-step predictions of samples 1..N-1
    pred_cov: jax.Array  # (N-1, S, S)
    loglik: jax.Array  # () log p(z_0..z_{N-1}) given the prior of s_0


def _steps(a, N: int, ndim: int):
    """`a` per step `(N-1, ...)`, broadcast when one array serves every step."""
    a = jnp.asarray(a)
    return jnp.broadcast_to(a, (N - 1,) + a.shape) if a.ndim == ndim else a


def _update(m, P, z, H, r):
    ll = 0.0
    for i in range(H.shape[0]):  # static: one scalar update per channel
        col = P @ H[i]
        S = H[i] @ col + r[i]
        res = z[i] - H[i] @ m
        m = m + col * (res / S)
        P = P - jnp.outer(col, col) / S
        ll = ll - 0.5 * (res * res / S + jnp.log(S) + jnp.log(2 * jnp.pi))
    return m, 0.5 * (P + P.T), ll


def kalman_filter(F, c, Q, H, e, r, z, m0, P0) -> Filtered:
    """Filter `z (N, p)`: `F (S, S)` or `(N-1, S, S)`, `c (S,)` or `(N-1, S)`, `Q` like `F`,
    `H (p, S)`, `e (N, p)` known measurement offsets, `r (p,)` noise variances, prior
    `m0 (S,)`, `P0 (S, S)` of `s_0`. Pure; jit, vmap and differentiate freely."""
    z = jnp.asarray(z)
    N = z.shape[0]
    H, r, e = jnp.asarray(H), jnp.asarray(r), jnp.asarray(e)
    y = z - e
    mf0, Pf0, ll0 = _update(jnp.asarray(m0), jnp.asarray(P0), y[0], H, r)

    def step(carry, inputs):
        m, P = carry
        Fk, ck, Qk, yk = inputs
        mp, Pp = Fk @ m + ck, Fk @ P @ Fk.T + Qk
        mn, Pn, ll = _update(mp, Pp, yk, H, r)
        return (mn, Pn), (mn, Pn, mp, Pp, ll)

    inputs = (_steps(F, N, 2), _steps(c, N, 1), _steps(Q, N, 2), y[1:])
    _, (mf, Pf, mp, Pp, ll) = jax.lax.scan(step, (mf0, Pf0), inputs)
    return Filtered(
        jnp.concatenate([mf0[None], mf]), jnp.concatenate([Pf0[None], Pf]), mp, Pp, ll0 + jnp.sum(ll)
    )


def rts_smoother(filtered: Filtered, F) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Smoothed means `(N, S)`, covariances `(N, S, S)` and lag-one cross covariances
    `cov(s_{k+1}, s_k | all) (N-1, S, S)` from :func:`kalman_filter`'s output and its `F`."""
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
