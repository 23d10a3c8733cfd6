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

`identify_linear` fits the nominal linear model itself from input-output data with
the same smoother (starting from pure kinematics), for a structure without a model; known
parameters (a mass, `K = 0`) can be fixed, and the model it returns is never unstable.
"""

from __future__ import annotations

import functools
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax.errors import DataError
from dtwin_jax.linalg import expm, mass_solve
from dtwin_jax.models.systems import (
    UPSAMPLE,
    LinearSecondOrder,
    check_interpolation,
    real_array,
    resolve_interpolation,
    upsample,
)
from dtwin_jax.preprocess.kalman import (
    kalman_filter,
    newton_log_variances,
    rts_smoother,
)

__all__ = ["discretize", "identify_linear", "measured_index", "state_smoother"]

_SEGMENT = 2000  # samples per piece in the noise fit (pieces run side by side)


def measured_index(names, nominal: LinearSecondOrder, what: str = "x_names") -> tuple[int, ...]:
    """Indices of the measured states named in `names`.

    **Arguments:**

    - `names`: state names (a string or a sequence of them), or None (all `m` states in order).
    - `nominal`: the nominal model, whose `state_names` they index.
    - `what`: the argument's name in the error messages (default `"x_names"`).

    **Returns:** the indices into the `m` states, a tuple of ints in the order of `names`.
    Raises a one-line `DataError` for an unknown or repeated name.
    """
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
    """Exact one-step map of the augmented model over one sample step.

    `s_{k+1} = F s_k + sum_j W_j [u~_{kL+j}, 1] + noise`, `u~` the input on a grid `L`
    times finer (`L = 1` unless band-limited, `systems.upsample`), held over the step
    (`W_1 = 0`) or linear between fine samples. `Q_unit` is the one-step covariance per unit
    intensity of each disturbance (8-point Gauss-Legendre quadrature of
    `exp(A s) e e^T exp(A^T s)`: Van Loan's block exponential loses the small entries when
    the states' scales differ by many orders).

    **Arguments:**

    - `nominal`: the nominal model (`m` states, `r` of them regressed, `n` inputs).
    - `dt`: sample step, s.
    - `interpolation`: the input between samples, `"held"` (default), `"linear"` or
      `"bandlimited"`.

    **Returns:** `(F, W, Q_unit)`: the state transition `(S, S)` of the augmented state
    `S = m + r`, the input gains `(L+1, S, n+1)` (inputs, then the constant force) and the
    unit disturbance covariances `(r, S, S)`.
    """
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
    intensity factor, then Newton steps in the logs (`kalman.newton_log_variances`).
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

    **Arguments:**

    - `nominal`: the nominal model.
    - `dt`: sample step, s.
    - `x`: `(R, N, p)` the measured states `x_index`.
    - `x_index`: indices of the measured states into the `m` states.
    - `u`: `(R, N, n)` the inputs, or None (output-only: then no input enters).
    - `xdot`: `(R, N, s)` measured rates of the states `xdot_index`, or None.
    - `xdot_index`: indices of the states whose rates are measured (ignored without `xdot`).
    - `interpolation`: the input between samples, `"held"` (default), `"linear"` or
      `"bandlimited"`.

    **Returns:** `(x, xdot, info)`: the smoothed states `(R, N, m)`, their rates `(R, N, m)`
    under the nominal model plus the estimated disturbance, and a dict with the method, the
    fitted noise standard deviations `(p + s,)` and the disturbance intensities `(r,)`.
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


_FIXABLE = ("M", "C", "K", "B", "F0")
_SIGN = {"K": -1.0, "C": -1.0, "B": 1.0, "F0": 1.0}  # force = -K q - C v + B u + F0
# A returned model's eigenvalues may have real parts up to this times the spectral radius
# (the round-off of an exact zero mode, e.g. an integrating plant's).
STABLE_RTOL = 1e-6


def _check_fixed(fixed, d: int, n: int) -> dict[str, np.ndarray]:
    """`fixed` as float64 arrays of the model's shapes; a scalar `M`, `C`, `K` is that
    multiple of the identity, a scalar `B`, `F0` fills every entry."""
    if fixed is None:
        return {}
    if not isinstance(fixed, dict):
        raise DataError(f"'fixed' must be a dict with keys among {list(_FIXABLE)}, got {type(fixed).__name__}")
    unknown = [k for k in fixed if k not in _FIXABLE]
    if unknown:
        raise DataError(f"'fixed' has unknown keys {unknown}; the keys are {list(_FIXABLE)}")
    shapes = {"M": (d, d), "C": (d, d), "K": (d, d), "B": (d, n), "F0": (d,)}
    out = {}
    for name, value in fixed.items():
        a = real_array(f"fixed {name}", value)
        given = a.shape
        if a.ndim == 0:
            a = float(a) * np.eye(d) if name in ("M", "C", "K") else np.full(shapes[name], float(a))
        elif name == "B" and a.ndim == 1 and n == 1:
            a = a[:, None]
        if a.shape != shapes[name]:
            raise DataError(f"fixed {name} has shape {given}, expected {shapes[name]} or a scalar")
        if not np.all(np.isfinite(a)):
            raise DataError(f"fixed {name} has a non-finite entry")
        out[name] = a
    if "M" in out:
        M = out["M"]
        if not np.allclose(M, M.T, rtol=1e-10, atol=0) or np.min(np.linalg.eigvalsh(M)) <= 0:
            raise DataError("fixed M must be symmetric positive definite")
    return out


def _max_real_part(M, C, K) -> tuple[float, float]:
    """Largest eigenvalue real part (1/s) of `[[0, I], [-M^-1 K, -M^-1 C]]` and the tolerance
    it must not exceed."""
    d = M.shape[0]
    A = np.block([[np.zeros((d, d)), np.eye(d)], [-np.linalg.solve(M, K), -np.linalg.solve(M, C)]])
    lam = np.linalg.eigvals(A)
    return float(np.max(lam.real)), STABLE_RTOL * float(np.max(np.abs(lam)))


def _psd_part(a: np.ndarray) -> np.ndarray:
    """The nearest symmetric positive semidefinite matrix (Frobenius norm)."""
    w, v = np.linalg.eigh(0.5 * (a + a.T))
    return (v * np.maximum(w, 0.0)) @ v.T


def _fit_rounds(rec, x_index, xdot_index, d, n, M, fixed, nominal, interpolation, max_iterations, rtol):
    """The smoother / least-squares rounds of `identify_linear`; returns the fitted model,
    its `C, K, B, F0` in force units (`M` times the acceleration)."""
    free = [k for k in ("K", "C", "B", "F0") if k not in fixed]
    widths = {"K": d, "C": d, "B": n, "F0": 1}
    params = {k: fixed[k] for k in fixed if k != "M"}
    previous = None
    for _ in range(max_iterations):
        xs, rates, _ = state_smoother(
            nominal, rec.dt, rec.x, x_index, rec.u, rec.xdot, xdot_index, interpolation=interpolation
        )
        phi = {"K": xs[..., :d], "C": xs[..., d : 2 * d], "B": rec.u, "F0": np.ones(xs.shape[:-1] + (1,))}
        phi = {k: v.reshape(-1, v.shape[-1]) for k, v in phi.items()}
        # M a = sum of the terms; the fixed ones move to the target, the free ones are fitted.
        target = rates[..., d : 2 * d].reshape(-1, d) @ M.T
        for k in fixed.keys() - {"M"}:
            target = target - _SIGN[k] * phi[k] @ fixed[k].reshape(d, -1).T
        if free:
            coef, *_ = np.linalg.lstsq(np.concatenate([phi[k] for k in free], axis=1), target, rcond=None)
            at = 0
            for k in free:
                params[k] = _SIGN[k] * coef[at : at + widths[k]].T
                at += widths[k]
        params["F0"] = params["F0"].reshape(d)
        nominal = LinearSecondOrder.create(M, params["C"], params["K"], params["B"], F0=params["F0"])
        regressors = np.concatenate([phi[k] for k in ("K", "C", "B", "F0")], axis=1)
        full = np.concatenate([_SIGN[k] * params[k].reshape(d, -1) for k in ("K", "C", "B", "F0")], axis=1)
        if not free:
            break
        if previous is not None:
            moved = np.std(regressors @ (full - previous).T, axis=0)
            if np.all(moved <= rtol * np.std(regressors @ full.T, axis=0)):
                break
        previous = full
    return nominal


def identify_linear(
    t,
    x,
    u,
    x_names=None,
    *,
    d: int = 1,
    xdot=None,
    xdot_names=None,
    interpolation: str = "auto",
    max_iterations: int = 30,
    rtol: float = 1e-4,
    fixed: dict | None = None,
) -> LinearSecondOrder:
    """A linear model `M q'' + C q' + K q = B u + F0` fitted to input-output records.

    Starting from pure kinematics (`C = K = B = F0 = 0`, the whole acceleration a
    disturbance), `state_smoother` estimates every state and acceleration, least
    squares fits the free parameters to them, and the smoother runs again under the fitted
    model, until the fitted acceleration moves by less than `rtol` of its std (at most
    `max_iterations` rounds): the model then interpolates between the samples, which at a
    few samples per period no differentiating filter can. The smoother shrinks the
    disturbance toward the current model, so each round corrects only part of the gap (a
    lightly damped system at a few samples per period needs many rounds to close it).

    The returned model is never unstable (no eigenvalue of `[[0, I], [-M^-1 K, -M^-1 C]]`
    with a real part above `STABLE_RTOL` times the spectral radius): when the free fit is,
    each free `K`, `C` that is not symmetric positive semidefinite is replaced by its
    nearest such matrix (a negative stiffness or damping clipped to 0), fixed there, the
    rest refitted, and a one-line `UserWarning` names what was clipped. An integrating
    plant (no spring) fitted from closed-loop data may need this; pass `fixed={"K": 0}`
    to say so up front. If clipping cannot make it stable (an unstable fixed part, a
    circulatory `K`) a one-line `DataError` is raised.

    **Arguments:**

    - `t`: `(N,)` sample times, s, uniform.
    - `x`: `(N, p)` or `(R, N, p)` measured states named `x_names`.
    - `u`: `(N, n)` or `(R, N, n)` inputs (force units when `M` is fixed).
    - `x_names`: the states of the columns of `x`, or None (default: all `2d`,
      displacements then velocities).
    - `d`: degrees of freedom.
    - `xdot`: `(N, s)` or `(R, N, s)` measured rates of the states `xdot_names`, or None.
    - `xdot_names`: the states whose rates are the columns of `xdot`, or None (default: all
      `2d` in order).
    - `interpolation`: the input between samples, `"held"`, `"linear"`, `"bandlimited"`, or
      `"auto"`: held or band-limited from the input's spectrum
      (`dtwin_jax.models.systems.choose_interpolation`).
    - `max_iterations`: the most smoother / least-squares rounds.
    - `rtol`: the rounds stop when the fitted acceleration moves by less than this fraction
      of its std.
    - `fixed`: known parameters, `{name: value}` with names among `M (d, d)`, `C (d, d)`,
      `K (d, d)`, `B (d, n)`, `F0 (d,)` (a scalar `M`, `C`, `K` is that times the
      identity, a scalar `B`, `F0` fills every entry); only the rest is fitted. A known
      `M` (symmetric positive definite, kg) sets the force scale: every parameter is then
      in physical units (C N s/m, K N/m, B N per input unit, F0 N). Without `M` the mass
      is the identity and `C`, `K`, `B`, `F0` (fixed or fitted) are per unit mass, since
      only `M^-1` times them is identifiable.

    **Returns:** the fitted `LinearSecondOrder`, its `M` the fixed one or the identity.
    Raises a one-line `DataError` for a bad `fixed` (unknown key, wrong shape, non-finite
    entry, an `M` not symmetric positive definite) or an unstable fit that clipping cannot
    repair.
    """
    from dtwin_jax.data import check_records

    if d < 1:
        raise DataError(f"d must be a positive number of degrees of freedom, got {d}")
    t = np.asarray(t, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64)
    u = np.asarray(u, dtype=np.float64)
    n = u.shape[-1]
    fixed = _check_fixed(fixed, d, n)
    M = fixed.get("M", np.eye(d))
    nominal = LinearSecondOrder.create(M, np.zeros((d, d)), np.zeros((d, d)), np.zeros((d, n)))
    x_index = measured_index(x_names, nominal)
    xdot_index = measured_index(xdot_names, nominal, "xdot_names") if xdot is not None else ()
    rec = check_records(t, x, u, xdot)
    if rec.x.shape[-1] != len(x_index):
        raise DataError(f"'x' has {rec.x.shape[-1]} columns but x_names names {len(x_index)}")
    interpolation, _ = resolve_interpolation(interpolation, rec.u)
    args = (rec, x_index, xdot_index, d, n, M)
    nominal = _fit_rounds(*args, fixed, nominal, interpolation, max_iterations, rtol)
    for _ in range(3):  # clip K and C, then again if the refit exposes the other one
        C, K = np.asarray(nominal.C), np.asarray(nominal.K)
        worst, tol = _max_real_part(M, C, K)
        if worst <= tol:
            return nominal
        clip = {k: _psd_part(v) for k, v in (("K", K), ("C", C)) if k not in fixed}
        clip = {k: v for k, v in clip.items() if not np.allclose(v, (K if k == "K" else C), rtol=1e-12, atol=0)}
        if not clip:
            break
        what = ", ".join(
            f"{k} (smallest eigenvalue {np.min(np.linalg.eigvalsh(0.5 * (a + a.T))):.4g})"
            for k, a in (("K", K), ("C", C)) if k in clip
        )
        warnings.warn(
            f"identify_linear: the fitted model is unstable (eigenvalue real part {worst:.3g} 1/s); "
            f"clipped {what} to the nearest positive semidefinite matrix and refitted the rest "
            f"(pass fixed={{'K': 0}} for a plant without a spring)",
            stacklevel=2,
        )
        fixed = {**fixed, **clip}
        nominal = _fit_rounds(*args, fixed, nominal, interpolation, max_iterations, rtol)
    worst, _ = _max_real_part(M, np.asarray(nominal.C), np.asarray(nominal.K))
    raise DataError(
        f"identify_linear: the fit is unstable (eigenvalue real part {worst:.3g} 1/s) and clipping the free K, C "
        f"does not repair it; fix the stiffness, e.g. fixed={{'K': 0}}"
    )
