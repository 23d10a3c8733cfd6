"""States from accelerometers alone: the most common instrumentation of a structure in service.

With only the accelerations `a` of the degrees of freedom measured (no displacement or
velocity sensor), the states `q, v` must be integrated from `a`; plain double
integration drifts (within seconds of a noisy record the integrated noise exceeds the
displacement). The low frequencies are anchored by the equation of motion instead. Each
degree of freedom is the kinematic chain `dq/dt = v, dv/dt = a` driven by the measured
acceleration (held input and trapezoidal smooth part, as
`dtwin_jax.preprocess.denoise.kinematic_smoother`), and every sample adds the pseudo-measurement

    K q + C v - M h(q, v, u) = B u + F0 - M a          (one row per degree of freedom)

with `h` the perturbation known so far, linearized at the previous states (a Rauch-Tung-
Striebel smoother with a measurement matrix per sample). While `h` is still being found, the
anchor's noise is raised so that it takes over only below the lowest natural frequency over
`CROSSOVER`; once the loop settles, the anchor keeps the accelerometers' own noise.

The loop (`accelerometer_states`) starts from the equivalent linear model (the nominal
plus the linear correction that fits the accelerations best, found without any state
estimate), then alternates a short sampler run on the weak-form statistics at the states
(`dtwin_jax.preprocess.weak_form_accelerometers`: the nominal part of every row exact, whatever the
states) with a Gauss-Newton step of the smoother. The final regression is that weak form at
the final states; draws of the states' estimation error (Durbin and Koopman's simulation
smoother) put their effect on the selected terms into its row covariance.

Measurements (`benchmarks/zoo.py --layout accelerometers`, against the former plain fixed point
with a high-passed pointwise regression): see the README's sensors table.

Output-only (no force measured) from accelerometers uses the same states with the force white and
unknown (`dtwin_jax.output_only.accelerometers`).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from scipy.linalg import sqrtm

from dtwin_jax.errors import DataError
from dtwin_jax.models.systems import LinearSecondOrder
from dtwin_jax.preprocess.denoise import auto_half_width, noise_std
from dtwin_jax.preprocess.kalman import kalman_filter, rts_smoother

__all__ = ["CROSSOVER", "ERROR_DRAWS", "MAX_FEEDBACK", "accelerometer_layout", "check_accelerometer_layout",
           "sampler_selection", "selected_least_squares", "anchored_smoother", "accelerometer_states",
           "unsettled_warnings", "state_feedback", "widened_draws"]

# The anchor and the integrated accelerations cross over at the lowest natural frequency over
# this factor. Example 1 (2 s, 3% noise), cubic coefficient with the true perturbation in the
# anchor: 0.2% off at 2, 0.7% at 4, 2-5% at 6 (the integrated noise grows as the cube of it).
CROSSOVER = 2.0
# Gauss-Newton steps of the anchor's loop: the most, and the relative change of the states
# that ends a phase (with the crossover, then without). Along a direction the data cannot fix
# the loop converges slowly (zoo-0018: by 0.8 a step); 0.1% of the states' spread is well below
# their error (1-5%), and the feedback's widening (state_feedback) covers what is left.
MAX_ITERATIONS = 20
TOLERANCE = 1e-3
# Draws of the final states' estimation error: their effect on the selected terms enters the
# regression's row covariance (errors in variables).
ERROR_DRAWS = 16
# The loop's feedback (:func:`state_feedback`): T' is scaled to this spectral radius at most,
# so that a direction the data cannot fix widens its terms 10 times, not without bound.
MAX_FEEDBACK = 0.99


def check_accelerometer_layout(nominal: LinearSecondOrder, xdot_index) -> None:
    """Refuse, in one line, an accelerometer-only layout whose states cannot be estimated.

    Raises a `DataError` when a degree of freedom has no accelerometer (the rate of its
    velocity state), when the model has extra states (nothing measures them), or when `K` is
    not positive definite (a free-floating mode has no quasi-static anchor).

    **Arguments:**

    - `nominal`: the nominal model (`d` degrees of freedom, `E` extra states).
    - `xdot_index`: indices of the measured rates (`xdot_names`) into the `m` states.
    """
    names = nominal.state_names
    missing = [names[i] for i in nominal.velocity_index if i not in tuple(xdot_index)]
    if missing:
        raise DataError(
            "accelerometers alone need the acceleration of every degree of freedom: missing 'xdot' of "
            + ", ".join(missing))
    if nominal.extra_states:
        extra = [names[i] for i in range(2 * nominal.d, nominal.m)]
        raise DataError(f"accelerometers alone cannot estimate the extra states {extra}: measure them ('x')")
    K = np.asarray(nominal.K)
    if np.min(np.linalg.eigvalsh(0.5 * (K + K.T))) <= 0:
        raise DataError("accelerometers alone need a positive definite nominal stiffness K to anchor the "
                        "displacements: measure a displacement ('x')")


def accelerometer_layout(nominal: LinearSecondOrder, xdot, xdot_names, u, refine: bool = False) -> tuple:
    """Check a layout without `x` and stand an empty `x` in for it.

    **Arguments:**

    - `nominal`: the nominal model.
    - `xdot`: `(N, s)` or `(R, N, s)` measured rates, or None.
    - `xdot_names`: their states, or None (all `m`).
    - `u`: the measured inputs, or None (output-only); the checks do not use them.
    - `refine`: whether an output-error refinement is asked for (it fits measured states).

    **Returns:** `(x, x_names)`: an empty `x` of shape `(..., N, 0)` and the empty list of its
    names. Raises a one-line `DataError` naming the missing measurement (see
    `check_accelerometer_layout`).
    """
    from dtwin_jax.models.systems import real_array
    from dtwin_jax.preprocess.estimate import measured_index

    if xdot is None:
        raise DataError("no measurement of the states: give 'x' (states) or 'xdot' (accelerations)")
    if refine:
        raise DataError("refine (output error) needs measured states 'x'; accelerometers alone have none")
    check_accelerometer_layout(nominal, measured_index(xdot_names, nominal, "xdot_names"))
    xdot = real_array("'xdot'", xdot)
    return np.zeros(xdot.shape[:-1] + (0,)), []


def _drive(nominal: LinearSecondOrder, a, u):
    """The kinematic chains' known input per step `(R, N-1, 2d)`: the double and single
    integrals over the step of `a (R, N, d)`, its input part held (`u (R, N, n)`, or None)
    and its smooth part trapezoidal (as `dtwin_jax.preprocess.denoise.kinematic_smoother`)."""
    held = np.zeros_like(a) if u is None else np.linalg.solve(np.asarray(nominal.M), np.asarray(nominal.B) @ np.moveaxis(u, -1, -2)).swapaxes(-1, -2)
    smooth = a - held
    s0, s1, h = smooth[:, :-1], smooth[:, 1:], held[:, :-1]
    return np.concatenate([h / 2 + (2 * s0 + s1) / 6, h + 0.5 * (s0 + s1)], axis=-1), smooth


@jax.jit
def _smooth(F, c, Q, H, z, r, m0, P0):
    """RTS smoothed means `(R, N, S)` of records `z (R, N, p)` with drives `c (R, N-1, S)`
    and measurement matrices `H (R, N, p, S)`."""
    def one(cc, hh, zz, mm):
        return rts_smoother(kalman_filter(F, cc, Q, hh, None, r, zz, mm, P0), F)[0]

    return jax.vmap(one)(c, H, z, m0)


def _error_draws(F, Q, H, r, P0, num: int, seed: int) -> np.ndarray:
    """`num` draws `(num, R, N, S)` of the smoother's estimation error (Durbin and Koopman's
    simulation smoother): states and measurements simulated from the model, minus what the
    smoother makes of those measurements."""
    R, N, p, S = H.shape
    rng = np.random.default_rng(seed)
    lam, V = np.linalg.eigh(Q)
    Q_half = V * np.sqrt(np.maximum(lam, 0.0))
    x0 = rng.standard_normal((num * R, S)) @ np.linalg.cholesky(P0).T
    w = rng.standard_normal((num * R, N - 1, S)) @ Q_half.T
    # The kinematic chain F = [[I, dt I], [0, I]] in closed form: v_k = v_0 + sum of the
    # velocity noise before k, q_k = q_0 + sum of dt v_j + the displacement noise before k.
    d, dt = S // 2, F[0, S // 2]
    zero = np.zeros((num * R, 1, d))
    v = x0[:, None, d:] + np.concatenate([zero, np.cumsum(w[..., d:], axis=1)], axis=1)
    q = x0[:, None, :d] + np.concatenate([zero, np.cumsum(dt * v[:, :-1] + w[..., :d], axis=1)], axis=1)
    x = np.concatenate([q, v], axis=-1)
    Hs = np.tile(H, (num, 1, 1, 1))
    z = np.einsum("bnps,bns->bnp", Hs, x) + rng.standard_normal((num * R, N, p)) * np.sqrt(r)
    est = _smooth(*(jnp.asarray(v) for v in (F, np.zeros((num * R, N - 1, S)), Q, Hs, z, r, np.zeros((num * R, S)), P0)))
    return (x - np.asarray(est)).reshape(num, R, N, S)


def anchored_smoother(nominal: LinearSecondOrder, dt: float, a, u=None, anchor=None, jacobian=None, *,
                      crossover: float | None = CROSSOVER, force_variance=None, error_draws: int = 0,
                      seed: int = 0, acceleration_noise_std=None) -> tuple[np.ndarray, dict]:
    """Displacements and velocities from measured accelerations, anchored by the equation of motion.

    **Arguments:**

    - `nominal`: the nominal model, `d` degrees of freedom, `K` positive definite.
    - `dt`: sample step, s.
    - `a`: `(R, N, d)` measured accelerations of the degrees of freedom, m/s^2 (state units / s^2).
    - `u`: `(R, N, n)` measured inputs, held over each step, or None (output-only: the force
      is unknown and white).
    - `anchor`: `(R, N, d)` known force added to the anchor's right-hand side (force
      units): the perturbation `M h(x)` known so far, or its linearization's constant part.
    - `jacobian`: `(R, N, d, 2d)`, the perturbation's force `M dh/dx` at a previous
      estimate (a Gauss-Newton step: the anchor then reads `[K C] x - M dh/dx x`), or None.
    - `crossover`: the anchor's noise is raised so that it takes over only below the lowest
      natural frequency over this (a perturbation not yet known cannot bias the states above
      it); None: its noise is the accelerometers' alone (the perturbation is known).
    - `force_variance`: `(d,)` variance per sample of the unmeasured force's error in the
      anchor (force units^2), added to its noise; None: zero.
    - `error_draws`: also return this many draws `S` of the estimation error, `(S, R, N, 2d)`
      (`info["error_draws"]`); 0 (default): none.
    - `seed`: the seed of the error draws.
    - `acceleration_noise_std`: `(d,)` the accelerometers' noise std, or None (the
      Savitzky-Golay residual of the accelerations' smooth part).

    **Returns:** `(x, info)`: the smoothed `[q, v]`, `(R, N, 2d)`, and a dict of the
    acceleration noise std `(d,)` and the anchor's noise std `(d,)` used (and the error
    draws, when asked for)."""
    a = np.asarray(a, dtype=np.float64)
    R, N, d = a.shape
    M, C, K = (np.asarray(getattr(nominal, k), dtype=np.float64) for k in ("M", "C", "K"))
    w_min = float(np.sqrt(np.min(np.real(np.linalg.eigvals(np.linalg.solve(M, K))))))
    drive, smooth = _drive(nominal, a, u)
    hw = auto_half_width(nominal, dt, N)
    # White noise on the smooth part: the sensor's, and the input's through M^-1 B.
    sig_a = (np.sqrt(np.mean(np.asarray(noise_std(jnp.asarray(smooth), hw)) ** 2, axis=0))
             if acceleration_noise_std is None else np.asarray(acceleration_noise_std, dtype=np.float64))
    z = -a @ M.T + np.asarray(nominal.F0)
    if u is not None:
        z = z + np.asarray(u) @ np.asarray(nominal.B).T
    if anchor is not None:
        z = z + anchor
    # The accelerations' own noise enters the anchor through M a; with a crossover, the
    # anchor's displacement error r / K^2 meets the integrated noise sig_a^2 / w^4 there.
    r = (np.diag(M) * sig_a) ** 2
    if crossover is not None:
        r = r + (np.diag(K) * sig_a / (w_min / crossover) ** 2) ** 2
    if force_variance is not None:
        r = r + np.asarray(force_variance)
    r = np.maximum(r, 1e-300)
    I = np.eye(d)
    F = np.block([[I, dt * I], [0 * I, I]])
    c = np.concatenate([dt**2 * drive[..., :d], dt * drive[..., d:]], axis=-1)
    Q = np.zeros((2 * d, 2 * d))
    q_unit = np.array([[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt**2]])
    for j in range(d):  # the trapezoid averages two noisy samples
        Q[np.ix_([j, d + j], [j, d + j])] = sig_a[j] ** 2 / 2 * q_unit
    H = np.broadcast_to(np.concatenate([K, C], axis=1), (R, N, d, 2 * d))
    if jacobian is not None:
        H = H - np.asarray(jacobian)
    # A diffuse prior at the scale of the quasi-static displacement and its velocity.
    q_var = np.var(np.linalg.solve(K, z.reshape(-1, d).T), axis=1) + 1e-300
    P0 = np.diag(1e4 * np.concatenate([q_var, q_var * np.diag(K) / np.diag(M)]))
    m0 = np.zeros((R, 2 * d))
    s = _smooth(*(jnp.asarray(v) for v in (F, c, Q, H, z, r, m0, P0)))
    info = {"acceleration_noise_std": sig_a.tolist(), "anchor_noise_std": np.sqrt(r).tolist()}
    if error_draws:
        info["error_draws"] = _error_draws(F, Q, np.asarray(H), r, P0, error_draws, seed)
    return np.asarray(s), info


@functools.partial(jax.jit, static_argnums=(0,))
def _force_and_jacobian(lib, M, coef, x, u):
    """`M h(x)` and its Jacobian per sample, `x (N, m)`, `u (N, n)`: one program per library
    (the coefficients are arguments, not constants folded into a new program each step)."""
    def force(xx, uu):
        return M @ (coef @ lib(xx[None], uu[None])[0])

    return jax.vmap(lambda xx, uu: (force(xx, uu), jax.jacfwd(force)(xx, uu)))(x, u)


def _linearized(nominal: LinearSecondOrder, lib, coef, x, u) -> tuple[np.ndarray, np.ndarray]:
    """The perturbation's force `M h(x) (R, N, d)` under coefficients `coef (q, K)` and its
    Jacobian in the states `(R, N, d, m)`."""
    R, N, m = x.shape
    value, jac = _force_and_jacobian(lib, jnp.asarray(nominal.M), jnp.asarray(coef), jnp.asarray(x.reshape(-1, m)),
                                     jnp.asarray(np.reshape(u, (R * N, -1))))
    return np.asarray(value).reshape(R, N, -1), np.asarray(jac).reshape(R, N, -1, m)


def accelerometer_states(nominal: LinearSecondOrder, dt: float, xdot, xdot_index, u, lib, select, *,
                         crossover: float = CROSSOVER, max_iterations: int = MAX_ITERATIONS,
                         interpolation: str = "held", error_draws: int = ERROR_DRAWS,
                         seed: int = 0, force_variance=None, acceleration_noise_std=None,
                         refit=None) -> tuple[np.ndarray, np.ndarray, dict]:
    """Every state and rate from accelerometers and the force, the twin in the anchor's loop.

    The first states come from the anchor of the equivalent linear model (the nominal plus
    the linear correction that best fits the accelerations, `equivalent_linear`; the
    nominal when that is not stable): a hardening spring larger than the nominal stiffness
    would otherwise pull them well off. Then, in turn, a short sampler run on the weak-form
    statistics at the states selects terms (`select`), and the anchored smoother runs
    again with their force linearized at the states (Gauss-Newton: a cubic stiffer than the
    nominal made the plain fixed point diverge). Once two selections in a row agree, the
    support stays and its coefficients come from least squares on the weak rows. Once this
    settles with the crossover, it goes on with the anchor at the accelerometers' own noise.

    **Arguments:**

    - `nominal`: the nominal model (checked by `check_accelerometer_layout`).
    - `dt`: sample step, s.
    - `xdot`: `(R, N, s)` measured rates of the states `xdot_index`; those of the velocity
      states are the accelerations (m/s^2).
    - `xdot_index`: indices of the measured rates' states into the `m` states (every velocity
      state among them).
    - `u`: `(R, N, n)` measured inputs.
    - `lib`: the library whose selected terms form `h`.
    - `select`: `select(x (R, N, m)) -> (q, K)` coefficients of the perturbation at these
      states (`sampler_selection`).
    - `crossover`: of the first phase (`anchored_smoother`).
    - `max_iterations`: most Gauss-Newton steps.
    - `interpolation`: the inputs' (`"held"` or `"bandlimited"`).
    - `error_draws`: draws of the final states' estimation error, for the errors in
      variables of the regression (0: none).
    - `seed`: the seed of those draws.
    - `force_variance`: `(d,)` variance per sample of an unmeasured force in the anchor
      (`anchored_smoother`), or None.
    - `acceleration_noise_std`: `(d,)` the accelerometers' noise std, or None (estimated).
    - `refit`: `refit(x, index) -> (P,)` the settled support's coefficients at states
      `x`, `index` a list of `(equation, column)`; None: generalized least squares on
      the weak rows (output-only passes its own rows' fit).

    **Returns:** `(x, rates, info)`: the estimated states `(R, N, m)`; their rates `(R, N, m)`,
    whose velocity rows are the measured accelerations and whose displacement rows are the
    estimated velocities (or the measured ones); and a dict saying how (method, iterations,
    the terms in the anchor, whether the states converged, noise levels;
    `info["error_draws"] (S, R, N, m)` and `info["coefficients"] (q, K)` for
    `dtwin_jax.preprocess.weak_form_accelerometers.accelerometer_weak_stats`)."""
    from dtwin_jax.preprocess.weak_form_accelerometers import equivalent_linear

    d = nominal.d
    xdot = np.asarray(xdot, dtype=np.float64)
    xdot_index = tuple(xdot_index)
    vel = list(nominal.velocity_index)
    a = xdot[..., [xdot_index.index(i) for i in vel]]
    uu = np.asarray(u, dtype=np.float64)

    def rates_of(x):
        rates = np.concatenate([x[..., d:2 * d], a], axis=-1)
        for col, i in enumerate(xdot_index):  # measured velocities (rates of displacements) kept
            if i < d:
                rates[..., i] = xdot[..., col]
        return rates

    M = np.asarray(nominal.M)
    delta = equivalent_linear(nominal, dt, a, uu, interpolation)
    K_eq = np.asarray(nominal.K) - M @ delta[:, :d]
    stable = bool(np.min(np.real(np.linalg.eigvals(np.linalg.solve(M, K_eq)))) > 0)
    start = (LinearSecondOrder.create(M, np.asarray(nominal.C) - M @ delta[:, d:], K_eq, nominal.B, F0=nominal.F0)
             if stable else nominal)
    x, info = anchored_smoother(start, dt, a, uu, crossover=crossover, force_variance=force_variance, acceleration_noise_std=acceleration_noise_std)
    phase, steps, coef, diverged, change = crossover, 0, None, False, np.inf
    settled = 0  # selections in a row with the same support
    for steps in range(1, max_iterations + 1):
        if settled < 2:
            new_coef = np.asarray(select(x))
            settled = settled + 1 if coef is not None and np.array_equal(new_coef != 0, coef != 0) else 1
            coef = new_coef
        else:  # the support has settled: its coefficients by least squares, no sampler run
            index = [(e, int(k)) for e in range(coef.shape[0]) for k in np.flatnonzero(coef[e])]
            coef = np.zeros_like(coef)
            values = (_selected_fit(nominal, lib, dt, a, uu, x, index, interpolation) if refit is None
                      else refit(x, index))
            for (e, k), v in zip(index, values):
                coef[e, k] = v
        force, jac = _linearized(nominal, lib, coef, x, uu)
        anchor = force - np.einsum("rnij,rnj->rni", jac, x)
        new, new_info = anchored_smoother(nominal, dt, a, uu, anchor, jac, crossover=phase,
                                          force_variance=force_variance, acceleration_noise_std=acceleration_noise_std)
        if not np.all(np.isfinite(new)) or np.any(np.std(new, axis=(0, 1)) > 3 * np.std(x, axis=(0, 1))):
            diverged = True  # a wild selection's linearization: keep the last states
            break
        change = np.max(np.std(new - x, axis=(0, 1)) / np.maximum(np.std(new, axis=(0, 1)), 1e-300))
        x, info = new, new_info
        if change < TOLERANCE:
            if phase is None:
                break
            phase = None
    if coef is not None and error_draws:
        force, jac = _linearized(nominal, lib, coef, x, uu)
        x, info = anchored_smoother(nominal, dt, a, uu, force - np.einsum("rnij,rnj->rni", jac, x), jac,
                                    crossover=phase, error_draws=error_draws, seed=seed,
                                    force_variance=force_variance, acceleration_noise_std=acceleration_noise_std)
    reg = list(nominal.regressed_index)
    selected = np.zeros((len(reg), lib.K), bool) if coef is None else coef != 0
    names = list(lib.names)
    info = {
        "method": "anchored kinematic RTS (integrated accelerations, and the equation of motion with "
                  "the discovered perturbation linearized at the states)",
        "start": "equivalent linear model" if stable else "nominal model",
        "crossover_ratio": crossover,
        "crossover_released": phase is None,
        "stopped_diverging": diverged,
        # The states stopped moving (the last step's change below the tolerance, in either phase).
        "converged": bool(not diverged and change < TOLERANCE),
        "last_change": float(change) if np.isfinite(change) else None,
        "anchor_iterations": int(steps),
        "anchor_terms": {nominal.state_names[i]: [names[k] for k in np.flatnonzero(selected[j])]
                         for j, i in enumerate(reg)},
        "coefficients": None if coef is None else coef,
        **info,
    }
    return x, rates_of(x), info


def unsettled_warnings(info: dict) -> list[str]:
    """A warning when `accelerometer_states` ran out of iterations before its first
    phase (the anchor below the crossover) settled: the states then follow a selection that
    keeps changing, and the terms regressed on them are not to be trusted, however sharp
    their intervals. A loop that ends unconverged in its second phase is not warned about:
    with a Coulomb term the states move by a fraction of a percent a step for ever, and the
    terms hold (the zoo's measurements: the documentation's Which sensors page).

    **Arguments:**

    - `info`: the states' `info` dict of `accelerometer_states`.

    **Returns:** a list of zero or one warning lines."""
    if info.get("crossover_released", True):
        return []
    terms = sum(len(v) for v in info.get("anchor_terms", {}).values())
    return [f"the states estimated from the accelerometers did not settle ({info['anchor_iterations']} iterations of "
            f"the anchor, {terms} terms in it at the end): the selected terms and their intervals are unreliable; "
            "longer or more records, a smaller library or a displacement sensor would help"]


def sampler_selection(nominal: LinearSecondOrder, dt: float, a, lib, u, settings, seed: int,
                      interpolation: str = "held"):
    """The `select` of `accelerometer_states`: coefficients from a short sampler run.

    `select(x)` returns the coefficients of the terms with inclusion probability above 1/2
    (the posterior mean with zeros counted spreads weight over a large library's look-alikes,
    `x1**6` and the like, whose linearization threw the loop off) in a short sampler run
    (`dtwin_jax.output_only.stats.first_pass_settings`) on the weak-form statistics of the
    accelerations and inputs at states `x (R, N, m)`.

    **Arguments:**

    - `nominal`: the nominal model.
    - `dt`: sample step, s.
    - `a`: `(R, N, d)` measured accelerations.
    - `lib`: the library.
    - `u`: `(R, N, n)` measured inputs.
    - `settings`: the update's `SamplerSettings` (shortened by `first_pass_settings`).
    - `seed`: the sampler's seed.
    - `interpolation`: the inputs' (`"held"` or `"bandlimited"`).

    **Returns:** the function `select(x (R, N, m)) -> (q, K)`, the selected coefficients of the
    `q` regressed equations on the library's `K` columns (zero off the selection)."""
    from dtwin_jax.output_only.stats import first_pass_settings
    from dtwin_jax.preprocess.weak_form_accelerometers import accelerometer_weak_stats
    from dtwin_jax.update.sampling import posteriors, sample_equations

    names = [nominal.state_names[i] for i in nominal.regressed_index]

    def select(x):
        stats, _ = accelerometer_weak_stats(nominal, lib, dt, a, u, x, interpolation=interpolation)
        trace = sample_equations(stats, first_pass_settings(settings), seed, False)
        return np.stack([e.coefficients for e in posteriors(trace, names, "drift", lib.names, 0.5)])

    return select


def _selected_fit(nominal, lib, dt, a, u, x, index, interpolation) -> np.ndarray:
    """Generalized least squares of the selected terms `index [(equation, column)]` on the
    weak rows at states `x`, stacked in `index` order."""
    from dtwin_jax.preprocess.weak_form_accelerometers import accelerometer_weak_stats

    stats, _ = accelerometer_weak_stats(nominal, lib, dt, a, u, x, interpolation=interpolation, equation_error=False)
    return selected_least_squares(stats, index)


def selected_least_squares(stats, index) -> np.ndarray:
    """Least squares of the selected terms from batched statistics.

    **Arguments:**

    - `stats`: `dtwin_jax.sampler.SuffStats` batched over the equations (`gram (q, K, K)`,
      `xty (q, K)`).
    - `index`: the terms, a list of `(equation, column)`.

    **Returns:** the coefficients `(P,)`, in `index` order (each equation's terms fitted
    together)."""
    gram, xty = np.asarray(stats.gram), np.asarray(stats.xty)
    out = np.zeros(len(index))
    for e in sorted({e for e, _ in index}):
        rows = [j for j, (ee, _) in enumerate(index) if ee == e]
        ks = [index[j][1] for j in rows]
        out[rows] = np.linalg.lstsq(gram[e][np.ix_(ks, ks)], xty[e][ks], rcond=None)[0]
    return out


def state_feedback(nominal: LinearSecondOrder, lib, dt: float, a, u, x, coef, error_draws, *,
                   interpolation: str = "held", steps: int = 3, max_gain: float = MAX_FEEDBACK) -> dict:
    """How much the anchor's loop feeds the coefficients back into themselves, and the states'
    own uncertainty: the widening of the selected terms' posterior.

    The loop's estimate is a fixed point `theta = T(theta)`: the regression on the states
    that the anchor with `theta` gives. Where the states follow the anchor, a change of
    `theta` comes back nearly unchanged (`T'` has an eigenvalue near 1: a two-storey
    shear frame's cubic coupling, whose common-mode drift accelerometers do not fix), and the
    data cannot tell those coefficients apart although each regression on fixed states is
    sharp (zoo-0018: the coefficient off by many times its posterior std). By the delta method, the
    fixed point's error is `(I - T')^-1` times the regression's own, which is the sampler's
    spread plus that of the fit over draws of the states' estimation error.

    **Arguments:**

    - `nominal`: the nominal model, as in `accelerometer_states`.
    - `lib`: the library, as in `accelerometer_states`.
    - `dt`: sample step, s.
    - `a`: `(R, N, d)` measured accelerations.
    - `u`: `(R, N, n)` measured inputs.
    - `x`: `(R, N, m)` the loop's final states.
    - `coef`: `(q, K)` the loop's final coefficients (nonzero: the selected terms).
    - `error_draws`: `(S, R, N, m)` draws of the states' estimation error.
    - `interpolation`: the inputs' (`"held"` or `"bandlimited"`).
    - `steps`: Gauss-Newton steps of the anchor per evaluation of `T`.
    - `max_gain`: `T'` is scaled to at most this spectral radius (a neutral direction then
      widens `(1 - max_gain)^-1/2` times); `T'` with a spectral radius beyond 1 is not used
      (nothing widened).

    **Returns:** a dict: `"index"`, the selected terms `[(equation, column)]` (`P` of them);
    `"gain"`, `(I - T')^-1/2`, `(P, P)`; `"extra"`, the `(P, P)` covariance of the fit over
    the error draws; `"eigenvalues"`, the moduli of the eigenvalues of `T'`, largest first.
    An empty index when nothing is selected."""
    coef = np.asarray(coef)
    index = [(e, int(k)) for e in range(coef.shape[0]) for k in np.flatnonzero(coef[e])]
    if not index:
        return {"index": [], "gain": np.zeros((0, 0)), "extra": np.zeros((0, 0)), "eigenvalues": []}
    theta0 = np.array([coef[e, k] for e, k in index])

    def T(theta):
        cf = np.zeros_like(coef)
        for (e, k), v in zip(index, theta):
            cf[e, k] = v
        xs = x
        for _ in range(steps):
            force, jac = _linearized(nominal, lib, cf, xs, u)
            xs, _ = anchored_smoother(nominal, dt, a, u, force - np.einsum("rnij,rnj->rni", jac, xs), jac, crossover=None)
        return _selected_fit(nominal, lib, dt, a, u, xs, index, interpolation)

    base = T(theta0)
    P = len(index)
    Tp = np.zeros((P, P))
    for j in range(P):
        step = 1e-3 * abs(theta0[j])
        moved = theta0.copy()
        moved[j] += step
        Tp[:, j] = (T(moved) - base) / step
    lam = np.linalg.eigvals(Tp)
    radius = float(np.max(np.abs(lam)))
    # Beyond 1 the loop cannot have settled there: the linearization does not hold (a sign()
    # term's regression jumps with each velocity reversal; zoo-0024 measured 1.79 with the
    # coefficient 0.4% off), and nothing is widened. Below, T' is scaled to at most max_gain.
    inverse = np.eye(P) if radius > 1.0 else np.linalg.inv(np.eye(P) - Tp * min(1.0, max_gain / max(radius, 1e-300)))
    # The fixed point's covariance is the regression's times (I - T')^-1 (Meng and Rubin's
    # SEM for a self-consistent estimate): draws are moved by its square root.
    gain = np.real(sqrtm(inverse))
    fits = np.array([_selected_fit(nominal, lib, dt, a, u, x + draw, index, interpolation) for draw in error_draws])
    extra = np.atleast_2d(np.cov(fits.T)) if len(fits) > 1 else np.zeros((P, P))
    return {"index": index, "gain": gain, "extra": extra, "eigenvalues": sorted(np.abs(lam).tolist(), reverse=True)}


def widened_draws(theta, gamma, feedback: dict, seed: int = 0) -> np.ndarray:
    """The selected terms' draws widened by `state_feedback`.

    Each draw becomes `mean + G (theta - mean + e)` with `G = (I - T')^-1/2` and `e` Gaussian
    with the error draws' covariance; each term's mean is over the draws that include it, and
    a draw that excludes a term keeps it at zero.

    **Arguments:**

    - `theta`: `(q, chains, draws, K)` the sampler's coefficient draws.
    - `gamma`: `(q, chains, draws, K)` the inclusion indicators of those draws.
    - `feedback`: the dict of `state_feedback`.
    - `seed`: the seed of the Gaussian `e`.

    **Returns:** the widened draws, a new `theta` `(q, chains, draws, K)` (a copy; unchanged
    when nothing is selected)."""
    index = feedback["index"]
    theta = np.array(theta, dtype=np.float64, copy=True)
    if not index:
        return theta
    gamma = np.asarray(gamma).astype(bool)
    cols = np.stack([theta[e, ..., k] for e, k in index], axis=-1)  # (chains, draws, P)
    inc = np.stack([gamma[e, ..., k] for e, k in index], axis=-1)
    mean = np.array([cols[..., j][inc[..., j]].mean() if inc[..., j].any() else 0.0 for j in range(len(index))])
    extra = feedback["extra"]
    chol = np.linalg.cholesky(extra + 1e-12 * np.max(np.abs(np.diag(extra)), initial=1e-300) * np.eye(len(index)))
    noise = np.random.default_rng(seed).standard_normal(cols.shape) @ chol.T
    new = mean + (np.where(inc, cols - mean, 0.0) + noise) @ feedback["gain"].T
    for j, (e, k) in enumerate(index):
        theta[e, ..., k] = np.where(inc[..., j], new[..., j], 0.0)
    return theta
