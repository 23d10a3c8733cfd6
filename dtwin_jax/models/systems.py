"""Nominal second-order models, their perturbed versions, and the paper's examples.

State convention: `X = [q_1..q_d, v_1..v_d, e_1..e_E]`, named `x1..xm` with
`m = 2d + E`. The `e` are extra first-order states (e.g. a damage measure) whose
nominal rate is zero. Inputs are named `u1..un`.
"""

from collections.abc import Callable
from typing import NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PyTree

from dtwin_jax._compile.keys import strong_jit
from dtwin_jax.errors import DataError, dtype_word
from dtwin_jax.linalg import mass_solve
from dtwin_jax.resources import check_nominal

__all__ = [
    "LinearSecondOrder",
    "PerturbedSystem",
    "simulate",
    "simulate_checked",
    "fixed_grid",
    "NONSMOOTH_FAMILIES",
    "diffusion_matrix",
    "simulate_sde_checked",
    "simulate_sde",
    "Example",
    "example1",
    "example2",
    "example3",
    "simulate_example",
    "simulate_example_sde",
    "choose_interpolation",
    "resolve_interpolation",
    "high_band_fraction",
    "EXAMPLES",
]


_MAX_GAIN = 1e150  # largest |M^-1 K|, |M^-1 C|, |M^-1 B|, |M^-1 F0| entry: squares stay finite


def real_array(label: str, value) -> np.ndarray:
    """`value` as a float64 array, refusing what a float conversion would silently change.

    Complex numbers (the imaginary part would be dropped), booleans and strings are refused,
    as is a ragged nested list.

    **Arguments:**

    - `label`: what `value` is, named in the one-line error (`"'x'"`, `"nominal M"`).
    - `value`: array-like of real numbers, any shape.

    **Returns:** `value` as a float64 `np.ndarray` of its own shape. Raises a one-line
    `DataError` for anything else.
    """
    try:
        a = np.asarray(value)
    except ValueError as e:  # ragged nested lists
        raise DataError(f"{label} is not a numeric array: {e}") from None
    if a.dtype.kind not in "iuf":
        raise DataError(f"{label} must hold real numbers, got {dtype_word(a.dtype)} values")
    return a.astype(np.float64)


class LinearSecondOrder(eqx.Module):
    """Nominal model `M q'' + C q' + K q = B u + F0` in state-space form.

    `M`, `C`, `K` are `(d, d)`, `B` is `(d, n)`, `F0 (d,)` a constant force (a sensor or
    actuator offset, force units); `extra_states` (`E`) appends first-order states whose
    nominal rate is zero. Use `create` to validate input.
    """

    M: Float[Array, "d d"]
    C: Float[Array, "d d"]
    K: Float[Array, "d d"]
    B: Float[Array, "d n"]
    F0: Float[Array, " d"]
    extra_states: int = eqx.field(static=True, default=0)

    @classmethod
    def create(cls, M, C, K, B=None, extra_states: int = 0, F0=None) -> "LinearSecondOrder":
        """Validate concrete matrices and build the model.

        **Arguments:**

        - `M`: mass matrix `(d, d)`, real, finite, symmetric (to a relative 1e-10) and
          positive definite.
        - `C`: damping matrix `(d, d)`, real and finite.
        - `K`: stiffness matrix `(d, d)`, real and finite.
        - `B`: input matrix `(d, n)`, or `(d,)` for one input, real and finite; None
          (default) for the identity `(d, d)`.
        - `extra_states`: `E`, the number of first-order states appended after the
          velocities (nominal rate zero), a non-negative integer (default 0).
        - `F0`: constant force `(d,)` (force units), real and finite; None (default) for zero.

        **Returns:** the model, with float arrays. Raises a one-line `DataError` for complex,
        boolean or string entries, a wrong shape, a non-finite entry, a nonsymmetric, singular
        or indefinite `M`, or an `M^-1 K`, `M^-1 C`, `M^-1 B`, `M^-1 F0` with an entry beyond
        1e150 (whose square, in the update's Gram matrices, would overflow float64).
        """
        arrays = {}
        for name, value in (("M", M), ("C", C), ("K", K)):
            a = real_array(f"nominal {name}", value)
            if a.ndim != 2 or a.shape[0] != a.shape[1]:
                raise DataError(f"nominal {name} must be a square matrix, got shape {a.shape}")
            arrays[name] = a
        d = arrays["M"].shape[0]
        if d == 0:
            raise DataError("nominal model needs at least one degree of freedom (M is 0x0)")
        for name in ("C", "K"):
            if arrays[name].shape != (d, d):
                raise DataError(
                    f"nominal {name} has shape {arrays[name].shape}, expected ({d}, {d}) like M"
                )
        Bn = np.eye(d) if B is None else real_array("nominal B", B)
        if Bn.ndim == 1:
            Bn = Bn[:, None]
        if Bn.ndim != 2 or Bn.shape[0] != d:
            raise DataError(f"nominal B has shape {Bn.shape}, expected ({d}, n)")
        arrays["B"] = Bn
        F = np.zeros(d) if F0 is None else real_array("nominal F0", F0).reshape(-1)
        if F.shape != (d,):
            raise DataError(f"nominal F0 has {F.size} entries, expected {d} (one per degree of freedom)")
        arrays["F0"] = F
        for name, a in arrays.items():
            if not np.all(np.isfinite(a)):
                raise DataError(f"nominal {name} has non-finite entries")
        if int(extra_states) != extra_states or extra_states < 0:
            raise DataError(f"extra_states must be a non-negative integer, got {extra_states}")
        check_nominal(d, int(extra_states), Bn.shape[1])  # before anything holds m = 2d + E states
        Mn = arrays["M"]
        asym = np.max(np.abs(Mn - Mn.T))
        if asym > 1e-10 * np.max(np.abs(Mn)):  # relative: M may be in any units
            raise DataError(f"nominal mass matrix M is not symmetric (largest |M - M^T| = {asym:.3g})")
        with np.errstate(all="ignore"):
            cond = np.linalg.cond(Mn)
        if not np.isfinite(cond) or cond > 1e12:
            raise DataError(f"nominal mass matrix M is singular (cond={cond:.3g})")
        try:
            L = np.linalg.cholesky(Mn)
        except np.linalg.LinAlgError:
            raise DataError("nominal mass matrix M is not positive definite") from None
        # The rate uses M^-1 times each of these, and the update squares rates (Gram matrices,
        # residual checks): beyond 1e150 those squares overflow float64 and an inf shows up
        # far from its cause. No model in physical units comes near it.
        for name in ("K", "C", "B", "F0"):
            with np.errstate(all="ignore"):
                scaled = np.linalg.solve(L.T, np.linalg.solve(L, arrays[name]))
            if not np.all(np.abs(scaled) <= _MAX_GAIN):
                raise DataError(
                    f"nominal M^-1 {name} has entries beyond 1e150 (float64 overflows): rescale the model's units"
                )
        return cls(*(jnp.asarray(arrays[k]) for k in ("M", "C", "K", "B", "F0")), int(extra_states))

    @property
    def d(self) -> int:
        """Degrees of freedom."""
        return self.M.shape[-1]

    @property
    def n(self) -> int:
        """Number of inputs."""
        return self.B.shape[-1]

    @property
    def m(self) -> int:
        """Number of states, `2d + E`."""
        return 2 * self.d + self.extra_states

    @property
    def state_names(self) -> tuple[str, ...]:
        return tuple(f"x{i + 1}" for i in range(self.m))

    @property
    def input_names(self) -> tuple[str, ...]:
        return tuple(f"u{i + 1}" for i in range(self.n))

    @property
    def velocity_index(self) -> tuple[int, ...]:
        """Indices of the velocity states, `d..2d-1`."""
        return tuple(range(self.d, 2 * self.d))

    @property
    def regressed_index(self) -> tuple[int, ...]:
        """Velocity then extra states: the rows a perturbation is regressed on.

        Kinematic rows `dq/dt = v` are exact, so they are not regressed.
        """
        return tuple(range(self.d, self.m))

    def rate(self, x: Float[Array, " m"], u: Float[Array, " n"]) -> Float[Array, " m"]:
        """Nominal state rate at one sample.

        **Arguments:**

        - `x`: the state `(m,)`, `[q, v, e]`.
        - `u`: the input `(n,)`.

        **Returns:** the rate `(m,)`: `v`, then the accelerations `M^-1 (B u + F0 - C v - K q)`,
        then zero for the extra states.
        """
        d = self.d
        q, v = x[:d], x[d : 2 * d]
        a = mass_solve(self.M, self.B @ u + self.F0 - self.C @ v - self.K @ q)
        return jnp.concatenate([v, a, jnp.zeros(self.extra_states, dtype=x.dtype)])

    def rate_batch(self, x: Float[Array, "N m"], u: Float[Array, "N n"]) -> Float[Array, "N m"]:
        """`rate` over samples.

        **Arguments:**

        - `x`: states `(N, m)`.
        - `u`: inputs `(N, n)`.

        **Returns:** the nominal rates `(N, m)`.
        """
        return jax.vmap(self.rate)(x, u)


class PerturbedSystem(eqx.Module):
    """`dX/dt = f(X, u) + h(X, u)`: a nominal model plus a perturbation rate.

    `perturbation(x (m,), u (n,), params) -> (m,)` is static; `params` is a pytree
    of arrays, so a batch of systems can be built and simulated with `vmap`.
    """

    nominal: LinearSecondOrder
    perturbation: Callable[[Array, Array, PyTree], Array] = eqx.field(static=True)
    params: PyTree

    def rate(self, x: Float[Array, " m"], u: Float[Array, " n"]) -> Float[Array, " m"]:
        """True state rate at one sample: the nominal rate plus the perturbation's.

        **Arguments:**

        - `x`: the state `(m,)`.
        - `u`: the input `(n,)`.

        **Returns:** the rate `(m,)`.
        """
        return self.nominal.rate(x, u) + self.perturbation(x, u, self.params)

    def rate_batch(self, x: Float[Array, "N m"], u: Float[Array, "N n"]) -> Float[Array, "N m"]:
        """`rate` over samples.

        **Arguments:**

        - `x`: states `(N, m)`.
        - `u`: inputs `(N, n)`.

        **Returns:** the true rates `(N, m)`.
        """
        return jax.vmap(self.rate)(x, u)


def _held_field(s, y, args):
    # Module level (not a closure) so diffeqsolve's jit cache is reused across calls.
    system, t, u = args
    # side="right" gives i on [t_i, t_{i+1}); diffrax steps to prevbefore(t_{i+1})
    # and evaluates c == 1 stages at exactly that t1, so no stage sees t_{i+1}.
    i = jnp.clip(jnp.searchsorted(t, s, side="right") - 1, 0, t.shape[0] - 1)
    return system.rate(y, u[i])


def _linear_field(s, y, args):
    system, t, u = args
    i = jnp.clip(jnp.searchsorted(t, s, side="right") - 1, 0, t.shape[0] - 2)
    w = (s - t[i]) / (t[i + 1] - t[i])
    return system.rate(y, (1.0 - w) * u[i] + w * u[i + 1])


INTERPOLATIONS = ("held", "linear", "bandlimited")
UPSAMPLE = 8  # fine samples per step of a band-limited input, linear between them


def check_interpolation(interpolation: str) -> str:
    """Check the name of the input's behaviour between samples.

    `"held"`: zero-order hold, a digital controller's output; `"linear"`; or `"bandlimited"`:
    an analogue signal sampled below Nyquist, e.g. a multisine, reconstructed by `upsample`
    (at a few samples per period, linear interpolation of such an input is a large error).

    **Arguments:**

    - `interpolation`: one of `INTERPOLATIONS`, `"held"`, `"linear"` or `"bandlimited"`.

    **Returns:** `interpolation`, unchanged. Raises a one-line `DataError` for any other value.
    """
    if interpolation not in INTERPOLATIONS:
        raise DataError(f"input interpolation must be one of {INTERPOLATIONS}, got {interpolation!r}")
    return interpolation


HIGH_BAND_EDGE = 0.8  # the top band starts at this fraction of Nyquist
# Measured fractions above 0.8 Nyquist (tests/test_interpolation.py): held white noise 0.21,
# a held random signal new every 2 / 5 / 20 samples 0.014 / 0.021 / 0.0047, multisines to
# 10-40% of Nyquist <1e-17, with 2% / 5% white measurement noise <8.6e-5 / <5.6e-4, the
# Silverbox input 2.9e-6. The threshold sits 2.3x and 3.6x from the closest cases; it takes
# white noise up to ~10% of a band-limited input's std (0.2 level^2 = 2e-3).
HIGH_BAND_THRESHOLD = 2e-3
_MIN_SPECTRUM_SAMPLES = 32  # fewer samples: too few bins in the top band to judge


def high_band_fraction(u) -> np.ndarray:
    """The fraction of each input column's variance above `HIGH_BAND_EDGE` (0.8) times Nyquist.

    From the Hann-windowed periodogram of `u` minus its mean per record, pooled over records.

    **Arguments:**

    - `u`: sampled inputs `(N, n)` or `(R, N, n)` with `N >= 2`, any units, uniform sampling.

    **Returns:** fractions `(n,)` in `[0, 1]`, dimensionless; NaN for a column with no variance.
    """
    u = np.asarray(u, dtype=np.float64)
    if u.ndim == 2:
        u = u[None]
    if u.ndim != 3 or u.shape[1] < 2:
        raise DataError(f"input u must have shape (N, n) or (R, N, n) with N >= 2, got {np.shape(u)}")
    N = u.shape[1]
    # The window keeps a trend's or a non-periodic end's leakage out of the top band.
    w = np.hanning(N)[None, :, None]
    power = (np.abs(np.fft.rfft((u - u.mean(axis=1, keepdims=True)) * w, axis=1)) ** 2).sum(axis=0)
    top = np.fft.rfftfreq(N) >= HIGH_BAND_EDGE * 0.5  # cycles per sample, Nyquist 0.5
    total = power.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(total > 0, power[top].sum(axis=0) / total, np.nan)


def choose_interpolation(u) -> str:
    """`"held"` or `"bandlimited"` for the measured input `u`, from its spectrum.

    A band-limited input (an analogue signal sampled, e.g. a multisine) has almost no power
    near Nyquist; a held input that changes at the samples (held white noise, a controller's
    output, a random signal held over a few samples) has power up to Nyquist from its jumps.
    Rule: `"held"` when any column puts more than `HIGH_BAND_THRESHOLD` (0.2%) of its
    variance above 0.8 Nyquist (`high_band_fraction`), else `"bandlimited"`. A held
    input that varies smoothly (or changes only every ~50 samples or more) reads as
    band-limited; either reconstruction then is close. `"linear"` is never chosen. A
    constant input, or a record under 32 samples, gives `"held"` (nothing to tell apart).

    **Arguments:**

    - `u`: sampled inputs `(N, n)` or `(R, N, n)` with `N >= 2`, any units, uniform sampling,
      finite.

    **Returns:** `"held"` or `"bandlimited"`.
    """
    u = np.asarray(u, dtype=np.float64)
    if u.ndim not in (2, 3) or u.shape[-2] < 2:
        raise DataError(f"input u must have shape (N, n) or (R, N, n) with N >= 2, got {u.shape}")
    if not np.all(np.isfinite(u)):
        raise DataError("input u has non-finite values; cannot choose its interpolation")
    if u.shape[-2] < _MIN_SPECTRUM_SAMPLES:
        return "held"
    frac = high_band_fraction(u)
    if np.all(np.isnan(frac)) or np.nanmax(frac) > HIGH_BAND_THRESHOLD:
        return "held"
    return "bandlimited"


def resolve_interpolation(interpolation: str, u) -> tuple[str, str]:
    """The input interpolation to use, and who chose it.

    `"auto"` becomes `choose_interpolation` of `u`, chosen by `"spectrum"`; any other value
    is checked (`check_interpolation`) and chosen by `"user"`.

    **Arguments:**

    - `interpolation`: `"auto"`, `"held"`, `"linear"` or `"bandlimited"`.
    - `u`: sampled inputs `(N, n)` or `(R, N, n)`; read only for `"auto"`.

    **Returns:** `(interpolation, chosen_by)`: the checked interpolation name and
    `"spectrum"` or `"user"`.
    """
    if interpolation == "auto":
        return choose_interpolation(u), "spectrum"
    return check_interpolation(interpolation), "user"


def upsample(u, factor: int = UPSAMPLE):
    """Band-limited reconstruction of a sampled input on a grid `factor` times finer.

    The reconstruction passes through the samples: zero-padding of the spectrum of the record
    extended by its mirror image (so its ends meet without a jump).

    **Arguments:**

    - `u`: samples `(N, n)` on a uniform grid, any units.
    - `factor`: fine samples per sample interval (default `UPSAMPLE`, 8).

    **Returns:** the fine samples `(factor (N - 1) + 1, n)`, in `u`'s units; every
    `factor`-th one is a sample of `u`.
    """
    u = jnp.asarray(u)
    N = u.shape[0]
    ext = jnp.concatenate([u, u[-2:0:-1]])  # even extension, period 2N - 2
    P = ext.shape[0]
    spec = jnp.fft.rfft(ext, axis=0)
    if P % 2 == 0:  # split the Nyquist bin between +-f so the result stays real and exact
        spec = spec.at[-1].multiply(0.5)
    fine = jnp.fft.irfft(spec, n=P * factor, axis=0) * factor
    return fine[: (N - 1) * factor + 1]


NONSMOOTH_FAMILIES = ("sign", "abs", "xabs")  # library families with a jump or a kink


def fixed_grid(t: Float[Array, " N"], substeps: int) -> Float[Array, " M"]:
    """A time grid with `substeps` equal steps in every sample interval of `t`.

    Every `t_i` is in it exactly (so a held input's jumps are step ends).

    **Arguments:**

    - `t`: sample times `(N,)`, s.
    - `substeps`: steps per sample interval, a positive integer.

    **Returns:** the grid `((N - 1) substeps + 1,)`, s.
    """
    frac = jnp.arange(substeps, dtype=t.dtype) / substeps
    inner = (t[:-1, None] + (t[1:] - t[:-1])[:, None] * frac).ravel()
    return jnp.concatenate([inner, t[-1:]])


def _solve(system, x0, t, u, *, rtol, atol, max_steps, interpolation, adjoint, substeps, event, throw,
           save_end):
    """The diffrax solve behind `simulate` and `simulate_checked` (arguments as there)."""
    if interpolation is None:
        interpolation = getattr(system, "interpolation", "held")
    check_interpolation(interpolation)
    args = (system, t, u)
    if interpolation == "bandlimited":
        # Linear between 8x fine samples whose spacing is far below any resolved period:
        # fixed Tsit5 steps on that grid (on the Silverbox arrow 6e-7 V from adaptive Dopri8
        # at rtol 1e-10, and 18x faster: the adaptive controller clipped to 8N jump times
        # spends most of its time on the clipping).
        uf = upsample(u)
        tf = jnp.linspace(t[0], t[-1], uf.shape[0])
        args = (system, tf, uf)
        solver, controller, max_steps = diffrax.Tsit5(), diffrax.StepTo(ts=tf), tf.shape[0] - 1
    elif substeps is not None:
        # Fixed steps for a non-smooth rate (sign(v) chatters an adaptive solver to a halt).
        # Bosh3: no stage at a step's end enters its solution (the end's rate is the next
        # step's first, FSAL), so every stage sees the held input of its own interval.
        grid = fixed_grid(t, int(substeps))
        solver, controller, max_steps = diffrax.Bosh3(), diffrax.StepTo(ts=grid), grid.shape[0] - 1
    else:
        if max_steps is None:  # every input sample is a step end, plus room between them
            max_steps = 16 * t.shape[0] + 4096
        # The ends are not jumps inside [t_0, t_{N-1}]; passing them only adds tiny steps.
        jump_ts = t[1:-1] if t.shape[0] > 2 else None
        controller = diffrax.ClipStepSizeController(diffrax.PIDController(rtol=rtol, atol=atol), jump_ts=jump_ts)
        solver = diffrax.Dopri8()
    return diffrax.diffeqsolve(
        diffrax.ODETerm(_held_field if interpolation == "held" else _linear_field),
        solver,
        t0=t[0],
        t1=t[-1],
        dt0=None,
        y0=x0,
        args=args,
        saveat=diffrax.SaveAt(ts=t, t1=save_end),
        stepsize_controller=controller,
        max_steps=max_steps,
        adjoint=diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint,
        event=event,
        throw=throw,
    )


def _check_shapes(t, x0, u):
    float_ = jnp.result_type(float)
    t, x0, u = (jnp.asarray(a, dtype=float_) for a in (t, x0, u))
    if t.ndim != 1 or t.shape[0] < 2:
        raise DataError(f"time grid t must have shape (N,) with N >= 2, got {t.shape}")
    N = t.shape[0]
    if u.ndim != 2 or u.shape[0] != N:
        raise DataError(f"input u must have shape ({N}, n), got {u.shape}")
    if x0.ndim != 1:
        raise DataError(f"initial state x0 must have shape (m,), got {x0.shape}")
    return t, x0, u


@strong_jit
def simulate(
    system: PerturbedSystem | LinearSecondOrder,
    x0: Float[Array, " m"],
    t: Float[Array, " N"],
    u: Float[Array, "N n"],
    *,
    rtol: float = 1e-10,
    atol: float = 1e-12,
    max_steps: int | None = None,
    interpolation: str | None = None,
    adjoint: diffrax.AbstractAdjoint | None = None,
    substeps: int | None = None,
) -> tuple[Float[Array, "N m"], Float[Array, "N m"]]:
    """Integrate `dX/dt = system.rate(X, u(t))` under the sampled input `u`.

    Held and linear inputs: adaptive Dopri8 (`rtol`, `atol`), every `t_i` a jump time (of the
    input or its slope) that no step crosses; or, with `substeps`, fixed Bosh3 steps. A
    band-limited input: fixed Tsit5 steps on the 8x fine grid of `upsample` (`rtol`, `atol`,
    `max_steps` and `substeps` unused). The system is time-invariant: the solve runs from
    `t[0]` shifted to 0, so epoch times keep full precision. A solver failure raises.

    **Arguments:**

    - `system`: a `PerturbedSystem`, a `LinearSecondOrder`, or another module with their
      `rate(x, u)` (an updated twin, `prediction.UpdatedTwin`).
    - `x0`: the initial state `(m,)` at `t[0]`.
    - `t`: sample times `(N,)`, s, increasing, `N >= 2`.
    - `u`: the sampled input `(N, n)`.
    - `rtol`: relative tolerance of the adaptive solver (default 1e-10).
    - `atol`: absolute tolerance of the adaptive solver, the states' units (default 1e-12).
    - `max_steps`: the most steps of the adaptive solver; None (default) for `16 N + 4096`.
    - `interpolation`: the input between samples: `"held"` (`u[i]` holds on
      `[t_i, t_{i+1})`), `"linear"` (interpolated linearly between samples) or
      `"bandlimited"` (reconstructed by `upsample`); None (default) for the system's own
      (an updated twin's, from its data), else held.
    - `adjoint`: diffrax's adjoint for derivatives; None (default) for
      `RecursiveCheckpointAdjoint` (reverse mode); `diffrax.ForwardMode()` for `jax.jacfwd`.
    - `substeps`: None (default) for the adaptive solver; else fixed Bosh3 steps, this many
      per sample interval (for a non-smooth rate such as Coulomb friction `sign(v)`, on which
      an adaptive solver chatters).

    **Returns:** `(x, xdot)`: the states `(N, m)` at the times `t` and their rates `(N, m)`,
    `xdot[i] = system.rate(x[i], u[i])`, what an ideal accelerometer reads.
    """
    t, x0, u = _check_shapes(t, x0, u)
    t = t - t[0]  # time-invariant: from 0, epoch times (t ~ 1.7e9 s) keep full precision
    sol = _solve(system, x0, t, u, rtol=rtol, atol=atol, max_steps=max_steps, interpolation=interpolation,
                 adjoint=adjoint, substeps=substeps, event=None, throw=True, save_end=False)
    x = sol.ys
    xdot = jax.vmap(system.rate)(x, u)
    return x, xdot


# simulate_checked's status codes (per solve): finished, left its bounds or non-finite,
# out of solver steps, any other solver failure.
OK, DIVERGED, MAX_STEPS, FAILED = 0, 1, 2, 3


def _status(sol) -> Array:
    return jnp.where(sol.result == diffrax.RESULTS.successful, OK,
                     jnp.where(sol.result == diffrax.RESULTS.event_occurred, DIVERGED,
                               jnp.where(sol.result == diffrax.RESULTS.max_steps_reached, MAX_STEPS, FAILED)))


def _outside(s, y, args, *, lower, upper, **kwargs):
    # A boolean event: the solve ends on the first step whose state leaves the box.
    return jnp.any(~jnp.isfinite(y) | (y < lower) | (y > upper))


def simulate_checked(
    system: PerturbedSystem | LinearSecondOrder,
    x0: Float[Array, " m"],
    t: Float[Array, " N"],
    u: Float[Array, "N n"],
    lower: Float[Array, " m"],
    upper: Float[Array, " m"],
    *,
    rtol: float = 1e-10,
    atol: float = 1e-12,
    max_steps: int | None = None,
    interpolation: str | None = None,
    substeps: int | None = None,
) -> tuple[Float[Array, "N m"], Array, Array]:
    """`simulate` that stops instead of failing.

    A state outside `[lower, upper]` or non-finite ends the solve (a diffrax `Event`), and
    running out of solver steps returns rather than raises (`throw=False`). Jittable and
    vmappable. The adjoint is `RecursiveCheckpointAdjoint`.

    **Arguments:**

    - `system`: the system, as in `simulate`.
    - `x0`: the initial state `(m,)` at `t[0]`.
    - `t`: sample times `(N,)`, s, increasing, `N >= 2`.
    - `u`: the sampled input `(N, n)`.
    - `lower`: the lower bound `(m,)` of every state, its units.
    - `upper`: the upper bound `(m,)` of every state, its units.
    - `rtol`: relative tolerance of the adaptive solver (default 1e-10).
    - `atol`: absolute tolerance of the adaptive solver, the states' units (default 1e-12).
    - `max_steps`: the most steps of the adaptive solver; None (default) for `16 N + 4096`.
    - `interpolation`: the input between samples, as in `simulate`; None (default) for the
      system's own, else held.
    - `substeps`: None (default) for the adaptive solver, else fixed Bosh3 steps per sample
      interval, as in `simulate`.

    **Returns:** `(x, status, stop_time)`: the states `(N, m)` (inf after the stop); `status`,
    a scalar integer code (`OK`, `DIVERGED`, `MAX_STEPS` or `FAILED`); and `stop_time`, the
    time (s, on the clock of `t`) the solve reached.
    """
    t, x0, u = _check_shapes(t, x0, u)
    t0, t = t[0], t - t[0]  # from 0, as in simulate
    event = diffrax.Event(lambda s, y, args, **kw: _outside(s, y, args, lower=lower, upper=upper))
    sol = _solve(system, x0, t, u, rtol=rtol, atol=atol, max_steps=max_steps, interpolation=interpolation,
                 adjoint=diffrax.RecursiveCheckpointAdjoint(), substeps=substeps, event=event, throw=False,
                 save_end=True)
    # On a stop diffrax compacts the end time right after the last time saved, inf after it.
    N = t.shape[0]
    ys, ts = sol.ys, sol.ts
    stopped = ts[:N] != t
    x = jnp.where(stopped[:, None], jnp.inf, ys[:N])
    return x, _status(sol), t0 + jnp.max(jnp.where(jnp.isfinite(ts), ts, t[0]))


def diffusion_matrix(nominal: LinearSecondOrder) -> Float[Array, "m n"]:
    """The diffusion matrix `G (m, n)` of `dX = (f + h) dt + G dB` under the force `B dB`.

    The force `B dB` enters the velocity rows as `M^-1 B dB`; the kinematic and extra rows
    get no noise.

    **Arguments:**

    - `nominal`: the nominal model.

    **Returns:** `G (m, n)`: `M^-1 B` in the velocity rows, zero elsewhere.
    """
    d = nominal.d
    gain = mass_solve(nominal.M, nominal.B)
    return jnp.zeros((nominal.m, nominal.n), gain.dtype).at[d : 2 * d].set(gain)


def _sde_drift(s, y, system):
    return system.rate(y, jnp.zeros(system_nominal(system).n, y.dtype))


def _sde_diffusion(s, y, system):
    # An updated twin carries its discovered, possibly state-dependent, diffusion.
    if hasattr(system, "diffusion"):
        # A constant one is evaluated off y: ShARK checks (by a JVP) that it ignores y.
        return system.diffusion(jnp.zeros(y.shape, y.dtype) if system.additive_noise else y)
    return diffusion_matrix(system_nominal(system))


def system_nominal(system: PerturbedSystem | LinearSecondOrder) -> LinearSecondOrder:
    """The nominal model of a system (itself when it is nominal).

    **Arguments:**

    - `system`: a `LinearSecondOrder`, or a `PerturbedSystem` (or an updated twin) with a
      `nominal`.

    **Returns:** the `LinearSecondOrder`.
    """
    return system if isinstance(system, LinearSecondOrder) else system.nominal


def _solve_sde(system, x0, t, key, substeps, event, throw):
    nominal = system_nominal(system)
    N = t.shape[0]
    t = t - t[0]  # time-invariant: from 0, as in simulate
    fine = jnp.linspace(t[0], t[-1], (N - 1) * substeps + 1)
    brownian = diffrax.UnsafeBrownianPath(
        shape=(nominal.n,), key=key, levy_area=diffrax.SpaceTimeLevyArea
    )
    terms = diffrax.MultiTerm(
        diffrax.ODETerm(_sde_drift), diffrax.ControlTerm(_sde_diffusion, brownian)
    )
    # ShARK needs additive noise; a twin's state-dependent diffusion takes GeneralShARK.
    additive = getattr(system, "additive_noise", True)
    sol = diffrax.diffeqsolve(
        terms,
        diffrax.ShARK() if additive else diffrax.GeneralShARK(),
        t0=t[0],
        t1=t[-1],
        dt0=None,
        y0=x0,
        args=system,
        saveat=diffrax.SaveAt(steps=True),
        stepsize_controller=diffrax.StepTo(ts=fine),
        max_steps=(N - 1) * substeps,
        adjoint=diffrax.ForwardMode(),  # UnsafeBrownianPath cannot be checkpointed
        event=event,
        throw=throw,
    )
    return sol, jnp.concatenate([x0[None], sol.ys[substeps - 1 :: substeps]])


def _check_sde(t, x0):
    float_ = jnp.result_type(float)
    t, x0 = jnp.asarray(t, float_), jnp.asarray(x0, float_)
    if t.ndim != 1 or t.shape[0] < 2:
        raise DataError(f"time grid t must have shape (N,) with N >= 2, got {t.shape}")
    return t, x0


@strong_jit
def simulate_sde(
    system: PerturbedSystem | LinearSecondOrder,
    x0: Float[Array, " m"],
    t: Float[Array, " N"],
    key: Array,
    *,
    substeps: int = 4,
) -> Float[Array, "N m"]:
    """Sample the Ito SDE `dX = (f(X) + h(X)) dt + G dB` on a uniform grid.

    The force is `B dB` with `B` the nominal input matrix and `dB` the increment of an
    `n`-dimensional unit-intensity Brownian motion, so `G = diffusion_matrix(nominal)` and the
    diffusion of velocity `i` is `Gamma_ii = (G G^T)_ii`; a system with its own `diffusion(x)`
    (an output-only updated twin) uses that instead. Integrated with ShARK (strong order 1.5
    for additive noise; GeneralShARK for a state-dependent diffusion) at `dt / substeps`;
    Euler-Maruyama at 1 ms would inflate the variance of these oscillators. Vmap over `key`
    for an ensemble.

    **Arguments:**

    - `system`: a `PerturbedSystem` or `LinearSecondOrder` (or an updated twin); its input is
      zero, the forcing Brownian.
    - `x0`: the initial state `(m,)` at `t[0]`.
    - `t`: uniform sample times `(N,)`, s, `N >= 2`.
    - `key`: JAX PRNG key of the Brownian path.
    - `substeps`: solver steps per sample interval (default 4).

    **Returns:** the states `x (N, m)` at the times `t`, with `x[0] = x0`.
    """
    t, x0 = _check_sde(t, x0)
    return _solve_sde(system, x0, t, key, substeps, None, True)[1]


def simulate_sde_checked(
    system: PerturbedSystem | LinearSecondOrder,
    x0: Float[Array, " m"],
    t: Float[Array, " N"],
    key: Array,
    lower: Float[Array, " m"],
    upper: Float[Array, " m"],
    *,
    substeps: int = 4,
) -> tuple[Float[Array, "N m"], Array, Array]:
    """`simulate_sde` that stops when a state leaves its bounds or is non-finite.

    As `simulate_checked`: a diffrax `Event` ends the solve, and a failure returns rather than
    raises.

    **Arguments:**

    - `system`: the system, as in `simulate_sde`.
    - `x0`: the initial state `(m,)` at `t[0]`.
    - `t`: uniform sample times `(N,)`, s, `N >= 2`.
    - `key`: JAX PRNG key of the Brownian path.
    - `lower`: the lower bound `(m,)` of every state, its units.
    - `upper`: the upper bound `(m,)` of every state, its units.
    - `substeps`: solver steps per sample interval (default 4).

    **Returns:** `(x, status, stop_time)`: the states `(N, m)` (inf after the stop); `status`,
    a scalar integer code (`OK`, `DIVERGED`, `MAX_STEPS` or `FAILED`); and `stop_time`, the
    time (s, on the clock of `t`) the solve reached.
    """
    t, x0 = _check_sde(t, x0)
    event = diffrax.Event(lambda s, y, args, **kw: _outside(s, y, args, lower=lower, upper=upper))
    sol, x = _solve_sde(system, x0, t, key, substeps, event, False)
    # _solve_sde runs from 0: the stop time back on the caller's clock.
    return x, _status(sol), t[0] + jnp.max(jnp.where(jnp.isfinite(sol.ts), sol.ts, 0.0))


# ---------------------------------------------------------------------------
# Examples (paper, Table 1)


class Example(NamedTuple):
    """A benchmark: a true (perturbed) system, its setup and the terms to find.

    `true_terms` maps a regressed state name to `{term: coefficient}`, with the
    term in sympy's `str` form and the coefficient in the units of that rate.
    """

    name: str
    system: PerturbedSystem
    x0: Float[Array, " m"]
    dt: float
    duration: float
    input_std: float
    true_terms: dict[str, dict[str, float]]
    library: str
    description: str
    # Terms a 1 s window at 5% noise can identify (None: all of `true_terms`).
    identifiable_terms: dict[str, tuple[str, ...]] | None = None
    # Framework 2 (Brownian forcing, states only): initial state, when it differs from x0.
    x0_output_only: Float[Array, " m"] | None = None

    @property
    def library_output_only(self) -> str:
        """`library` without the `input` family (no input is measured)."""
        return ",".join(f for f in self.library.split(",") if f != "input")

    def for_output_only(self) -> "Example":
        """The example as framework 2 uses it (its `x0_output_only` as `x0`)."""
        if self.x0_output_only is None:
            return self
        return self._replace(x0=self.x0_output_only)

    def true_diffusion(self) -> dict[str, float]:
        """`Gamma_ii = (sigma_i / m_i)^2` of every velocity state under `simulate_sde`."""
        nominal = self.system.nominal
        G = np.asarray(diffusion_matrix(nominal))
        gamma = np.sum(G * G, axis=1)
        return {nominal.state_names[i]: float(gamma[i]) for i in nominal.velocity_index}

    def true_coefficients(self, names) -> np.ndarray:
        """Coefficients of the true perturbation in a library, one row per regressed state.

        **Arguments:**

        - `names`: the library's `K` term names, in sympy's `str` form (as
          `library.parse_library` names them); every true term must be among them.

        **Returns:** the coefficients `(r, K)`, `r` the number of regressed states, each in the
        units of that state's rate; zero for a term the truth does not have.
        """
        nominal = self.system.nominal
        names = list(names)
        coef = np.zeros((len(nominal.regressed_index), len(names)))
        for j, i in enumerate(nominal.regressed_index):
            for term, c in self.true_terms.get(nominal.state_names[i], {}).items():
                coef[j, names.index(term)] = c
        return coef

    def identifiable(self) -> dict[str, dict[str, float]]:
        """`true_terms` restricted to the identifiable terms."""
        if self.identifiable_terms is None:
            return self.true_terms
        return {
            state: {t: c for t, c in terms.items() if t in self.identifiable_terms[state]}
            for state, terms in self.true_terms.items()
        }


# Unit-intensity Gaussian white noise sampled and held at 1 kHz: u_k ~ N(0, 1/dt), so the
# force sigma*u has the spectral intensity of the paper's sigma*dB/dt (framework 2).
_WHITE_STD = 1e3**0.5


def _duffing_sdof(x, u, params):
    # Cubic spring force alpha q^3 moved to the rate side: -alpha q^3 / m.
    return jnp.stack([jnp.zeros_like(x[0]), -params["alpha"] * x[0] ** 3 / params["mass"]])


def _duffing_chain2(x, u, params):
    # Cubic springs: ground-DOF1 and DOF1-DOF2; `mass` is the diagonal of M.
    q1, q2 = x[0], x[1]
    alpha = params["alpha"]
    force = jnp.stack([alpha * q1**3 + alpha * (q1 - q2) ** 3, alpha * (q2 - q1) ** 3])
    return jnp.concatenate([jnp.zeros(2, dtype=x.dtype), -force / params["mass"]])


def _crack_degradation(x, u, params):
    # Stiffness k*lambda(q) with lambda(0) = 1; the nominal already holds k*x.
    p = params
    disp, vel, damage = x[0], x[1], x[2]
    lam = p["a1"] + p["a2"] * jnp.exp(-p["a3"] * jnp.maximum(damage, 0.0) ** p["a4"])
    accel = -p["k"] * (lam - 1.0) * disp / p["mass"]
    # Safe power: the base is >= 0, and 0**(beta/2) has no NaN gradient this way.
    r2 = disp**2 + vel**2
    r2_safe = jnp.where(r2 > 0, r2, 1.0)
    growth = p["gamma"] * jnp.where(r2 > 0, r2_safe ** (p["beta"] / 2), 0.0)
    return jnp.stack([jnp.zeros_like(disp), accel, growth])


_DUFFING_LIBRARY = "poly:6,sign,abs,xabs,exp,expxx,sin,cos,input"


def example1() -> Example:
    """SDOF Duffing oscillator: m=1, c=2, k=1000, alpha=1e5, force 0.5 u."""
    mass, c, k, alpha, sigma = 1.0, 2.0, 1000.0, 1e5, 0.5
    nominal = LinearSecondOrder.create([[mass]], [[c]], [[k]], [[sigma]])
    params = {"alpha": jnp.asarray(alpha), "mass": jnp.asarray(mass)}
    return Example(
        name="example1",
        system=PerturbedSystem(nominal, _duffing_sdof, params),
        x0=jnp.array([0.1, 0.0]),
        dt=1e-3,
        duration=1.0,
        input_std=_WHITE_STD,
        true_terms={"x2": {"x1**3": -alpha / mass}},
        library=_DUFFING_LIBRARY,
        description=(
            "SDOF Duffing: x1'' + 2 x1' + 1000 x1 + 1e5 x1^3 = 0.5 u, u unit-intensity "
            "white noise held over each 1 ms (u_k ~ N(0, 1/dt)); x0 = [0.1, 0]. "
            "The nominal model is linear."
        ),
    )


def example2() -> Example:
    """2-DOF Duffing chain: unit masses, c1=c2=4, k1=4000, k2=2000, alpha=5e4, sigma=0.5."""
    m1 = m2 = 1.0
    c1 = c2 = 4.0
    k1, k2, alpha, sigma = 4000.0, 2000.0, 5e4, 0.5
    nominal = LinearSecondOrder.create(
        np.diag([m1, m2]),
        [[c1 + c2, -c2], [-c2, c2]],
        [[k1 + k2, -k2], [-k2, k2]],
        np.diag([sigma, sigma]),
    )
    params = {"alpha": jnp.asarray(alpha), "mass": jnp.array([m1, m2])}
    # -force/m expanded in monomials of x1 = q1, x2 = q2 (checked with sympy in tests).
    a = alpha
    true_terms = {
        "x3": {"x1**3": -2 * a / m1, "x1**2*x2": 3 * a / m1, "x1*x2**2": -3 * a / m1,
               "x2**3": a / m1},
        "x4": {"x1**3": a / m2, "x1**2*x2": -3 * a / m2, "x1*x2**2": 3 * a / m2,
               "x2**3": -a / m2},
    }
    return Example(
        name="example2",
        system=PerturbedSystem(nominal, _duffing_chain2, params),
        x0=jnp.array([0.3, 0.2, 0.0, 0.0]),
        dt=1e-3,
        duration=1.0,
        input_std=_WHITE_STD,
        true_terms=true_terms,
        library=_DUFFING_LIBRARY,
        description=(
            "2-DOF chain with cubic springs alpha q1^3 (ground-1) and alpha (q1-q2)^3 "
            "(1-2), alpha=5e4; forces 0.5 u1, 0.5 u2 (unit-intensity white noise). "
            "x0 = [0.3, 0.2, 0, 0] excites both modes at large amplitude: from a "
            "single-mode start q2 ~ c q1 and the four cubic monomials are collinear."
        ),
    )


def example3() -> Example:
    """Crack degradation (paper Eq. 27): stiffness `k*lambda(q)` with damage `q' > 0`."""
    mass, c, k, sigma = 1.0, 2.0, 2000.0, 1.0
    a1, a2, a3, a4, beta, gamma = 0.5, 0.5, 1.0, 1.0, 2.0, 0.01
    nominal = LinearSecondOrder.create([[mass]], [[c]], [[k]], [[sigma]], extra_states=1)
    params = {
        name: jnp.asarray(value)
        for name, value in dict(
            mass=mass, k=k, a1=a1, a2=a2, a3=a3, a4=a4, beta=beta, gamma=gamma
        ).items()
    }
    # With a3 = a4 = 1 and beta = 2 the perturbation is exactly these four terms.
    true_terms = {
        "x2": {"x1": -k * (a1 - 1.0) / mass, "x1*exp(-x3)": -k * a2 / mass},
        "x3": {"x1**2": gamma, "x2**2": gamma},
    }
    return Example(
        name="example3",
        system=PerturbedSystem(nominal, _crack_degradation, params),
        x0=jnp.array([1.0, 0.0, 0.0]),
        dt=1e-3,
        duration=1.0,
        input_std=_WHITE_STD,
        true_terms=true_terms,
        library="poly:3,exp,expx,input",
        description=(
            "Crack degradation: x1'' + 2 x1' + 2000 lambda(x3) x1 = u, "
            "lambda = 0.5 + 0.5 exp(-x3), x3' = 0.01 (x1^2 + x2^2) (gamma = 0.01 as in "
            "the paper's Table 2, not the 0.001 of its Table 1). Nominal: the undamaged "
            "linear oscillator. x0 = [1, 0, 0]: the damage x3 grows from 0 to about 3.8 "
            "in 1 s (measured), so exp(-x3) x1 is distinguishable from x1. The damage "
            "law's 0.01 x1^2 is not identifiable: |x1| ~ |x2|/45, so it is ~0.05% of x3'."
        ),
        identifiable_terms={"x2": ("x1", "x1*exp(-x3)"), "x3": ("x2**2",)},
    )


EXAMPLES: dict[str, Callable[[], Example]] = {
    "example1": example1,
    "example2": example2,
    "example3": example3,
}


def simulate_example(
    example: Example,
    key: Array,
    *,
    duration: float | None = None,
    dt: float | None = None,
    x0: Array | None = None,
) -> dict[str, Array]:
    """Simulate an example under white Gaussian input held over each sample.

    `N = round(duration / dt)` samples from `t = 0`; `u ~ N(0, input_std^2)` iid.

    **Arguments:**

    - `example`: the `Example`.
    - `key`: JAX PRNG key of the input.
    - `duration`: the record's length, s; None (default) for `example.duration`.
    - `dt`: the sample interval, s; None (default) for `example.dt`.
    - `x0`: the initial state `(m,)`; None (default) for `example.x0`.

    **Returns:** `{"t": (N,), "x": (N, m), "xdot": (N, m), "u": (N, n)}`: times (s), states,
    their rates (as `simulate`) and the inputs.
    """
    duration = example.duration if duration is None else duration
    dt = example.dt if dt is None else dt
    x0 = example.x0 if x0 is None else jnp.asarray(x0)
    N = int(round(duration / dt))
    if N < 2:
        raise DataError(f"simulation needs at least 2 samples, got duration/dt = {N}")
    t = jnp.arange(N) * dt
    u = example.input_std * jax.random.normal(key, (N, example.system.nominal.n))
    x, xdot = simulate(example.system, x0, t, u)
    return {"t": t, "x": x, "xdot": xdot, "u": u}



def simulate_example_sde(
    example: Example,
    key: Array,
    *,
    num_records: int = 1,
    duration: float | None = None,
    dt: float | None = None,
    substeps: int = 4,
    accelerations: bool = False,
) -> dict[str, Array]:
    """Framework 2: independent records of an example driven by Brownian forcing.

    `R = num_records` records, all from `example.x0`, simulated by `simulate_sde` on
    `N = round(duration / dt) + 1` samples from `t = 0`.

    **Arguments:**

    - `example`: the `Example`.
    - `key`: JAX PRNG key; split into one Brownian path per record.
    - `num_records`: `R`, the number of records (default 1).
    - `duration`: the record's length, s; None (default) for `example.duration`.
    - `dt`: the sample interval, s; None (default) for `example.dt`.
    - `substeps`: solver steps per sample interval (default 4); with `accelerations`,
      `max(1, substeps // 2)` per half interval (the same for an even `substeps`).
    - `accelerations`: also return what an accelerometer averaging over each sample's
      interval measures (the change of each velocity from half a step before the sample to
      half a step after it, over `dt`; the force is white, so its acceleration has no value
      at an instant). The records then start half a step after `example.x0`.

    **Returns:** `{"t": (N,), "x": (R, N, m)}`, times (s) and states; with `accelerations`,
    also `"xdot": (R, N, d)`, the averaged accelerations of the velocity states.
    """
    duration = example.duration if duration is None else duration
    dt = example.dt if dt is None else dt
    N = int(round(duration / dt)) + 1
    if N < 3:
        raise DataError(f"simulation needs at least 3 samples, got duration/dt = {N - 1}")
    t = jnp.arange(N) * dt
    keys = jax.random.split(key, num_records)
    if not accelerations:
        x = jax.vmap(lambda k: simulate_sde(example.system, example.x0, t, k, substeps=substeps))(keys)
        return {"t": t, "x": x}
    half = jnp.arange(2 * N + 1) * (dt / 2)  # samples at the odd points, velocities at the even
    xh = jax.vmap(lambda k: simulate_sde(example.system, example.x0, half, k, substeps=max(1, substeps // 2)))(keys)
    vel = jnp.asarray(example.system.nominal.velocity_index)
    return {"t": t, "x": xh[:, 1::2], "xdot": (xh[:, 2::2, vel] - xh[:, :-2:2, vel]) / dt}
