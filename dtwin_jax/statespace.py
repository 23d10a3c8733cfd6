"""Diffusion by maximum likelihood of the noisy states, given the discovered drift.

With the drift known, the measured states are a nonlinear state-space model

    X_{k+1} = F(X_k) + w_k,   w_k ~ N(0, sum_v Gamma_v Q_v),   y_k = X_k + eps_k,

`F` one step of the updated drift (diffrax Tsit5), `Q_v` the one-step covariance per unit
diffusion of velocity `v` (Van Loan, nominal dynamics), `eps_k ~ N(0, diag(s^2))`. An
extended Kalman filter gives the likelihood of `Gamma`; Newton steps in `log Gamma` find its
maximum. This uses every sample's information about the diffusion, where a quadratic variation
of increments drowns: for example 2 at 5% noise the velocity noise per sample is ~400 times
the Brownian increment, and pre-averaged increments were off by +350%, the likelihood by ~1%.

The Gibbs sampler then sees the EM (Rauch-Tung-Striebel) targets of Eq. 23: the conditional
expectation, given all measurements, of each squared one-step velocity residual per unit
one-step variance. At the maximum their mean is the ML estimate.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.linalg import cho_factor, cho_solve

from dtwin_jax.library import Library
from dtwin_jax.systems import LinearSecondOrder


__all__ = [
    "DriftStep",
    "Linearization",
    "linearize",
    "smoother",
    "Smoothed",
    "segments",
    "diffusion_mle",
    "diffusion_targets",
]


class DriftStep(eqx.Module):
    """`F(x (m,)) -> (m,)`: one sample step `dt` s of the updated drift
    `dx/dt = A x + S Theta L(x)`, by `substeps` fixed Tsit5 steps (one is plenty at
    `omega dt <= 0.2`: its error is ~1e-7 of the state, the Brownian increment ~4e-4).

    `coefficients (r, K)` of `library` for the `regressed` states (pass a
    :meth:`Library.subset` of the selected terms to keep it cheap). The solver's `step` is
    called directly: no adaptive loop, so `F` differentiates in both modes, and as a pytree
    with static structure it reuses compiled code across updates of the same shape.
    """

    nominal: LinearSecondOrder
    library: Library
    coefficients: jax.Array
    regressed: tuple[int, ...] = eqx.field(static=True)
    dt: float = eqx.field(static=True)
    substeps: int = eqx.field(static=True, default=1)

    def perturbation(self, x):
        """Discovered extra rate `(m,)` at `x (m,)`."""
        h = self.coefficients @ self.library.eval_single(x)
        return jnp.zeros(x.shape[-1], h.dtype).at[jnp.asarray(self.regressed)].set(h)

    def rate(self, x):
        """Updated rate `(m,)` at `x (m,)`, no input."""
        return self.nominal.rate(x, jnp.zeros(self.nominal.n, x.dtype)) + self.perturbation(x)

    def __call__(self, x):
        term = diffrax.ODETerm(lambda t, y, args: self.rate(y))
        solver = diffrax.Tsit5(scan_kind="bounded")  # stage loop differentiable both ways
        h = self.dt / self.substeps
        for i in range(self.substeps):
            t0, t1 = i * h, (i + 1) * h
            state = solver.init(term, t0, t1, x, None)
            x = solver.step(term, t0, t1, x, None, state, made_jump=False)[0]
        return x


class Linearization(NamedTuple):
    """`F(X_k) ~ value_k + jac_k (X_k - point_k)` along a trajectory `point (N, m)`."""

    point: jax.Array  # (N, m)
    value: jax.Array  # (N-1, m) F at point_k
    jac: jax.Array  # (N-1, m, m) dF/dX at point_k


def linearize(step, point) -> Linearization:
    """Linearize `step` along `point (N, m)`: all samples at once, not in sequence."""
    x = jnp.asarray(point)[:-1]
    return Linearization(point, jax.vmap(step)(x), jax.vmap(jax.jacfwd(step))(x))


class Smoothed(NamedTuple):
    """Kalman filter and RTS smoother output for one record of `N` samples, `m` states."""

    mean: jax.Array  # (N, m) smoothed states
    cov: jax.Array  # (N, m, m) their covariances
    cross: jax.Array  # (N-1, m, m) cov(X_{k+1}, X_k | all)
    loglik: jax.Array  # () log p(y_1..y_{N-1} | y_0)


def _filter(lin: Linearization, y, Q, noise_var):
    """Kalman filter of `y (N, m)` on the linearized transition; per-step outputs."""
    m = y.shape[-1]
    Rm = jnp.diag(noise_var)
    eye = jnp.eye(m, dtype=y.dtype)

    def update(mp, Pp, yk):
        S = cho_factor(Pp + Rm, lower=True)
        K = cho_solve(S, Pp).T  # Pp (Pp + R)^-1
        r = yk - mp
        logdet = 2.0 * jnp.sum(jnp.log(jnp.diagonal(S[0])))
        ll = -0.5 * (r @ cho_solve(S, r) + logdet + m * jnp.log(2 * jnp.pi))
        IK = eye - K
        return mp + K @ r, IK @ Pp @ IK.T + K @ Rm @ K.T, ll  # Joseph form

    def forward(carry, inputs):
        mk, Pk = carry
        yk, xk, fk, J = inputs
        mp, Pp = fk + J @ (mk - xk), J @ Pk @ J.T + Q
        mn, Pn, ll = update(mp, Pp, yk)
        return (mn, Pn), (mn, Pn, mp, Pp, ll)

    # The first sample with a flat prior: the state is the measurement, covariance R.
    m0, P0 = y[0], Rm
    inputs = (y[1:], lin.point[:-1], lin.value, lin.jac)
    _, (mf, Pf, mp, Pp, ll) = jax.lax.scan(forward, (m0, P0), inputs)
    mf = jnp.concatenate([m0[None], mf])
    Pf = jnp.concatenate([P0[None], Pf])
    return mf, Pf, mp, Pp, jnp.sum(ll)


def smoother(lin: Linearization, y, Q, noise_var) -> Smoothed:
    """Kalman filter and RTS smoother of `y (N, m)` under `X_{k+1} = F(X_k) + N(0, Q)`,
    `F` linearized by `lin`, `y_k = X_k + N(0, diag(noise_var (m,)))`."""
    mf, Pf, mp, Pp, ll = _filter(lin, y, Q, noise_var)

    def backward(carry, inputs):
        ms1, Ps1 = carry
        mk, Pk, mpk, Ppk, Jk = inputs
        G = cho_solve(cho_factor(Ppk, lower=True), Jk @ Pk).T  # Pk J^T Pp^-1
        ms = mk + G @ (ms1 - mpk)
        Ps = Pk + G @ (Ps1 - Ppk) @ G.T
        return (ms, Ps), (ms, Ps, Ps1 @ G.T)

    _, (ms, Ps, C) = jax.lax.scan(
        backward, (mf[-1], Pf[-1]), (mf[:-1], Pf[:-1], mp, Pp, lin.jac), reverse=True
    )
    return Smoothed(jnp.concatenate([ms, mf[-1:]]), jnp.concatenate([Ps, Pf[-1:]]), C, ll)


def segments(x, length: int = 1000):
    """Split records `x (R, N, m)` into `(R * S, L, m)` pieces sharing their end samples,
    `L - 1 = (N - 1) // S` with `S = ceil((N - 1) / length)`; at most `S - 1` trailing
    samples are dropped. A long record filtered in pieces loses one sample's information per
    cut and runs `S` filters side by side instead of one long sequential scan."""
    x = jnp.asarray(x)
    R, N, m = x.shape
    S = max(1, -(-(N - 1) // length))
    L = (N - 1) // S + 1
    idx = np.arange(S)[:, None] * (L - 1) + np.arange(L)[None, :]
    return x[:, idx].reshape(R * S, L, m)


def _noise_floor(y, noise_var):
    # A state measured without noise and driven without diffusion (a damage variable) would
    # make the innovation covariance singular; a floor far below any real noise avoids that.
    var = jnp.var(y.reshape(-1, y.shape[-1]), axis=0)
    return jnp.maximum(jnp.asarray(noise_var), 1e-12 * var + 1e-300)


@eqx.filter_jit
def _linearize_records(step: DriftStep, x):
    return jax.vmap(lambda xx: linearize(step, xx))(x)


_smoothed_means = jax.jit(jax.vmap(lambda l, yy, Q, r: smoother(l, yy, Q, r).mean, (0, 0, None, None)))


def _relinearized(step: DriftStep, y, Q, r, passes: int):
    """Linearizations of every record `y (R, N, m)`: along the measurements, then `passes`
    times along the smoothed states (iterated extended Kalman smoother)."""
    lin = _linearize_records(step, y)
    for _ in range(passes):
        lin = _linearize_records(step, _smoothed_means(lin, y, Q, r))
    return lin


def _loglik(log_gamma, lin, y, r, unit_cov):
    Q = jnp.einsum("v,vij->ij", jnp.exp(log_gamma), unit_cov)
    return jnp.sum(jax.vmap(lambda l, yy: _filter(l, yy, Q, r)[-1])(lin, y))


_value = jax.jit(_loglik)
_derivatives = jax.jit(lambda *a: (jax.grad(_loglik)(*a), jax.hessian(_loglik)(*a)))


def diffusion_mle(
    step: DriftStep, y, unit_cov, noise_var, start, *, rounds: int = 2, max_iter: int = 10, tol: float = 1e-4
):
    """Maximum-likelihood diffusion `Gamma (d,)` of records `y (R, N, m)`.

    `unit_cov (d, m, m)` from :func:`kramers_moyal.process_covariances`, `start (d,)` a
    positive first guess. In each of `rounds`, the transition is linearized along the states
    smoothed at the current `Gamma`, then Newton steps in `log Gamma` (at most a factor
    e^1.5 each, halved while the likelihood falls) find the maximum. Returns `(Gamma (d,),
    information (d, d), lin)`: the observed Fisher information in `Gamma` units and the last
    linearization (batched over records).
    """
    y = jnp.asarray(y)
    r = _noise_floor(y, noise_var)
    lg = jnp.log(jnp.maximum(jnp.asarray(start, y.dtype), 1e-300))
    Q_of = lambda lg: jnp.einsum("v,vij->ij", jnp.exp(lg), unit_cov)
    for round_ in range(rounds):
        lin = _relinearized(step, y, Q_of(lg), r, 2 if round_ == 0 else 1)
        args = (lin, y, r, unit_cov)
        for _ in range(max_iter):
            f = _value(lg, *args)
            g, H = _derivatives(lg, *args)
            if bool(jnp.all(jnp.linalg.eigvalsh(H) < 0)):
                delta = -jnp.linalg.solve(H, g)
            else:  # not concave here: a gradient step scaled by the curvature's size
                delta = g / jnp.maximum(jnp.abs(jnp.diagonal(H)), 1.0)
            delta = jnp.clip(delta, -1.5, 1.5)
            for _ in range(6):
                if bool(_value(lg + delta, *args) >= f):
                    break
                delta = delta / 2
            lg = lg + delta
            if float(jnp.max(jnp.abs(delta))) < tol:
                break
    g, H = _derivatives(lg, *args)
    gamma = jnp.exp(lg)
    # d2l/dG2 = (H_log - diag(g_log)) / (G G^T), with g_log ~ 0 at the maximum.
    info = -(H - jnp.diag(g)) / (gamma[:, None] * gamma[None, :])
    return gamma, info, lin


@functools.partial(jax.jit, static_argnums=5)
def diffusion_targets(lin: Linearization, y, unit_cov, noise_var, gamma, velocity_index):
    """EM targets of the velocity diffusions at `gamma (d,)`, from records `y (R, N, m)`
    and their linearizations `lin` (batched over records, from :func:`diffusion_mle`);
    `velocity_index` a tuple of the `d` velocities' positions in the state.

    `Y_kv = E[(X_{k+1} - F(X_k))_v^2 | y] / Q_v[v, v]`, with `E[Gamma_v] = Y_kv` for a
    constant diffusion. Returns `(Y (R, N-1, d), X (R, N-1, m))`, `X` the smoothed states.
    """
    y = jnp.asarray(y)
    r = _noise_floor(y, noise_var)
    Q = jnp.einsum("v,vij->ij", jnp.asarray(gamma), unit_cov)
    vel = np.asarray(velocity_index)
    unit = unit_cov[np.arange(vel.size), vel, vel]

    def one(l, yy):
        s = smoother(l, yy, Q, r)
        x0, P0, P1, J = s.mean[:-1], s.cov[:-1], s.cov[1:], l.jac
        res = s.mean[1:] - l.value - jnp.einsum("kij,kj->ki", J, x0 - l.point[:-1])
        JC = jnp.einsum("kij,klj->kil", J, s.cross)  # J cov(X_k, X_{k+1})
        second = (
            jnp.einsum("ki,kj->kij", res, res) + P1 - JC - jnp.swapaxes(JC, 1, 2)
            + jnp.einsum("kij,kjl,kml->kim", J, P0, J)
        )
        return second[:, vel, vel] / unit, x0

    return jax.vmap(one)(lin, y)
