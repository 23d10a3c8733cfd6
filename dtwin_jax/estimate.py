"""States and rates from measurements of some of the states, by a state-space smoother.

When only some states are measured (a displacement sensor alone, say), the velocities and
accelerations must be estimated, and filters that differentiate the samples break down at
low oversampling (a Savitzky-Golay derivative needs many samples per period; the Silverbox
record has nine). Instead the nominal model itself interpolates between samples: the
state is augmented with one unknown disturbance rate `w_i` per regressed state,

    dq/dt = v,   dv/dt = M^-1 (B u + F0 - C v - K q) + w_v,   de/dt = w_e,   dw = sqrt(Q_w) dB,

(the perturbation, whatever it is, as an unknown input that wanders as a random walk),
discretized exactly under the held or linearly interpolated input, with the measured states
and rates as noisy linear measurements. The measurement noise variances and the
disturbance intensities are fitted by maximum likelihood; the Rauch-Tung-Striebel smoother
then gives every state and the disturbance, and the disturbance is the framework-1 target
`xdot - f(x, u)` of every regressed state.

:func:`identify_linear` fits the nominal linear model itself from input-output data with
the same smoother (starting from pure kinematics), for a structure without a model.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax.errors import DataError
from dtwin_jax.kalman import kalman_filter, newton_log_variances, rts_smoother
from dtwin_jax.linalg import expm, mass_solve
from dtwin_jax.systems import UPSAMPLE, LinearSecondOrder, check_interpolation, upsample

__all__ = ["measured_index", "discretize", "state_smoother", "identify_linear"]

_SEGMENT = 2000  # samples per piece in the noise fit (pieces run side by side)


def measured_index(names, nominal: LinearSecondOrder, what: str = "x_names") -> tuple[int, ...]:
    """Indices of the measured states named in `names` (`None`: all `m` in order)."""
    if names is None:
        return tuple(range(nominal.m))
    names = [str(n) for n in np.atleast_1d(np.asarray(names))]
    unknown = [n for n in names if n not in nominal.state_names]
    if unknown:
        raise DataError(f"'{what}' names unknown states {unknown}; the states are {list(nominal.state_names)}")
    if len(set(names)) != len(names):
        raise DataError(f"'{what}' repeats a state: {names}")
    return tuple(nominal.state_names.index(n) for n in names)


def _continuous(nominal: LinearSecondOrder):
    """`A (S, S)`, `Bc (S, n+1)` (inputs, then the constant force) of the augmented state
    `[x (m), w (r)]`, `r` = number of regressed states."""
    d, m, n = nominal.d, nominal.m, nominal.n
    reg = np.asarray(nominal.regressed_index)
    S = m + reg.size
    Minv = mass_solve(nominal.M, jnp.eye(d))
    A = jnp.zeros((S, S)).at[:d, d : 2 * d].set(jnp.eye(d))
    A = A.at[d : 2 * d, :d].set(-Minv @ nominal.K).at[d : 2 * d, d : 2 * d].set(-Minv @ nominal.C)
    A = A.at[reg, m + np.arange(reg.size)].set(1.0)
    Bc = jnp.zeros((S, n + 1)).at[d : 2 * d, :n].set(Minv @ nominal.B).at[d : 2 * d, n].set(Minv @ nominal.F0)
    return A, Bc


def discretize(nominal: LinearSecondOrder, dt: float, interpolation: str = "held"):
    """Exact one-step map of the augmented model over `dt` s:
    `s_{k+1} = F s_k + sum_j W_j [u~_{kL+j}, 1] + noise`, `u~` the input on a grid `L`
    times finer (`L = 1` unless band-limited, :func:`systems.upsample`), held over the step
    (`W_1 = 0`) or linear between fine samples. Returns `(F, W (L+1, S, n+1), Q_unit (r, S, S))`,
    `Q_unit` the one-step covariance per unit intensity of each disturbance (8-point
    Gauss-Legendre quadrature of `exp(A s) e e^T exp(A^T s)`: Van Loan's block exponential
    loses the small entries when the states' scales differ by many orders)."""
    check_interpolation(interpolation)
    A, Bc = _continuous(nominal)
    S, p = Bc.shape
    L = UPSAMPLE if interpolation == "bandlimited" else 1
    h = dt / L
    block = jnp.zeros((S + 2 * p, S + 2 * p)).at[:S, :S].set(A * h).at[:S, S : S + p].set(Bc * h)
    E = expm(block.at[S : S + p, S + p :].set(jnp.eye(p)))
    Fh, G_all, G_ramp = E[:S, :S], E[:S, S : S + p], E[:S, S + p :]
    G0, G1 = (G_all, jnp.zeros_like(G_all)) if interpolation == "held" else (G_all - G_ramp, G_ramp)
    # Sub-step j (fine samples j, j+1) reaches the step's end through F_h^(L-1-j).
    powers = [jnp.eye(S)]
    for _ in range(L):
        powers.append(Fh @ powers[-1])
    W = jnp.stack([
        (powers[L - 1 - j] @ G0 if j < L else 0.0) + (powers[L - j] @ G1 if j > 0 else 0.0)
        for j in range(L + 1)
    ])
    nodes, weights = np.polynomial.legendre.leggauss(8)
    Es = jax.vmap(lambda s: expm(A * s))(jnp.asarray(0.5 * dt * (nodes + 1)))
    m = nominal.m
    cols = Es[:, :, m:]  # (8, S, r): exp(A s) e_w
    Q_unit = 0.5 * dt * jnp.einsum("g,gir,gjr->rij", jnp.asarray(weights), cols, cols)
    return powers[L], W, Q_unit


def _measurement(nominal: LinearSecondOrder, x_index, xdot_index):
    """`H (p, S)` and the input gain `D (p, n+1)` of the measured states then rates:
    a rate is `A s + Bc [u, 1]` at the sample."""
    A, Bc = _continuous(nominal)
    S = A.shape[0]
    H = jnp.concatenate([jnp.eye(S)[np.asarray(x_index, int)], A[np.asarray(xdot_index, int)]])
    D = jnp.concatenate([jnp.zeros((len(x_index), Bc.shape[1])), Bc[np.asarray(xdot_index, int)]])
    return H, D


class _Model(eqx.Module):
    F: jax.Array
    W: jax.Array
    Q_unit: jax.Array
    H: jax.Array
    D: jax.Array


def _model(nominal, dt, interpolation, x_index, xdot_index) -> _Model:
    return _Model(*discretize(nominal, dt, interpolation), *_measurement(nominal, x_index, xdot_index))


def _prior(model: _Model, z, r):
    """A diffuse prior of `s_0` at the scale of the data: each state's variance `1e4` times
    the largest it could have given the measured channels' variances."""
    S = model.F.shape[0]
    scale = jnp.var(z, axis=0) + r  # (p,)
    # Channel i measures H_i s; a state j it sees with gain |H_ij| has variance <~ var_i / H_ij^2.
    gain = jnp.abs(model.H)
    per = jnp.where(gain > 0, scale[:, None] / jnp.where(gain > 0, gain, 1.0) ** 2, 0.0)
    var = jnp.max(per, axis=0)
    var = jnp.where(var > 0, var, jnp.max(var))
    return jnp.zeros(S), jnp.diag(1e4 * var)


def _run(model: _Model, z, u, r, q):
    """Filter one record: `z (N, p)` measurements, `u (L (N-1) + 1, n+1)` the fine inputs
    with the constant (`L + 1 = model.W.shape[0]`)."""
    L = model.W.shape[0] - 1
    N = z.shape[0]
    window = jnp.arange(N - 1)[:, None] * L + jnp.arange(L + 1)[None, :]
    c = jnp.einsum("jsi,kji->ks", model.W, u[window])
    u = u[::L]
    Q = jnp.einsum("r,rij->ij", q, model.Q_unit)
    m0, P0 = _prior(model, z, r)
    return kalman_filter(model.F, c, Q, model.H, u @ model.D.T, r, z, m0, P0), Q


def _pieces(a, length: int, fine: int = 1):
    """`(R, N, c)` -> `(R * P, L, c)` pieces of `L = N // P` samples (the tail dropped)
    sharing their end samples; `fine > 1`: `a` is on a grid `fine` times finer."""
    R, N, c = a.shape
    N = (N - 1) // fine + 1
    P = max(1, (N - 1) // length)
    L = (N - 1) // P
    idx = (np.arange(P)[:, None] * L + np.arange(L + 1)[None, :])  # coarse indices
    idx = (idx[:, :1] * fine + np.arange(L * fine + 1)[None, :])
    return a[:, idx].reshape(R * P, L * fine + 1, c)


@functools.partial(jax.jit, static_argnames=("iterations",))
def _fit_noise(model: _Model, z, u, iterations: int = 20):
    """Maximum-likelihood measurement variances `(p,)` and disturbance intensities `(r,)`
    of records `z (R, N, p)` under inputs `u (R, L (N-1) + 1, n+1)` (fine grid): a coarse scan of a common
    intensity factor, then Newton steps in the logs (:func:`kalman.newton_log_variances`).
    Pieces of the records are filtered side by side."""
    zp, up = _pieces(z, _SEGMENT), _pieces(u, _SEGMENT, model.W.shape[0] - 1)
    var_z = jnp.var(z.reshape(-1, z.shape[-1]), axis=0)
    p = z.shape[-1]
    r_floor = 1e-12 * var_z + 1e-300
    # First guesses: noise 1e-3 of each channel's std; disturbances of an acceleration as
    # large as the state's scale could give at the Nyquist frequency (an upper bound, then
    # scanned down over 13 decades).
    r0 = 1e-6 * var_z
    _, P0 = _prior(model, z.reshape(-1, p)[: 4 * _SEGMENT], r0)
    dt = model.Q_unit[0, -model.Q_unit.shape[0], -model.Q_unit.shape[0]]  # int_0^dt ds
    omega = jnp.pi / dt
    q0 = jnp.full(model.Q_unit.shape[0], jnp.max(jnp.diagonal(P0)) / 1e4 * omega**5)
    def loglik(params):
        r = jnp.exp(params[:p])
        q = jnp.exp(params[p:])
        return jnp.sum(jax.vmap(lambda zz, uu: _run(model, zz, uu, r, q)[0].loglik)(zp, up))

    base = jnp.log(jnp.concatenate([r0, q0]))
    factors = jnp.linspace(-30.0, 0.0, 16)
    trial = jax.vmap(lambda f: loglik(base.at[p:].add(f)))(factors)
    params = base.at[p:].add(factors[jnp.argmax(jnp.where(jnp.isfinite(trial), trial, -jnp.inf))])
    floor = jnp.concatenate([jnp.log(r_floor), jnp.full(q0.shape, -700.0)])

    params = newton_log_variances(loglik, params, floor, iterations)
    return jnp.exp(params[:p]), jnp.exp(params[p:])


@jax.jit
def _smooth_records(model: _Model, z, u, r, q):
    def one(zz, uu):
        filtered, _ = _run(model, zz, uu, r, q)
        return rts_smoother(filtered, model.F)[0]

    return jax.vmap(one)(z, u)


def state_smoother(
    nominal: LinearSecondOrder,
    dt: float,
    x,
    x_index,
    u=None,
    xdot=None,
    xdot_index=(),
    *,
    interpolation: str = "held",
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Every state and rate from measurements of some of them (see the module docstring).

    `x (R, N, p)` the measured states `x_index` (indices into the `m` states), `u (R, N, n)`
    the inputs or None (output-only: then no input enters), `xdot (R, N, s)` measured rates
    of the states `xdot_index`, or None; `dt` s. Returns `(x (R, N, m), xdot (R, N, m),
    info)`: smoothed states, their rates under the nominal model plus the estimated
    disturbance, and the fitted noise standard deviations and disturbance intensities.
    """
    x = np.asarray(x, dtype=np.float64)
    R, N, _ = x.shape
    xdot = np.zeros((R, N, 0)) if xdot is None else np.asarray(xdot, dtype=np.float64)
    xdot_index = tuple(xdot_index) if xdot.shape[-1] else ()
    n = nominal.n
    uu = np.zeros((R, N, n)) if u is None else np.asarray(u, dtype=np.float64)
    if u is None:
        nominal = eqx.tree_at(lambda s: s.B, nominal, jnp.zeros_like(nominal.B))
    u1 = jnp.asarray(np.concatenate([uu, np.ones((R, N, 1))], axis=-1))
    fine = jax.vmap(upsample)(u1) if interpolation == "bandlimited" else u1
    z = jnp.asarray(np.concatenate([x, xdot], axis=-1))
    model = _model(nominal, dt, interpolation, tuple(x_index), xdot_index)
    r, q = _fit_noise(model, z, fine)
    s = _smooth_records(model, z, fine, r, q)
    m = nominal.m
    A, Bc = _continuous(nominal)
    rates = jnp.einsum("ij,rnj->rni", A[:m], s) + jnp.einsum("ij,rnj->rni", Bc[:m], u1)
    info = {
        "method": "state-space RTS (nominal model + random-walk disturbance)",
        "interpolation": interpolation,
        "noise_std": np.sqrt(np.asarray(r)).tolist(),
        "disturbance_intensity": np.asarray(q).tolist(),
    }
    return np.asarray(s[..., :m]), np.asarray(rates), info


def identify_linear(
    t,
    x,
    u,
    x_names=None,
    *,
    d: int = 1,
    xdot=None,
    xdot_names=None,
    interpolation: str = "held",
    max_iterations: int = 30,
    rtol: float = 1e-4,
) -> LinearSecondOrder:
    """A linear model `q'' + C q' + K q = B u + F0` (unit mass matrix: only `M^-1` times
    the rest is identifiable without a known force scale) fitted to input-output records.

    `t (N,)` s, `x (N, p)` or `(R, N, p)` measured states named `x_names` (default all
    `2d`), `u (.., N, n)` inputs. Starting from pure kinematics (`C = K = B = F0 = 0`, the
    whole acceleration a disturbance), :func:`state_smoother` estimates every state and
    acceleration, least squares fits `C, K, B, F0` to them, and the smoother runs again
    under the fitted model, until the fitted acceleration moves by less than `rtol` of its
    std (at most `max_iterations` rounds): the model then interpolates between the samples,
    which at a few samples per period no differentiating filter can. The smoother shrinks
    the disturbance toward the current model, so each round corrects only part of the gap
    (a lightly damped system at 9 samples per period: C 7.5% and B 3.5% short after 4
    rounds, exact after 12).
    """
    from dtwin_jax.data import check_records

    if d < 1:
        raise DataError(f"d must be a positive number of degrees of freedom, got {d}")
    t = np.asarray(t, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64)
    u = np.asarray(u, dtype=np.float64)
    n = u.shape[-1]
    nominal = LinearSecondOrder.create(np.eye(d), np.zeros((d, d)), np.zeros((d, d)), np.zeros((d, n)))
    x_index = measured_index(x_names, nominal)
    xdot_index = measured_index(xdot_names, nominal, "xdot_names") if xdot is not None else ()
    rec = check_records(t, x, u, xdot)
    if rec.x.shape[-1] != len(x_index):
        raise DataError(f"'x' has {rec.x.shape[-1]} columns but x_names names {len(x_index)}")
    previous = None
    for _ in range(max_iterations):
        xs, rates, _ = state_smoother(
            nominal, rec.dt, rec.x, x_index, rec.u, rec.xdot, xdot_index, interpolation=interpolation
        )
        regressors = np.concatenate([xs[..., : 2 * d], rec.u, np.ones(xs.shape[:-1] + (1,))], axis=-1)
        regressors = regressors.reshape(-1, regressors.shape[-1])
        coef, *_ = np.linalg.lstsq(regressors, rates[..., d : 2 * d].reshape(-1, d), rcond=None)
        coef = coef.T  # (d, 2d + n + 1): [-K, -C, B, F0]
        nominal = LinearSecondOrder.create(
            np.eye(d), -coef[:, d : 2 * d], -coef[:, :d], coef[:, 2 * d : 2 * d + n], F0=coef[:, -1]
        )
        if previous is not None:
            moved = np.std(regressors @ (coef - previous).T, axis=0)
            if np.all(moved <= rtol * np.std(regressors @ coef.T, axis=0)):
                break
        previous = coef
    return nominal
