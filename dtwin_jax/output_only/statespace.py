"""Diffusion by maximum likelihood of the noisy states, given the discovered drift.

With the drift known, the measured states are a nonlinear state-space model

    X_{k+1} = F(X_k) + w_k,   w_k ~ N(0, sum_v Gamma_v Q_v),   y_k = X_k + eps_k,

`F` one step of the updated drift (diffrax Tsit5), `Q_v` the one-step covariance per unit
diffusion of velocity `v` (Van Loan, under the drift's local Jacobian), `eps_k ~ N(0,
diag(s^2))`. An
extended Kalman filter gives the likelihood of `Gamma` and of the velocities' noise
variances (fitted with it: a difference-based noise estimate is good to a few percent, and its
error moves `Gamma` as much); Newton steps in their logs find the maximum. This uses every
sample's information about the diffusion, where a quadratic variation of increments drowns:
where the velocity noise per sample is hundreds of times the Brownian increment (example 2),
pre-averaged increments put the diffusion far too low, and the likelihood stays close.

The Gibbs sampler then sees the EM (Rauch-Tung-Striebel) targets of Eq. 23: the conditional
expectation, given all measurements, of each squared one-step velocity residual per unit
one-step variance. At the maximum their mean is the ML estimate.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax.library import Library, parse_library
from dtwin_jax.models.systems import LinearSecondOrder
from dtwin_jax.preprocess.kalman import Filtered, kalman_filter, rts_smoother

__all__ = [
    "DriftStep",
    "Linearization",
    "linearize",
    "local_gramians",
    "smoother",
    "Smoothed",
    "segments",
    "diffusion_mle",
    "diffusion_targets",
    "standardized_innovations",
]


class DriftStep(eqx.Module):
    """`F(x (m,)) -> (m,)`: one sample step `dt` s of the updated drift
    `dx/dt = A x + S Theta L(x)`, by `substeps` fixed Tsit5 steps (one is plenty at
    `omega dt <= 0.2`: its error is far below the Brownian increment).

    `coefficients (r, K)` of `library` for the `regressed` states (pass a
    `Library.subset` of the selected terms to keep it cheap). The solver's `step` is
    called directly: no adaptive loop, so `F` differentiates in both modes, and as a pytree
    with static structure it reuses compiled code across updates of the same shape.
    """

    nominal: LinearSecondOrder
    library: Library
    coefficients: jax.Array
    regressed: tuple[int, ...] = eqx.field(static=True)
    dt: float = eqx.field(static=True)
    substeps: int = eqx.field(static=True, default=1)
    smoothing: jax.Array | None = None

    @classmethod
    def from_coefficients(cls, nominal: LinearSecondOrder, library: Library, coefficients, dt: float,
                          smoothing=None):
        """The drift of `coefficients` of `library` for `nominal`'s regressed states, keeping
        only the terms in use.

        **Arguments:**

        - `nominal`: the nominal model `LinearSecondOrder`.
        - `library`: the drift `Library` (no inputs).
        - `coefficients`: `(r, K)` the coefficients of `library`'s terms in the regressed rows
          (zero columns are dropped).
        - `dt`: the sample step, s.
        - `smoothing`: variances `(m,)` over which the non-smooth terms (`sign`, `Abs`) are
          averaged (`Library.__call__`): the mean drift over a step whose Brownian increment
          crosses a friction's discontinuity; or None (default) for exact terms.

        **Returns:** the `DriftStep`, one Tsit5 step per sample."""
        coef = np.asarray(coefficients)
        keep = np.any(coef != 0, axis=0)
        regressed = tuple(int(i) for i in nominal.regressed_index)
        return cls(nominal, library.subset(keep), jnp.asarray(coef[:, keep]), regressed, dt, 1, smoothing)

    @classmethod
    def true(cls, example) -> "DriftStep":
        """The true perturbation of an example, for checks and studies.

        **Arguments:**

        - `example`: a `systems.Example` (its nominal model, output-only library, true
          coefficients and `dt`).

        **Returns:** the `DriftStep` of the example's true drift."""
        nominal = example.system.nominal
        lib = parse_library(example.library_output_only, nominal.m, 0)
        return cls.from_coefficients(nominal, lib, example.true_coefficients(lib.names), example.dt)

    def perturbation(self, x):
        """Discovered extra rate at one state.

        **Arguments:**

        - `x`: the state, shape `(m,)`.

        **Returns:** the perturbation `S h(x)`, shape `(m,)` (rate units, zero outside the
        regressed rows)."""
        h = self.coefficients @ self.library.eval_single(x, None, self.smoothing)
        return jnp.zeros(x.shape[-1], h.dtype).at[jnp.asarray(self.regressed)].set(h)

    def rate(self, x):
        """Updated rate at one state, no input.

        **Arguments:**

        - `x`: the state, shape `(m,)`.

        **Returns:** the nominal rate plus the perturbation, shape `(m,)` (rate units)."""
        return self.nominal.rate(x, jnp.zeros(self.nominal.n, x.dtype)) + self.perturbation(x)

    def __call__(self, x):
        """One sample step of the updated drift from a state.

        **Arguments:**

        - `x`: the state at the step's start, shape `(m,)`.

        **Returns:** `F(x)`, the state `dt` s later, shape `(m,)`.
        """
        term = diffrax.ODETerm(lambda t, y, args: self.rate(y))
        solver = diffrax.Tsit5(scan_kind="bounded")  # stage loop differentiable both ways
        h = self.dt / self.substeps
        for i in range(self.substeps):
            t0, t1 = i * h, (i + 1) * h
            state = solver.init(term, t0, t1, x, None)
            x = solver.step(term, t0, t1, x, None, state, made_jump=False)[0]
        return x


class Linearization(NamedTuple):
    """`F(X_k) ~ value_k + jac_k (X_k - point_k)` along a trajectory `point (N, m)`, and the
    one-step noise covariance per unit diffusion of each velocity there."""

    point: jax.Array  # (N, m)
    value: jax.Array  # (N-1, m) F at point_k
    jac: jax.Array  # (N-1, m, m) dF/dX at point_k
    unit_cov: jax.Array  # (N-1, d, m, m)


# Samples per block of :func:`linearize`: vmapped over all samples at once (300 records of
# 1000), the Runge-Kutta stages' buffers leave the cache and the step's Jacobian took 5x longer.
LINEARIZE_BLOCK = 1024


def linearize(step: DriftStep, point) -> Linearization:
    """Linearize `step` along a trajectory: all samples at once, not in sequence (in blocks
    of `LINEARIZE_BLOCK`).

    The noise covariance uses the local Jacobian of the drift, not the nominal one: a
    velocity's noise reaches other states through the perturbation (example 3's damage rate
    `gamma x2^2`), and a model without that path reads their residuals as extra diffusion.

    **Arguments:**

    - `step`: the `DriftStep` to linearize.
    - `point`: the trajectory, shape `(..., N, m)`, records along the leading axes.

    **Returns:** the `Linearization`: `point`, `value (..., N-1, m)`, `jac (..., N-1, m, m)`
    and `unit_cov (..., N-1, d, m, m)`.
    """
    point = jnp.asarray(point)
    m = point.shape[-1]
    x = point[..., :-1, :].reshape(-1, m)
    vel = step.nominal.velocity_index

    def one(xk):
        local = local_gramians(jax.jacfwd(step.rate)(xk), vel, step.dt, step.substeps)
        jac, value = jax.jacfwd(lambda z: (step(z),) * 2, has_aux=True)(xk)
        return value, jac, local

    # Padded to whole blocks: a remainder would compile the body a second time.
    n = x.shape[0]
    blocks = -(-n // LINEARIZE_BLOCK)
    padded = jnp.concatenate([x, jnp.broadcast_to(x[-1:], (blocks * LINEARIZE_BLOCK - n, m))])
    value, jac, local = jax.lax.map(one, padded, batch_size=LINEARIZE_BLOCK)
    lead = point.shape[:-2] + (point.shape[-2] - 1,)
    return Linearization(point, value[:n].reshape(lead + (m,)), jac[:n].reshape(lead + (m, m)),
                         local[:n].reshape(lead + local.shape[1:]))


def local_gramians(J, velocity_index, dt: float, substeps: int = 1, order: int = 6) -> jax.Array:
    """The one-step covariance per unit diffusion of each velocity under local linear
    dynamics, `int_0^dt exp(J s) e_v e_v^T exp(J^T s) ds`.

    The Taylor series `sum_k h^(k+1) / (k+1)! L^k(e_v e_v^T)`, `L(X) = J X + X J^T`, to
    `order` over each of `substeps` steps `h` (relative error ~ `(2 |J| h)^7 / 8!`, below the
    drift step's own at `|J| h = 0.2`), chained by `Q <- Phi Q Phi^T + Q_h`.
    Batched over samples this is several times cheaper than Van Loan's matrix exponential
    (`kramers_moyal.gramians`), whose Pade branches all run under `vmap`.

    **Arguments:**

    - `J`: the drift's local Jacobian, shape `(m, m)`.
    - `velocity_index`: the `d` velocities' positions in the state, a sequence of ints.
    - `dt`: the step, s.
    - `substeps`: the number of steps `h = dt / substeps` (default 1).
    - `order`: the Taylor series' order over each step (default 6).

    **Returns:** `Q`, shape `(d, m, m)`.
    """
    m = J.shape[0]
    h = dt / substeps
    v = np.asarray(velocity_index)
    B = jnp.zeros((v.size, m, m), J.dtype).at[np.arange(v.size), v, v].set(1.0)
    term, Q = B, h * B
    Phi = power = jnp.eye(m, dtype=J.dtype)
    for k in range(1, order + 1):
        term = J @ term + term @ J.T
        Q = Q + h ** (k + 1) / math.factorial(k + 1) * term
        power = power @ J * (h / k)
        Phi = Phi + power
    step_Q = Q
    for _ in range(substeps - 1):
        Q = Phi @ Q @ Phi.T + step_Q
    return Q


class Smoothed(NamedTuple):
    """Kalman filter and RTS smoother output for one record of `N` samples, `m` states."""

    mean: jax.Array  # (N, m) smoothed states
    cov: jax.Array  # (N, m, m) their covariances
    cross: jax.Array  # (N-1, m, m) cov(X_{k+1}, X_k | all)
    loglik: jax.Array  # () log p(y_1..y_{N-1} | y_0)


def _filter(lin: Linearization, y, gamma, noise_var) -> Filtered:
    """Kalman filter (`kalman.kalman_filter`) of `y (N, m)` on the linearized
    transition `X_{k+1} = value_k + jac_k (X_k - point_k) + N(0, Q_k)`,
    `Q_k = sum_v gamma_v lin.unit_cov[k, v]`, every state measured with noise variances
    `noise_var (m,)`. The first sample with a flat prior: the state is the measurement,
    covariance `diag(noise_var)`, and the likelihood is that of `y_1..y_{N-1}` given `y_0`."""
    c = lin.value - jnp.einsum("kij,kj->ki", lin.jac, lin.point[:-1])
    Q = (gamma, lin.unit_cov)
    return kalman_filter(lin.jac, c, Q, None, None, noise_var, y, y[0], jnp.diag(noise_var), update_first=False)


def smoother(lin: Linearization, y, gamma, noise_var) -> Smoothed:
    """Kalman filter and RTS smoother of one record under `X_{k+1} = F(X_k) + N(0, Q_k)`,
    `F` linearized by `lin`, `Q_k = sum_v gamma_v lin.unit_cov[k, v]`,
    `y_k = X_k + N(0, diag(noise_var))`.

    **Arguments:**

    - `lin`: the record's `Linearization` (`N - 1` steps).
    - `y`: the measured states, shape `(N, m)`.
    - `gamma`: the velocities' diffusions, shape `(d,)` (velocity^2 / s).
    - `noise_var`: the measurement noise variances, shape `(m,)` (the states' units squared).

    **Returns:** the `Smoothed` means `(N, m)`, covariances `(N, m, m)`, cross covariances
    `(N-1, m, m)` and the log-likelihood of `y_1..y_{N-1}` given `y_0`."""
    filtered = _filter(lin, y, gamma, noise_var)
    mean, cov, cross = rts_smoother(filtered, lin.jac)
    return Smoothed(mean, cov, cross, filtered.loglik)


def segments(x, length: int = 1000):
    """Split records into pieces sharing their end samples, `L - 1 = (N - 1) // S` with
    `S = ceil((N - 1) / length)`; at most `S - 1` trailing samples are dropped.

    A long record filtered in pieces loses one sample's information per cut and runs `S`
    filters side by side instead of one long sequential scan.

    **Arguments:**

    - `x`: the records, shape `(R, N, m)`.
    - `length`: the most steps per piece (default 1000).

    **Returns:** the pieces, shape `(R * S, L, m)`, record by record."""
    x = jnp.asarray(x)
    R, N, m = x.shape
    S = max(1, -(-(N - 1) // length))
    L = (N - 1) // S + 1
    idx = np.arange(S)[:, None] * (L - 1) + np.arange(L)[None, :]
    return x[:, idx].reshape(R * S, L, m)


def _noise_floor(y, noise_var):
    """Noise variances `(m,)` or `(R, m)` -> one row per record of `y (R, N, m)`, floored.

    A state measured without noise and driven without diffusion (a damage variable) would
    make the innovation covariance singular; a floor far below any real noise avoids that.
    """
    var = jnp.var(y.reshape(-1, y.shape[-1]), axis=0)
    r = jnp.maximum(jnp.asarray(noise_var), 1e-12 * var + 1e-300)
    return jnp.broadcast_to(r, (y.shape[0], y.shape[-1]))


@eqx.filter_jit
def _linearize_records(step: DriftStep, x):
    return linearize(step, x)


_smoothed_means = jax.jit(jax.vmap(lambda l, yy, g, r: smoother(l, yy, g, r).mean, (0, 0, None, 0)))


def _unpack(params, r, velocity_index):
    """`params = [log Gamma (d), log f_v (d)]` -> `(Gamma, noise variances (R, m))`: each
    record's velocity noise is its own estimate in `r (R, m)` times a common factor `f_v`."""
    d = len(velocity_index)
    factor = jnp.ones(r.shape[-1], r.dtype).at[np.asarray(velocity_index)].set(jnp.exp(params[d:]))
    return jnp.exp(params[:d]), r * factor


def _loglik(params, lin, y, r, velocity_index):
    gamma, noise = _unpack(params, r, velocity_index)
    return jnp.sum(jax.vmap(lambda l, yy, rr: _filter(l, yy, gamma, rr).loglik)(lin, y, noise))


def _loglik_derivatives(params, lin, y, r, velocity_index):
    """`(loglik, gradient (2d,), Hessian (2d, 2d))` of `_loglik` at `params`: forward
    over reverse of one function, so the program holds one copy of the filter's derivative
    (separate value, gradient and Hessian calls compiled three; forward over forward was
    slower to run)."""
    def grad_and_value(p):
        value, g = jax.value_and_grad(_loglik)(p, lin, y, r, velocity_index)
        return g, (value, g)

    H, (value, g) = jax.jacfwd(grad_and_value, has_aux=True)(params)
    return value, g, H


@eqx.filter_jit
def diffusion_mle(
    step: DriftStep,
    y,
    noise_var,
    start,
    *,
    rounds: int = 2,
    max_iter: int = 11,
    tol: float = 1e-3,
):
    """Maximum-likelihood diffusion `Gamma (d,)` and velocity noise of records.

    The transition is linearized along the records, then along the states smoothed at the
    first guess, twice; then in each of `rounds` it is linearized along the states smoothed
    at the current values and Newton steps in the logs (at most a factor e^1.5 each,
    halved while the likelihood falls) find the maximum. Pure and jittable (vmapped over the
    levels and replicates of a study).

    **Arguments:**

    - `step`: the updated drift's `DriftStep`.
    - `y`: the measured records, shape `(R, N, m)` (`segments` of them in the update).
    - `noise_var`: the states' noise variances (the states' units squared), `(m,)`, or
      `(R, m)` one row per record (a sensor whose noise scales with each record's amplitude:
      a pooled variance would read the loud records' noise as diffusion that grows with the
      state); the velocities' are a first guess, scaled by a fitted common factor (a
      difference-based estimate's error, small beside `Gamma dt`, still moves `Gamma` markedly).
    - `start`: a positive first guess of `Gamma`, shape `(d,)` (velocity^2 / s).
    - `rounds`: rounds of linearization and Newton steps after the first guess's two
      (default 2).
    - `max_iter`: the most likelihood evaluations per round (default 11).
    - `tol`: stop a round's Newton steps once the next step of `log Gamma` is below it
      (default 1e-3).

    **Returns:** `(Gamma, Gamma_cov, noise_var, lin)`: the diffusion `Gamma (d,)`
    (velocity^2 / s), `Gamma_cov (d, d)` the inverse observed information of `Gamma` with the
    noise profiled out, the fitted noise variances `(R, m)` and the last `Linearization`
    (batched over records).
    """
    y = jnp.asarray(y)
    vel = tuple(int(v) for v in step.nominal.velocity_index)
    d = len(vel)
    r = _noise_floor(y, noise_var)
    gamma0 = jnp.maximum(jnp.asarray(start, y.dtype), 1e-300)
    # A noise-free record has its MLE at s_v^2 = 0; start no lower than 1e-4 of an increment.
    r = r.at[:, np.asarray(vel)].max(1e-4 * gamma0 * step.dt)
    params = jnp.concatenate([jnp.log(gamma0), jnp.zeros(d, y.dtype)])

    def round_(k, carry):
        # Linearize along the current points (the records, then smoothed states), Newton
        # steps from round 2 on, then smooth at the current values for the next round. One
        # compiled body for every round: a Python loop, or a first linearization outside the
        # loop, would compile the filters and the linearization once per copy.
        params, points, lin, g, H = carry
        lin = _linearize_records(step, points)
        iterations = jnp.where(k < 2, 0, max_iter)
        params, g, H = _newton(params, (lin, y, r, vel), iterations, tol, d, g, H)
        gamma, noise = _unpack(params, r, vel)
        points = jax.lax.cond(k < rounds + 1, lambda: _smoothed_means(lin, y, gamma, noise), lambda: points)
        return params, points, lin, g, H

    blank = jnp.zeros((2 * d, 2 * d), y.dtype)
    lin = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), eqx.filter_eval_shape(_linearize_records, step, y))
    params, _, lin, g, H = jax.lax.fori_loop(0, rounds + 2, round_, (params, y, lin, blank[0], blank))
    gamma, noise = _unpack(params, r, vel)
    theta = jnp.exp(params)
    # Information in natural units, d2l/dp2 = (H_log - diag(g_log)) / (p p^T).
    info = -(H - jnp.diag(g)) / (theta[:, None] * theta[None, :])
    I_gg, I_gs, I_ss = info[:d, :d], info[:d, d:], info[d:, d:]
    profiled = I_gg - I_gs @ jnp.linalg.solve(I_ss, I_gs.T)  # the noise profiled out
    I_gg = jnp.where(jnp.all(jnp.linalg.eigvalsh(I_ss) > 0), profiled, I_gg)
    return gamma, jnp.linalg.inv(I_gg), noise, lin


def _newton(params, args, max_iter, tol: float, d: int, g, H):
    """Newton steps in the logs from `params`: at most a factor e^1.5 each, halved (up to 6
    times) while the likelihood falls; a scaled gradient step where it is not concave. Stops
    when the next step of `Gamma` is below `tol` (a vanishing noise may still creep to zero)
    or after `max_iter` evaluations, the last of which takes no step, so the returned
    `(params, gradient, Hessian)` belong together (the information at the maximum);
    with `max_iter = 0` it returns its inputs. Every evaluation is one
    `_loglik_derivatives` at a trial point: accepted, or the step halved."""

    def newton_step(g, H):
        newton = -jnp.linalg.solve(H, g)
        gradient = g / jnp.maximum(jnp.abs(jnp.diagonal(H)), 1.0)
        return jnp.clip(jnp.where(jnp.all(jnp.linalg.eigvalsh(H) < 0), newton, gradient), -1.5, 1.5)

    def iterate(carry):
        i, p, f, g, H, delta, halvings, _ = carry
        f_new, g_new, H_new = _loglik_derivatives(p + delta, *args)
        # The first evaluation (delta 0, f -inf) is always accepted.
        accept = (f_new >= f) | (halvings >= 6)
        p, f, g, H = jax.tree.map(lambda new, old: jnp.where(accept, new, old), (p + delta, f_new, g_new, H_new),
                                  (p, f, g, H))
        step = newton_step(g, H)
        done = accept & ((jnp.max(jnp.abs(step[:d])) < tol) | (i + 1 >= max_iter))
        delta = jnp.where(accept, step, delta / 2)
        halvings = jnp.where(accept, 0, halvings + 1)
        return i + 1, p, f, g, H, delta, halvings, done

    going = lambda c: (c[0] < max_iter) & ~c[7]
    zero = jnp.zeros_like(params)
    start = (0, params, jnp.asarray(-jnp.inf, params.dtype), g, H, zero, 0, False)
    _, params, _, g, H, _, _, _ = jax.lax.while_loop(going, iterate, start)
    return params, g, H


@functools.partial(jax.jit, static_argnums=4)
def diffusion_targets(lin: Linearization, y, noise_var, gamma, velocity_index: tuple[int, ...]):
    """EM targets of the velocity diffusions, from smoothed records.

    `Y_kv = E[(X_{k+1} - F(X_k))_v^2 | y] / Q_kv[v, v]`, with `E[Gamma_v] = Y_kv` for a
    constant diffusion.

    **Arguments:**

    - `lin`: the records' `Linearization` (batched over records, from `diffusion_mle`).
    - `y`: the measured records, shape `(R, N, m)`.
    - `noise_var`: the measurement noise variances, `(m,)` or `(R, m)` one row per record
      (the states' units squared).
    - `gamma`: the diffusions at which to smooth, shape `(d,)` (velocity^2 / s).
    - `velocity_index`: the `d` velocities' positions in the state, a tuple of ints (static).

    **Returns:** `(Y, X)`: the targets `Y (R, N-1, d)` (velocity^2 / s) and the smoothed states
    `X (R, N-1, m)` they regress on.
    """
    y = jnp.asarray(y)
    r = _noise_floor(y, noise_var)
    vel = np.asarray(velocity_index)

    def one(l, yy, rr):
        s = smoother(l, yy, gamma, rr)
        x0, P0, P1, J = s.mean[:-1], s.cov[:-1], s.cov[1:], l.jac
        res = s.mean[1:] - l.value - jnp.einsum("kij,kj->ki", J, x0 - l.point[:-1])
        JC = jnp.einsum("kij,klj->kil", J, s.cross)  # J cov(X_k, X_{k+1})
        second = (
            jnp.einsum("ki,kj->kij", res, res) + P1 - JC - jnp.swapaxes(JC, 1, 2)
            + jnp.einsum("kij,kjl,kml->kim", J, P0, J)
        )
        unit = l.unit_cov[:, np.arange(vel.size), vel, vel]  # (N-1, d)
        return second[:, vel, vel] / unit, x0

    return jax.vmap(one)(lin, y, r)


@functools.partial(jax.jit, static_argnums=4)
def standardized_innovations(lin: Linearization, y, noise_var, gamma, velocity_index: tuple[int, ...]):
    """One-step prediction errors of the velocities under the fitted drift and diffusion,
    each divided by its predicted std, and the predicted states they follow.

    The innovations are white standard normal, and independent of anything predicted from
    the past, when the model explains the data; a missing or wrong drift term leaves
    structure in them against the predicted states.

    **Arguments:**

    - `lin`: the records' `Linearization` (batched over records, from `diffusion_mle`).
    - `y`: the measured records, shape `(R, N, m)`.
    - `noise_var`: the measurement noise variances, `(m,)` or `(R, m)` one row per record
      (the states' units squared).
    - `gamma`: the fitted diffusions, shape `(d,)` (velocity^2 / s).
    - `velocity_index`: the `d` velocities' positions in the state, a tuple of ints (static).

    **Returns:** `(innovations, predicted)`: the standardized innovations `(R, N-1, d)`
    (dimensionless) and the predicted states `(R, N-1, m)`.
    """
    y = jnp.asarray(y)
    r = _noise_floor(y, noise_var)
    vel = np.asarray(velocity_index)

    def one(l, yy, rr):
        filtered = _filter(l, yy, gamma, rr)
        mp, Pp = filtered.pred_mean, filtered.pred_cov
        scale = jnp.sqrt(Pp[:, vel, vel] + rr[vel])
        return (yy[1:, vel] - mp[:, vel]) / scale, mp

    return jax.vmap(one)(lin, y, r)
