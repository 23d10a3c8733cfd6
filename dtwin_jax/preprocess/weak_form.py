"""The weak (integral) form of framework 1: states without rates, nothing differentiated.

Each regressed equation `x_i' = f_i(x, u) + Theta(x, u) theta` is multiplied by test
functions `phi_k(t) = (s (1 - s))^p` on windows of the record (`s` runs 0..1 over the
window) and integrated; `phi_k` and its derivatives vanish at the window's ends, so by
parts `y_k = -int phi_k' x_i dt - int phi_k f_i(x, u) dt = int phi_k Theta(x, u) dt theta`:
the rate never appears. A velocity that is not measured (displacement sensors alone) is
integrated by parts once more, `int phi v = -int phi' q` and `int phi' v = -int phi'' q`,
so the nominal model's part stays exact; so is a library term `g(q_j) v_j`, the time
derivative of `G(q_j)`: `int phi g v = -int phi' G`. Only the terms nonlinear in an
unmeasured velocity see an estimate of it (a Savitzky-Golay derivative).

Windows overlap, so the rows' noise is correlated. Each equation's rows are whitened by their
covariance: white measurement noise on the sensors (`sum_j s_j^2 A_j A_j^T`, `A_j = d y /
d x_j` through the test functions and the nominal model) plus a white equation error of
unknown size (input noise, process noise, what the library misses: `lambda Phi Phi^T`),
`lambda` chosen by restricted maximum likelihood on the whole library's residual. Without
that second part, input noise and model error would pass for information and the intervals
would be too narrow.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax import sampler
from dtwin_jax.errors import DataError
from dtwin_jax.library import Library
from dtwin_jax.models.systems import LinearSecondOrder
from dtwin_jax.preprocess.denoise import (
    auto_half_width,
    noise_std,
    savgol_design_ok,
    savgol_states,
)
from dtwin_jax.preprocess.instruments import instrumented_stats, reference_fit
from dtwin_jax.preprocess.measurement import (
    highest_natural_frequency_hz,
    savgol_coefficients,
    smooth,
)

__all__ = ["weak_windows", "weak_window_fits", "check_window", "window_filter", "window_grams", "window_quadrature",
           "weak_layout_supported", "weak_stats",
           "weak_input_output_stats", "derivative_terms", "reml_weight", "effective_share", "bump_functions",
           "TEST_POWER", "cut_segments"]

TEST_POWER = 6
_STRIDES = 8  # windows per window width


# Longer records are cut into segments whose dense quadrature and covariance matrices stay
# under this (a window's worth of samples is lost at each cut).
_SEGMENT_BYTES = 128 << 20
# Restricted maximum likelihood looks at this many rows at most (records evenly chosen).
_REML_ROWS = 4096

# Relative sizes of the equation error (to the sensor noise's trace), log-uniform a priori.
_ERROR_GRID = np.logspace(-4, 4, 33)


def _period_samples(nominal: LinearSecondOrder, dt: float, num_samples: int) -> float:
    """One period of the nominal's fastest mode in samples (1 % of the record without stiffness)."""
    f_hz = highest_natural_frequency_hz(nominal)
    return 1.0 / (f_hz * dt) if f_hz > 0 else max(16, num_samples // 100)


def weak_windows(nominal: LinearSecondOrder, dt: float, num_samples: int) -> tuple[int, int]:
    """Default window `(width, stride)` in samples: one period of the nominal's fastest
    mode (a 1 % of the record without stiffness), moved by an eighth of it.

    **Arguments:**

    - `nominal`: the nominal model, whose fastest undamped mode sets the width.
    - `dt`: the sample step, s.
    - `num_samples`: the samples per record.

    **Returns:** `(width, stride)` in samples: the width at least `2 TEST_POWER + 3` and
    clipped to the record, the stride `width // 8` (at least 1).
    """
    width = int(round(_period_samples(nominal, dt, num_samples)))
    width = int(min(max(width, 2 * TEST_POWER + 3), num_samples))
    return width, max(1, width // _STRIDES)


def weak_window_fits(nominal: LinearSecondOrder, dt: float, num_samples: int) -> bool:
    """Whether a record of `num_samples` holds at least two of the default windows
    (`weak_windows`: one period of the fastest mode, at least `2 p + 3` samples).

    **Arguments:**

    - `nominal`: the nominal model.
    - `dt`: the sample step, s.
    - `num_samples`: the samples per record.

    **Returns:** True when `width + stride <= num_samples`."""
    width, stride = weak_windows(nominal, dt, num_samples)
    return width + stride <= num_samples


def _segment_length(num_samples: int, width: int, stride: int) -> int:
    """The longest record length (at most `num_samples`, at least 4 windows) whose
    quadrature (4 W N) and covariance (9 W^2) matrices fit `_SEGMENT_BYTES`."""
    n = num_samples
    while n > 4 * width:
        w = (n - width) // stride + 1
        if 8 * (4 * w * n + 9 * w * w) <= _SEGMENT_BYTES:
            break
        n = max(4 * width, n // 2)
    return n


def cut_segments(a: np.ndarray, length: int) -> np.ndarray:
    """`(R, N, c)` -> `(R * (N // length), length, c)`; the remainder is dropped.

    **Arguments:**

    - `a`: records `(R, N, c)`.
    - `length`: the segment length in samples.

    **Returns:** the segments `(R * (N // length), length, c)`, each a record of its own
    (record by record, in time order)."""
    R, N, c = a.shape
    k = N // length
    return a[:, : k * length].reshape(R * k, length, c)


def weak_layout_supported(nominal: LinearSecondOrder, x_index) -> bool:
    """Whether the measured states `x_index` suit the weak form: every displacement and
    extra state measured (a velocity may be missing: it is integrated by parts).

    **Arguments:**

    - `nominal`: the nominal model.
    - `x_index`: the indices of the measured states (0-based, among the `m`).

    **Returns:** True when every state but the velocities is in `x_index`."""
    need = [i for i in range(nominal.m) if i not in nominal.velocity_index]
    return all(i in tuple(x_index) for i in need)


def bump_functions(width: int, dt: float, power: int):
    """`phi`, `phi'`, `phi''` on one window's samples, scaled to unit integral, each
    times `dt` (quadrature weights); and the held input's exact weights.

    **Arguments:**

    - `width`: the window in samples.
    - `dt`: the sample step, s.
    - `power`: p of `phi = (s (1 - s))^p`, `s` running 0..1 over the window.

    **Returns:** `(phi, dphi, ddphi, held)`, each `(width,)`: the weights of `phi`, `phi'`
    (1/s) and `phi''` (1/s^2), and `held`, the exact integral of `phi` over each step
    `[s_j, s_j+1]` (zero at the last sample)."""
    s = np.arange(width) / (width - 1)
    span = (width - 1) * dt
    b = s * (1 - s)
    base = b**power
    scale = 1.0 / (np.sum(base) * dt)  # the trapezoid's ends are zero
    phi = scale * base * dt
    dphi = scale * power * b ** (power - 1) * (1 - 2 * s) / span * dt
    ddphi = scale * power * (
        (power - 1) * b ** (power - 2) * (1 - 2 * s) ** 2 - 2 * b ** (power - 1)) / span**2 * dt
    # Exact integral of the polynomial phi over each step [s_j, s_j+1] (Gauss-Legendre).
    nodes, weights = np.polynomial.legendre.leggauss(power + 1)
    h = 1.0 / (width - 1)
    mid = s[:-1, None] + h * (nodes[None] + 1) / 2
    held = np.zeros(width)
    held[:-1] = scale * np.sum(weights * (mid * (1 - mid)) ** power, axis=1) * h / 2 * span
    return phi, dphi, ddphi, held


def check_window(num_samples: int, width: int, stride: int, power: int) -> np.ndarray:
    """The windows' first samples on a record, after checking the window fits.

    **Arguments:**

    - `num_samples`: N, the samples per record.
    - `width`: the window in samples.
    - `stride`: the step between windows' starts, samples (at least 1).
    - `power`: the test functions' p (a window needs at least `2 p + 3` samples).

    **Returns:** the sample indices `(W,)`; raises `DataError` when the window does not fit."""
    if width < 2 * power + 3 or width > num_samples:
        raise DataError(f"weak-form window of {width} samples must lie in [{2 * power + 3}, {num_samples}]")
    if stride < 1:
        raise DataError(f"weak-form stride must be >= 1 sample, got {stride}")
    return np.arange(0, num_samples - width + 1, stride)


def _place(row: np.ndarray, starts: np.ndarray, num_samples: int) -> np.ndarray:
    out = np.zeros((starts.size, num_samples))
    for k, a in enumerate(starts):
        out[k, a:a + row.size] = row
    return out


def window_quadrature(num_samples: int, dt: float, width: int, stride: int, power: int = TEST_POWER,
                      held: bool = True, second: bool = False) -> tuple[np.ndarray, ...]:
    """Quadrature matrices of the test functions over one record.

    **Arguments:**

    - `num_samples`: N, the samples per record.
    - `dt`: the sample step, s.
    - `width`: the window in samples.
    - `stride`: the step between windows' starts, samples.
    - `power`: p of `phi = (s (1 - s))^p` (scaled to unit integral); default `TEST_POWER`.
    - `held`: True (default): the input's weights integrate `phi` exactly over each held step;
      False: by the trapezoid rule.
    - `second`: also return the second derivative's (default False).

    **Returns:** `(Phi, dPhi, Phi_u)` (and `ddPhi` with `second`), each `(num_windows, N)`
    (s and 1/s units folded in): `Phi @ g` ~ `int phi_k g dt`, `dPhi @ g` ~ `int phi_k' g dt`,
    `ddPhi @ g` ~ `int phi_k'' g dt`, `Phi_u` the input's weights.
    """
    starts = check_window(num_samples, width, stride, power)
    phi, dphi, ddphi, held_w = bump_functions(width, dt, power)
    out = (_place(phi, starts, num_samples), _place(dphi, starts, num_samples),
           _place(held_w if held else phi, starts, num_samples))
    return (*out, _place(ddphi, starts, num_samples)) if second else out


def window_grams(kernels, num_windows: int, stride: int) -> np.ndarray:
    """Every `A @ B.T` of quadrature matrices that place one kernel per window (those of
    `window_quadrature`: row `k` is the kernel on samples `[k stride, k stride + width)`),
    from the kernels alone.

    Two windows overlap when their starts are less than `width` apart, so each product is a
    band of `2 (width - 1) // stride + 1` diagonals, constant along each: `O(width^2 / stride)`
    work instead of the dense product's `O(W^2 N)`, which took most of a long accelerometer
    record's update.

    **Arguments:**

    - `kernels`: `c` arrays `(width,)` of quadrature weights.
    - `num_windows`: the number of windows `W`.
    - `stride`: the step between windows' starts, samples.

    **Returns:** the products `(c, c, W, W)`: `[i, j]` is `A_i @ A_j.T`."""
    width = len(kernels[0])
    k = np.arange(num_windows)
    out = np.zeros((len(kernels), len(kernels), num_windows, num_windows))
    for o in range(-((width - 1) // stride), (width - 1) // stride + 1):
        rows = k[max(0, -o):num_windows - max(0, o)]
        shift = abs(o) * stride  # how far the later of windows k and k + o starts after the other
        early, late = (slice(shift, None), slice(None, width - shift)) if o >= 0 else \
            (slice(None, width - shift), slice(shift, None))
        for i, a in enumerate(kernels):
            for j, b in enumerate(kernels):
                out[i, j, rows, rows + o] = np.dot(a[early], b[late])
    return out


def window_filter(kernel: np.ndarray, stride: int, x: np.ndarray) -> np.ndarray:
    """`int chi_k g dt` on every window: `x (R, N, c)` through one kernel `(width,)` of
    quadrature weights placed every `stride` samples (what a matrix of
    `window_quadrature` does, without the `(W, N)` matrix).

    **Arguments:**

    - `kernel`: the quadrature weights on one window, `(width,)`.
    - `stride`: the step between windows' starts, samples.
    - `x`: the signals `(R, N, c)`.

    **Returns:** the integrals `(R, W, c)`, `W = (N - width) // stride + 1`."""
    view = np.lib.stride_tricks.sliding_window_view(x, len(kernel), axis=1)[:, ::stride]  # (R, W, c, width)
    return view @ kernel


def derivative_terms(lib: Library, x, u, pairs, *, grid: int = 8193) -> dict[int, np.ndarray]:
    """The library terms that are a time derivative `g(q_j) v_j = d G(q_j) / dt`, and `G`.

    A term qualifies when, on 64 sampled points, it scales with `v_j` (by 2 and by -1/2) and
    does not change when every other state and input is redrawn; `G` is its cumulative
    trapezoid integral in `q_j` on the grid.

    **Arguments:**

    - `lib`: the library of `K` candidate terms.
    - `x`: states `(R, N, m)` (estimates where not measured).
    - `u`: inputs `(R, N, n)`.
    - `pairs`: `(position index, velocity index)` of the states whose velocity is not
      measured.
    - `grid`: the points of the antiderivative's grid over the measured displacement range
      (default 8193).

    **Returns:** `{column: G(q_j(t))}`, each `(R, N)`, for the qualifying columns.
    """
    x, u = np.asarray(x, dtype=np.float64), np.asarray(u, dtype=np.float64)
    m = x.shape[-1]
    flat_x, flat_u = x.reshape(-1, m), u.reshape(-1, u.shape[-1])
    rng = np.random.default_rng(0)
    rows = rng.choice(flat_x.shape[0], 64)
    others = rng.choice(flat_x.shape[0], 64)
    p, pu = flat_x[rows], flat_u[rows]
    t0 = np.asarray(lib(p, pu))
    tol = 1e-9 * (np.abs(t0) + np.max(np.abs(t0), axis=0) + 1e-300)
    found: dict[int, np.ndarray] = {}
    for qi, vi in pairs:
        ok = np.any(np.abs(t0) > 0, axis=0)
        for c in (2.0, -0.5):
            pc = p.copy()
            pc[:, vi] *= c
            ok &= np.all(np.abs(np.asarray(lib(pc, pu)) - c * t0) <= abs(c) * tol, axis=0)
        po = flat_x[others].copy()
        po[:, [qi, vi]] = p[:, [qi, vi]]
        ok &= np.all(np.abs(np.asarray(lib(po, flat_u[others])) - t0) <= tol, axis=0)
        cols = [k for k in np.flatnonzero(ok) if k not in found]
        if not cols:
            continue
        q = flat_x[:, qi]
        lo, hi = float(min(q.min(), 0.0)), float(max(q.max(), 0.0))
        pad = 1e-6 * (hi - lo) + 1e-300
        s = np.unique(np.concatenate([np.linspace(lo - pad, hi + pad, grid), [0.0]]))
        pts = np.repeat(flat_x[:1], s.size, axis=0)
        pts[:, qi], pts[:, vi] = s, 1.0
        g = np.asarray(lib(pts, np.repeat(flat_u[:1], s.size, axis=0)))[:, cols]
        G = np.concatenate([np.zeros((1, len(cols))), np.cumsum((g[1:] + g[:-1]) / 2 * np.diff(s)[:, None], axis=0)])
        for j, k in enumerate(cols):
            found[int(k)] = np.interp(x[..., qi], s, G[:, j])
    return found


# Each of these one program: called eagerly, each operation was one (a new process traces,
# lowers and loads every program it meets, ~10 ms each).
@eqx.filter_jit
def _input_rates(nominal: LinearSecondOrder, u):
    """The nominal rates at the zero state under `u (R, N, n)` less those without input,
    `(R, N, m)`, and the rate at the zero state and input `(m,)`."""
    f_0 = nominal.rate(jnp.zeros(nominal.m), jnp.zeros(nominal.n))
    return jax.vmap(nominal.rate_batch)(jnp.zeros(u.shape[:-1] + (nominal.m,)), u) - f_0, f_0


@eqx.filter_jit
def _windowed_library(lib, Phi, full, u, spread):
    """The library's columns integrated against the test functions `Phi (W, N)`, per record
    of the states `full (R, N, m)` and inputs `u (R, N, n)`: `(R, W, K)`."""
    return jax.vmap(lambda a, b: Phi @ lib(a, b, smoothing=spread))(full, u)


@eqx.filter_jit
def _rate_jacobian(nominal: LinearSecondOrder) -> jax.Array:
    """The nominal rate's Jacobian in the states `(m, m)`."""
    return jax.jacfwd(nominal.rate)(jnp.zeros(nominal.m), jnp.zeros(nominal.n))


def _operators(nominal: LinearSecondOrder, x_index):
    """Per regressed equation and measured column, the weights `(alpha, beta, gamma)` of
    `Phi`, `dPhi`, `ddPhi` in `y_i = -sum_r (alpha Phi + beta dPhi + gamma ddPhi) x_r + ...`.

    Returns `(q, p, 3)`, from `int phi x_s` and `int phi' x_s` written on measured
    columns, and the nominal Jacobian."""
    x_index = tuple(x_index)
    d, m = nominal.d, nominal.m
    J = np.asarray(_rate_jacobian(nominal))
    integral = np.zeros((m, len(x_index), 3))  # int phi x_s = sum_r w . (Phi, dPhi, ddPhi) x_r
    derivative = np.zeros((m, len(x_index), 3))  # int phi' x_s
    for s in range(m):
        if s in x_index:
            r = x_index.index(s)
            integral[s, r, 0], derivative[s, r, 1] = 1.0, 1.0
        else:  # an unmeasured velocity v_j = q_j'
            r = x_index.index(s - d)
            integral[s, r, 1], derivative[s, r, 2] = -1.0, -1.0
    idx = list(nominal.regressed_index)
    return derivative[idx] + np.einsum("is,srk->irk", J[idx], integral)


def _bandwidth(cov: np.ndarray) -> int:
    """The largest `|i - j|` of a nonzero `cov[i, j]`."""
    i, j = np.nonzero(cov)
    return int(np.max(np.abs(i - j))) if i.size else 0


def _as_band(cov: np.ndarray, band: int) -> np.ndarray:
    """`cov (W, W)` in LAPACK's lower band storage when only `band` diagonals either side
    are nonzero and that saves work (`band < W / 8`), else `cov` itself."""
    W = cov.shape[0]
    if band >= W // 8:
        return cov
    return np.stack([np.concatenate([np.diagonal(cov, -o), np.zeros(o)]) for o in range(band + 1)])


def _whitener(cov: np.ndarray):
    """`b -> chol(cov)^-1 b` and `log det cov`, a relative jitter of 1e-10 on the diagonal.
    Without the states' error the rows' covariance is a band (only overlapping windows
    correlate): its Cholesky factor then costs `O(W band^2)` instead of `O(W^3)`.

    `cov`: `(W, W)`, or `(band + 1, W)` in lower band storage (`_as_band`)."""
    from scipy.linalg import cholesky_banded, lapack, solve_triangular

    W = cov.shape[1]
    banded = cov.shape[0] != W
    diagonal = cov[0] if banded else np.diagonal(cov)
    jitter = 1e-10 * np.sum(diagonal) / W
    if not banded:
        chol = np.linalg.cholesky(cov + jitter * np.eye(W))
        return (lambda b: solve_triangular(chol, b, lower=True)), 2 * float(np.sum(np.log(np.diag(chol))))
    lower = cov.copy()
    lower[0] += jitter
    factor = cholesky_banded(lower, lower=True)

    def solve(b):
        x, info = lapack.dtbtrs(factor, np.reshape(b, (W, -1)), uplo="L")
        if info != 0:
            raise np.linalg.LinAlgError(f"banded triangular solve failed (info {info})")
        return x.reshape(np.shape(b))

    return solve, 2 * float(np.sum(np.log(factor[0])))


def reml_weight(L, Y, S_x, S_w) -> float:
    """The equation error's weight `lambda` in `S_x + lambda S_w`: its posterior mean under
    the restricted likelihood of the whole library's least-squares residual and a log-uniform
    prior over `_ERROR_GRID` (relative to the traces). The mode would often sit at the
    boundary, no error at all, where the likelihood is flat, and then let spurious terms in.

    **Arguments:**

    - `L`: the library columns `(R, W, K)`.
    - `Y`: one equation's targets `(R, W)`.
    - `S_x`: the rows' covariance from the sensor noise, `(W, W)`.
    - `S_w`: the rows' covariance of a unit white equation error, `(W, W)`.

    **Returns:** `lambda`, a float (0 when the columns leave no residual degrees of freedom)."""
    R = L.shape[0]
    unit = np.trace(S_x) / np.trace(S_w)
    lams, lls = _ERROR_GRID * unit, []
    band = max(_bandwidth(S_x), _bandwidth(S_w))
    S_x, S_w = _as_band(S_x, band), _as_band(S_w, band)
    for lam in lams:
        solve, logdet = _whitener(S_x + lam * S_w)
        X = np.concatenate([solve(L[r]) for r in range(R)])
        y = np.concatenate([solve(Y[r]) for r in range(R)])
        U, sv, _ = np.linalg.svd(X, full_matrices=False)
        keep = sv > 1e-10 * sv[0]
        dof = y.size - int(keep.sum())
        if dof <= 0:
            return 0.0
        resid = y - U[:, keep] @ (U[:, keep].T @ y)
        lls.append(-0.5 * (dof * np.log(resid @ resid / dof) + R * logdet + 2 * np.sum(np.log(sv[keep]))))
    w = np.exp(np.asarray(lls) - np.max(lls))
    return float(np.sum(w * lams) / np.sum(w))


def effective_share(L, Y, cov) -> float:
    """`n_eff / n` of the whitened rows: arviz's ESS of the whole library's least-squares
    residual, summed over records, at most 1.

    Where the fit absorbs more than half the rows' dimensions (a short record's few windows
    and a large library), the residual is mostly the fit's projection, or rounding when
    nothing is left: its ESS says nothing about the errors (it changed with the BLAS's thread
    count), so the share is 1, the covariance's whitening trusted.

    **Arguments:**

    - `L`: the library columns `(R, W, K)`.
    - `Y`: one equation's targets `(R, W)`.
    - `cov`: the rows' covariance `(W, W)`.

    **Returns:** the share `n_eff / n`, a float, at most 1."""
    import arviz_stats as az

    R, W, K = L.shape
    solve, _ = _whitener(_as_band(cov, _bandwidth(cov)))
    X = np.stack([solve(L[r]) for r in range(R)])
    y = np.stack([solve(Y[r]) for r in range(R)])
    coef, _, rank, _ = np.linalg.lstsq(X.reshape(-1, K), y.reshape(-1), rcond=1e-10)
    if R * W - rank < R * W / 2:
        return 1.0
    resid = y - X @ coef
    n_eff = sum(float(az.ess(r[None], method="mean")) for r in resid)
    return float(min(n_eff / (R * W), 1.0))


@jax.jit
def weak_stats(Y, L, cov) -> sampler.SuffStats:
    """Whitened weak-form statistics of every regressed equation, pooled over records.

    **Arguments:**

    - `Y`: the weak targets `(R, W, q)`.
    - `L`: the weak library columns `(R, W, K)`.
    - `cov`: the rows' noise covariance per equation `(q, W, W)` (the same in every record;
      only its shape matters, the sampler fits the scale).

    **Returns:** `SuffStats` batched over the `q` equations (`n = R W` rows).
    """

    def one(y, c):
        jitter = 1e-10 * jnp.trace(c) / c.shape[0] + jnp.finfo(c.dtype).tiny
        chol = jnp.linalg.cholesky(c + jitter * jnp.eye(c.shape[0], dtype=c.dtype))
        solve = lambda b: jax.scipy.linalg.solve_triangular(chol, b, lower=True)  # noqa: E731
        Lw = jax.vmap(solve)(L).reshape(-1, L.shape[-1])
        yw = jax.vmap(solve)(y).reshape(-1)
        return sampler.SuffStats(Lw.T @ Lw, Lw.T @ yw, yw @ yw, jnp.asarray(float(Lw.shape[0]), c.dtype))

    return jax.vmap(one, in_axes=(2, 0))(Y, cov)


def _library_states(nominal, x, x_index, u, dt, hw, noise_var, interpolation):
    """The states the library is evaluated at `(R, N, m)`, the variances of their
    estimation error (`(m,)`, for the non-smooth terms' regression calibration) and how an
    unmeasured velocity was estimated.

    Displacements are Savitzky-Golay smoothed (the noise of a nonlinear term is not in the
    rows' covariance: a cubic stiffness of noisy displacements picks velocity terms); a
    measured velocity stays raw (smoothing blunts its reversals, and sign(v) with them). An
    unmeasured velocity is the derivative of its displacement: Savitzky-Golay at half the
    states' width (sharper reversals; its noise goes into the calibration) where the filter
    can reach 8x the fastest mode below Nyquist, else the state-space smoother's."""
    R, N, _ = x.shape
    full = np.zeros((R, N, nominal.m))
    full[..., list(x_index)] = x
    positions = [r for r, i in enumerate(x_index) if i not in nominal.velocity_index]
    full[..., [x_index[r] for r in positions]] = np.asarray(savgol_states(x[..., positions], hw))
    missing = [(i - nominal.d, i) for i in range(nominal.m) if i not in x_index]
    spread = np.zeros(nominal.m)
    if not missing:
        return full, spread, None
    if not savgol_design_ok(nominal, dt):
        from dtwin_jax.preprocess.estimate import state_smoother

        smoothed, _, _ = state_smoother(nominal, dt, x, x_index, u, interpolation=interpolation)
        for _, vi in missing:
            full[..., vi] = smoothed[..., vi]
        return full, spread, "state-space smoother"
    vhw = max(3, hw // 2)
    taps = savgol_coefficients(vhw, 4, deriv=1, dt=dt)
    for qi, vi in missing:
        r = x_index.index(qi)
        full[..., vi] = np.asarray(smooth(x[..., [r]], vhw, order=4, deriv=1, dt=dt))[..., 0]
        spread[vi] = noise_var[r] * np.sum(taps**2)
    return full, spread, f"savitzky-golay derivative (order 4, half width {vhw})"


def weak_input_output_stats(nominal: LinearSecondOrder, lib: Library, t, x, u, *, x_index=None,
                            width: int | None = None, stride: int | None = None, power: int = TEST_POWER,
                            interpolation: str = "held", noise_var=None,
                            equation_error: bool = True, reference=None) -> tuple[sampler.SuffStats, dict]:
    """Weak-form statistics from measured states without rates.

    Long records are cut into segments, each a record of its own. Raises `DataError` when the
    shapes disagree or a displacement or extra state is not measured.

    **Arguments:**

    - `nominal`: the nominal model.
    - `lib`: the library of `K` candidate terms.
    - `t`: the sample times `(N,)`, s (uniform).
    - `x`: the measured states `x_index`, `(R, N, p)`.
    - `u`: inputs `(R, N, n)`.
    - `x_index`: the indices of the measured states (default all `m`): every displacement
      and extra state must be measured, a velocity may be missing.
    - `width`: the window in samples (default: from `weak_windows`).
    - `stride`: the step between windows' starts in samples (default: from `weak_windows`).
    - `power`: p of the test functions `(s (1 - s))^p` (default `TEST_POWER`).
    - `interpolation`: the inputs between samples: `"held"` (default) integrates them exactly
      over each step; another (`"linear"`, `"bandlimited"`) by the trapezoid rule; it also
      reaches the state-space smoother of an unmeasured velocity.
    - `noise_var`: the measured states' noise variances `(p,)` (default: from the
      Savitzky-Golay residual of each, pooled over records).
    - `equation_error`: add a white equation error to the rows' covariance, its size by
      restricted maximum likelihood, and weigh the rows by their effective share (default
      True; False: measurement noise only).
    - `reference`: a closed loop's reference signal `(R, N, r)`, or None; given, it is the
      instrument of a two-stage least squares (`dtwin_jax.preprocess.instruments`).

    **Returns:** `(stats, info)`: `SuffStats` batched over the regressed equations, and a
    description dict (window, noise, equation error share, velocities estimated ...).
    """

    t = np.asarray(t, dtype=np.float64)
    x, u = np.asarray(x, dtype=np.float64), np.asarray(u, dtype=np.float64)
    x_index = tuple(range(nominal.m)) if x_index is None else tuple(x_index)
    if x.ndim != 3 or u.ndim != 3 or x.shape[:2] != u.shape[:2] or x.shape[1] != t.size:
        raise DataError(f"weak form needs x (R, N, p) and u (R, N, n) on t (N,), got {x.shape}, {u.shape}, {t.shape}")
    if x.shape[2] != len(x_index) or not weak_layout_supported(nominal, x_index):
        raise DataError(f"weak form needs every displacement and extra state of the {nominal.m} measured, "
                        f"got {x.shape[2]} columns for states {[i + 1 for i in x_index]}")
    dt = float(t[1] - t[0])
    default_width, default_stride = weak_windows(nominal, dt, t.size)
    width = default_width if width is None else int(width)
    stride = default_stride if stride is None else int(stride)
    hw = auto_half_width(nominal, dt, t.size)
    if noise_var is None:
        noise_var = np.mean(np.asarray(noise_std(x, hw)) ** 2, axis=0)
    noise_var = np.asarray(noise_var, dtype=np.float64)
    samples = x.shape[0] * x.shape[1]
    full, spread, velocity = _library_states(nominal, x, x_index, u, dt, hw, noise_var, interpolation)
    if reference is not None:  # the states and inputs the reference explains
        fitted = reference_fit(np.concatenate([full, u], axis=-1), reference, dt)
    missing = [(i - nominal.d, i) for i in range(nominal.m) if i not in x_index]
    length = _segment_length(t.size, width, stride)
    if length < t.size:  # a long record: segments, each a record of its own
        x, u, full = cut_segments(x, length), cut_segments(u, length), cut_segments(full, length)
        if reference is not None:
            fitted = cut_segments(fitted, length)
    R, N, _ = x.shape
    Phi, dPhi, Phi_u, ddPhi = window_quadrature(N, dt, width, stride, power, held=interpolation == "held",
                                                second=True)
    ops = _operators(nominal, x_index)  # (q, p, 3)
    # The targets: linear in the measured states, nothing differentiated.
    integrals = np.stack([np.einsum("wn,rnp->rwp", M, x) for M in (Phi, dPhi, ddPhi)], axis=-1)  # (R, W, p, 3)
    f_u, f_0 = (np.asarray(a) for a in _input_rates(nominal, jnp.asarray(u)))
    idx = list(nominal.regressed_index)
    Y = -(np.einsum("rwpk,ipk->rwi", integrals, ops) + np.einsum("wn,rni->rwi", Phi_u, f_u[..., idx])
          + Phi.sum(axis=1)[None, :, None] * f_0[idx][None, None])
    # The library at the states; the exact time derivatives by parts.
    L = np.array(_windowed_library(lib, jnp.asarray(Phi), jnp.asarray(full), jnp.asarray(u), jnp.asarray(spread)))
    by_parts = derivative_terms(lib, full, u, missing) if missing else {}
    for k, G in by_parts.items():
        L[..., k] = -np.einsum("wn,rn->rw", dPhi, G)
    # The rows' covariance: sensor noise through the operators, plus the equation error.
    phi, dphi, ddphi, _ = bump_functions(width, dt, power)
    grams = window_grams((phi, dphi, ddphi), Phi.shape[0], stride)  # (3, 3, W, W)
    S_x = np.einsum("p,ipa,ipb,abvw->ivw", noise_var, ops, ops, grams)
    S_w = grams[0, 0]
    weights = np.zeros(len(idx))
    if equation_error:
        Ls = L / np.maximum(np.linalg.norm(L.reshape(-1, L.shape[-1]), axis=0), 1e-300)
        some = np.unique(np.linspace(0, R - 1, max(1, min(R, _REML_ROWS // L.shape[1]))).round().astype(int))
        for i in range(len(idx)):
            weights[i] = reml_weight(Ls[some], Y[some, :, i], S_x[i], S_w)
    cov = S_x + weights[:, None, None] * S_w[None]
    if reference is None:
        stats = weak_stats(jnp.asarray(Y), jnp.asarray(L), jnp.asarray(cov))
    else:
        m = nominal.m
        Z = np.array(jax.vmap(lambda a, b: jnp.asarray(Phi) @ lib(a, b))(jnp.asarray(fitted[..., :m]),
                                                                        jnp.asarray(fitted[..., m:])))
        stats = instrumented_stats(Y, L, Z, cov)
    scale = np.ones(len(idx))
    if equation_error:  # what whitening leaves correlated (coloured model error) counts once
        for i in range(len(idx)):
            scale[i] = effective_share(Ls, Y[..., i], cov[i])
        stats = sampler.weigh(sampler.SuffStats(*(np.asarray(a) for a in stats)), scale)
    names = nominal.state_names
    info = {"method": "weak-form", "width": width, "stride": stride, "power": power, "windows": int(Phi.shape[0]),
            "whitened": "white sensor noise" + (" and a white equation error (REML)" if equation_error else ""),
            "state_noise_std": np.sqrt(noise_var).tolist(), "segments": int(R), "segment_samples": int(N),
            "samples_used": int(R * N), "samples": int(samples),
            "effective_share": scale.tolist(),
            "equation_error_share": [float(w * np.trace(S_w) / (w * np.trace(S_w) + np.trace(S_x[i])))
                                     for i, w in enumerate(weights)],
            "velocities_estimated": [names[v] for _, v in missing], "velocity_estimate": velocity,
            "integrated_by_parts": sorted(lib.names[k] for k in by_parts),
            **({"instrument": "the reference's lags (two-stage least squares)"} if reference is not None else {})}
    return stats, info
