"""States from accelerometers alone: the most common instrumentation of a structure in service.

With only the accelerations ``a`` of the degrees of freedom measured (no displacement or
velocity sensor), the states ``q, v`` must be integrated from ``a``; plain double
integration drifts (2 s at 1 kHz and 5% noise: the integrated noise exceeds the
displacement). The low frequencies are anchored by the equation of motion instead. Each
degree of freedom is the kinematic chain ``dq/dt = v, dv/dt = a`` driven by the measured
acceleration (held input and trapezoidal smooth part, as
:func:`dtwin_jax.denoise.kinematic_smoother`), and every sample adds the quasi-static
pseudo-measurement

    K q + C v = B u + F0 - M a + M h(q, v, u)          (one row per degree of freedom)

with ``h`` the perturbation known so far (zero at first). Its variance is set so that the two
cross over at ``CROSSOVER`` times below the lowest nominal natural frequency: above it the
states are the integrated accelerations, below it the anchor (a Rauch-Tung-Striebel smoother
does the split optimally for that noise model, and handles the record's ends).

The anchor is only as right as ``h``: with ``h = 0`` it pulls the states toward the nominal
model (example 1, 2 s, 3% noise: displacement 4-5% off, the cubic 10-30% low and a dozen
spurious terms selected). So the discovered twin goes into the loop: a short sampler run on
the states selects terms and their coefficients, their ``h`` along the trajectory enters the
anchor, the smoother runs again, and so on (a relaxed fixed-point iteration: undamped, the
estimate oscillates about the fixed point with a ratio near -1/2). The short runs regress
high-passed targets and library (:func:`high_pass`): the states' errors lie below the
crossover, and there they would call for spurious terms. With the true ``h`` in the anchor
the cubic of example 1 comes out within 0.5% of the states-known fit; with the loop, within
0.2% (3 seeds, exact support).

The regression target stays the *measured* acceleration minus the nominal rate at the
estimated states (:func:`dtwin_jax.targets.input_output_targets`): the smoother's model never
replaces the measurement, so it cannot absorb the perturbation. Only the terms selected by
the sampler enter the anchor (a full-library fit would fit any state error and anchor
nothing).

Output-only (no force measured): the unknown white force is part of the pseudo-measurement's
error, with variance ``Gamma M^2 / dt`` per sample; the crossover then falls about
``sqrt(noise level)`` times the natural frequency, a high-pass integration whose cutoff the
data choose.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax.denoise import auto_half_width, noise_std
from dtwin_jax.errors import DataError
from dtwin_jax.kalman import kalman_filter, rts_smoother
from dtwin_jax.systems import LinearSecondOrder

__all__ = ["CROSSOVER", "accelerometer_layout", "check_accelerometer_layout", "sampler_selection", "output_only_refusal", "anchored_smoother", "accelerometer_states"]

# The anchor and the integrated accelerations cross over at the lowest natural frequency over
# this factor. Example 1 (2 s, 3% noise), cubic coefficient with the true perturbation in the
# anchor: 0.2% off at 2, 0.7% at 4, 2-5% at 6 (the integrated noise grows as the cube of it).
CROSSOVER = 2.0
# Fixed-point iteration of the anchor: relaxation (the undamped ratio is about -1/2, so 2/3
# converges in a few steps), the most steps, and the relative change of the states that ends it.
RELAXATION = 2.0 / 3.0
MAX_ITERATIONS = 12
TOLERANCE = 1e-4


def check_accelerometer_layout(nominal: LinearSecondOrder, xdot_index) -> None:
    """Refuse, in one line, an accelerometer-only layout whose states cannot be estimated.

    **Arguments:**

    - ``nominal``: the nominal model (``d`` degrees of freedom, ``E`` extra states).
    - ``xdot_index``: indices of the measured rates (``xdot_names``).

    **Returns:**

    None. Raises :class:`DataError` when a degree of freedom has no accelerometer (the rate of
    its velocity state), when the model has extra states (nothing measures them), or when
    ``K`` is not positive definite (a free-floating mode has no quasi-static anchor)."""
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
    """Check a layout without ``x`` and stand an empty ``x`` in for it.

    **Arguments:**

    - ``nominal``: the nominal model.
    - ``xdot``: ``(N, s)`` or ``(R, N, s)`` measured rates, or None.
    - ``xdot_names``: their states (None: all ``m``).
    - ``u``: the measured inputs, or None (output-only).
    - ``refine``: whether an output-error refinement is asked for (it fits measured states).

    **Returns:**

    ``(x (..., N, 0), x_names [])``. Raises a one-line :class:`DataError` naming the missing
    measurement (see :func:`check_accelerometer_layout`)."""
    from dtwin_jax.estimate import measured_index
    from dtwin_jax.systems import real_array

    if xdot is None:
        raise DataError("no measurement of the states: give 'x' (states) or 'xdot' (accelerations)")
    if refine:
        raise DataError("refine (output error) needs measured states 'x'; accelerometers alone have none")
    check_accelerometer_layout(nominal, measured_index(xdot_names, nominal, "xdot_names"))
    xdot = real_array("'xdot'", xdot)
    return np.zeros(xdot.shape[:-1] + (0,)), []


def output_only_refusal(nominal: LinearSecondOrder, xdot, xdot_names) -> None:
    """Refuse output-only data with measured rates, in one line naming what is missing.

    **Arguments:**

    - ``nominal``: the nominal model.
    - ``xdot``: the measured rates, or None.
    - ``xdot_names``: their states (None: all ``m``).

    **Returns:**

    Never; raises :class:`DataError`. With nothing measured, or a degree of freedom without an
    accelerometer, it names the missing ``xdot``. Otherwise (accelerometers alone, ambient
    vibration): the drift could be anchored without the force (its white part is the
    anchor's noise), but the diffusion cannot be told from the accelerometers' own white
    noise by this update yet, so it asks for the states ``x`` or the force ``u``."""
    from dtwin_jax.estimate import measured_index

    if xdot is None:
        raise DataError("no measurement of the states: output-only needs 'x' (states)")
    check_accelerometer_layout(nominal, measured_index(xdot_names, nominal, "xdot_names"))
    raise DataError("output-only from accelerometers alone is not supported yet: the diffusion needs the states "
                    "'x' (or measure the force 'u' and update input-output)")


def _drive(nominal: LinearSecondOrder, a, u):
    """The kinematic chains' known input per step ``(R, N-1, 2d)``: the double and single
    integrals over the step of ``a (R, N, d)``, its input part held (``u (R, N, n)``, or None)
    and its smooth part trapezoidal (as :func:`dtwin_jax.denoise.kinematic_smoother`)."""
    held = np.zeros_like(a) if u is None else np.linalg.solve(np.asarray(nominal.M), np.asarray(nominal.B) @ np.moveaxis(u, -1, -2)).swapaxes(-1, -2)
    smooth = a - held
    s0, s1, h = smooth[:, :-1], smooth[:, 1:], held[:, :-1]
    return np.concatenate([h / 2 + (2 * s0 + s1) / 6, h + 0.5 * (s0 + s1)], axis=-1), smooth


@jax.jit
def _smooth(F, c, Q, H, z, r, m0, P0):
    """RTS smoothed means ``(R, N, S)`` of records ``z (R, N, p)`` with drives ``c (R, N-1, S)``."""
    def one(cc, zz, mm):
        return rts_smoother(kalman_filter(F, cc, Q, H, None, r, zz, mm, P0), F)[0]

    return jax.vmap(one)(c, z, m0)


def anchored_smoother(nominal: LinearSecondOrder, dt: float, a, u=None, anchor=None, *,
                      crossover: float = CROSSOVER, force_variance=None) -> tuple[np.ndarray, dict]:
    """Displacements and velocities from measured accelerations, anchored by the equation of motion.

    **Arguments:**

    - ``nominal``: the nominal model, ``d`` degrees of freedom, ``K`` positive definite.
    - ``dt``: sample step, s.
    - ``a``: ``(R, N, d)`` measured accelerations of the degrees of freedom, m/s^2 (state units / s^2).
    - ``u``: ``(R, N, n)`` measured inputs, held over each step, or None (output-only: the force
      is unknown and white).
    - ``anchor``: ``(R, N, d)`` force of the perturbation known so far, ``M h`` (force units), or
      None (zero).
    - ``crossover``: the anchor takes over below the lowest natural frequency over this.
    - ``force_variance``: ``(d,)`` variance per sample of the unmeasured force's error in the
      anchor (force units^2), added to its noise; None: zero.

    **Returns:**

    ``(x (R, N, 2d), info)``: smoothed ``[q, v]`` and a dict of the acceleration noise std
    ``(d,)`` and the anchor's noise std ``(d,)`` used."""
    a = np.asarray(a, dtype=np.float64)
    R, N, d = a.shape
    M, C, K = (np.asarray(getattr(nominal, k), dtype=np.float64) for k in ("M", "C", "K"))
    w_min = float(np.sqrt(np.min(np.real(np.linalg.eigvals(np.linalg.solve(M, K))))))
    drive, smooth = _drive(nominal, a, u)
    hw = auto_half_width(nominal, dt, N)
    # White noise on the smooth part: the sensor's, and the input's through M^-1 B.
    sig_a = np.sqrt(np.mean(np.asarray(noise_std(jnp.asarray(smooth), hw)) ** 2, axis=0))
    z = -a @ M.T + np.asarray(nominal.F0)
    if u is not None:
        z = z + np.asarray(u) @ np.asarray(nominal.B).T
    if anchor is not None:
        z = z + anchor
    # Crossover where the anchor's displacement error r / K^2 meets the integrated noise
    # sig_a^2 / w^4; the accelerations' own noise enters the anchor through M a.
    w_c = w_min / crossover
    r = (np.diag(K) * sig_a / w_c**2) ** 2 + (np.diag(M) * sig_a) ** 2
    if force_variance is not None:
        r = r + np.asarray(force_variance)
    I = np.eye(d)
    F = np.block([[I, dt * I], [0 * I, I]])
    c = np.concatenate([dt**2 * drive[..., :d], dt * drive[..., d:]], axis=-1)
    Q = np.zeros((2 * d, 2 * d))
    q_unit = np.array([[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt**2]])
    for j in range(d):  # the trapezoid averages two noisy samples
        Q[np.ix_([j, d + j], [j, d + j])] = sig_a[j] ** 2 / 2 * q_unit
    H = np.concatenate([K, C], axis=1)
    # A diffuse prior at the scale of the quasi-static displacement and its velocity.
    q_var = np.var(np.linalg.solve(K, z.reshape(-1, d).T), axis=1) + 1e-300
    P0 = np.diag(1e4 * np.concatenate([q_var, q_var * np.diag(K) / np.diag(M)]))
    m0 = np.zeros((R, 2 * d))
    s = _smooth(*(jnp.asarray(v) for v in (F, c, Q, H, z, np.maximum(r, 1e-300), m0, P0)))
    return np.asarray(s), {"acceleration_noise_std": sig_a.tolist(), "anchor_noise_std": np.sqrt(r).tolist()}


def accelerometer_states(nominal: LinearSecondOrder, dt: float, xdot, xdot_index, u, lib, select, *,
                         crossover: float = CROSSOVER, max_iterations: int = MAX_ITERATIONS,
                         force_variance=None) -> tuple[np.ndarray, np.ndarray, dict]:
    """Every state and rate from accelerometers (and the force), the twin in the anchor's loop.

    **Arguments:**

    - ``nominal``: the nominal model (checked by :func:`check_accelerometer_layout`).
    - ``dt``: sample step, s.
    - ``xdot``: ``(R, N, s)`` measured rates of the states ``xdot_index``; those of the velocity
      states are the accelerations (m/s^2).
    - ``u``: ``(R, N, n)`` measured inputs, or None (output-only).
    - ``lib``: the library whose selected terms form ``h``.
    - ``select``: ``select(x (R, N, m), rates (R, N, m)) -> (q, K)``, the coefficients of the
      terms a short sampler run selects from these states, zero elsewhere
      (:func:`sampler_selection`); called once per fixed-point step, so that a term the first,
      biased states call for can drop out as they improve.
    - ``crossover``, ``force_variance``: as :func:`anchored_smoother`.
    - ``max_iterations``: most fixed-point steps after the first pass.

    **Returns:**

    ``(x (R, N, m), rates (R, N, m), info)``: estimated states; rates whose velocity rows are
    the measured accelerations and whose displacement rows are the estimated velocities (or
    the measured ones); and a dict saying how (method, crossover, iterations, the terms in
    the anchor, noise levels)."""
    d, m = nominal.d, nominal.m
    xdot = np.asarray(xdot, dtype=np.float64)
    xdot_index = tuple(xdot_index)
    vel = list(nominal.velocity_index)
    a = xdot[..., [xdot_index.index(i) for i in vel]]
    uu = None if u is None else np.asarray(u, dtype=np.float64)
    R, N, _ = a.shape
    u_lib = np.zeros((R, N, nominal.n)) if uu is None else uu
    reg = list(nominal.regressed_index)
    Minv_rows = [reg.index(i) for i in vel]

    def rates_of(x):
        rates = np.concatenate([x[..., d:2 * d], a], axis=-1)
        for col, i in enumerate(xdot_index):  # measured velocities (rates of displacements) kept
            if i < d:
                rates[..., i] = xdot[..., col]
        return rates

    def perturbation(x, coef):
        """``M h`` along the trajectory ``x (R, N, m)`` under coefficients ``coef (q, K)``."""
        L = np.asarray(lib(jnp.asarray(x.reshape(-1, m)), jnp.asarray(u_lib.reshape(-1, nominal.n))))
        h = L @ np.asarray(coef)[Minv_rows].T
        return (h @ np.asarray(nominal.M).T).reshape(R, N, d)

    x, info = anchored_smoother(nominal, dt, a, uu, crossover=crossover, force_variance=force_variance)
    rates = rates_of(x)
    anchor = np.zeros((R, N, d))
    steps, coef = 0, None
    for steps in range(1, max_iterations + 1):
        coef = np.asarray(select(x, rates))
        anchor = anchor + RELAXATION * (perturbation(x, coef) - anchor)
        new, info = anchored_smoother(nominal, dt, a, uu, anchor, crossover=crossover, force_variance=force_variance)
        change = np.max(np.std(new - x, axis=(0, 1)) / np.maximum(np.std(new, axis=(0, 1)), 1e-300))
        x, rates = new, rates_of(new)
        if change < TOLERANCE:
            break
    selected = np.zeros((len(reg), lib.K), bool) if coef is None else coef != 0
    names = list(lib.names)
    info = {
        "method": "anchored kinematic RTS (integrated accelerations above the crossover, "
                  "equation of motion with the selected perturbation below)",
        "crossover_ratio": crossover,
        "anchor_iterations": int(steps),
        "anchor_terms": {nominal.state_names[i]: [names[k] for k in np.flatnonzero(selected[j])]
                         for j, i in enumerate(reg)},
        **info,
    }
    return x, rates, info


def sampler_selection(nominal: LinearSecondOrder, dt: float, lib, u, settings, seed: int):
    """The ``select`` of :func:`accelerometer_states`: the terms with inclusion probability
    above 1/2 in a short sampler run (:func:`~dtwin_jax.update.output_only_stats.first_pass_settings`)
    on the statistics of states ``x (R, N, m)`` and rates ``(R, N, m)``; ``u (R, N, n)`` or None."""
    from dtwin_jax.targets import equation_stats, input_output_targets
    from dtwin_jax.update.output_only_stats import first_pass_settings
    from dtwin_jax.update.sampling import _sample_equations, posteriors

    def select(x, rates):
        R, N, m = x.shape
        uf = jnp.zeros((R * N, nominal.n)) if u is None else jnp.asarray(u).reshape(R * N, -1)
        xf = jnp.asarray(x).reshape(R * N, m)
        Y = np.asarray(input_output_targets(nominal, xf, uf, jnp.asarray(rates).reshape(R * N, m))).reshape(R, N, -1)
        L = np.asarray(lib(xf, uf)).reshape(R, N, -1)
        Lf, Yf = (high_pass(nominal, dt, v).reshape(R * N, -1) for v in (L, Y))
        # A constant force only shifts the static displacement, which accelerometers do not
        # see: the constant term (nothing left of it once high-passed) is left out.
        keep = np.flatnonzero(np.std(Lf, axis=0) > 1e-3 * np.std(L.reshape(R * N, -1), axis=0))
        trace = _sample_equations(equation_stats(Lf[:, keep], Yf), first_pass_settings(settings), seed, False)
        names = [nominal.state_names[i] for i in nominal.regressed_index]
        coef = np.zeros((len(names), lib.K))
        coef[:, keep] = np.stack([e.coefficients for e in posteriors(trace, names, "drift", [lib.names[k] for k in keep], 0.5)])
        return coef

    return select


def high_pass(nominal: LinearSecondOrder, dt: float, y, crossover: float = CROSSOVER) -> np.ndarray:
    """``y (R, N, c)`` without what lies below the crossover (the band where the anchored states
    err): a zero-phase 4th-order Butterworth high-pass at the lowest natural frequency over
    ``crossover``, applied to targets and library alike (the regression is unchanged)."""
    from scipy.signal import butter, sosfiltfilt

    M, K = np.asarray(nominal.M), np.asarray(nominal.K)
    f_min = float(np.sqrt(np.min(np.real(np.linalg.eigvals(np.linalg.solve(M, K)))))) / (2 * np.pi)
    sos = butter(4, f_min / crossover, "highpass", fs=1.0 / dt, output="sos")
    return sosfiltfilt(sos, np.asarray(y), axis=1)
