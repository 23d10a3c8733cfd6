"""The weak (integral) form of framework 1: states without rates, nothing differentiated.

Each regressed equation ``x_i' = f_i(x, u) + Theta(x, u) theta`` is multiplied by test
functions ``phi_k(t) = (s (1 - s))^p`` on windows of the record (``s`` runs 0..1 over the
window) and integrated; ``phi_k`` vanishes at the window's ends, so by parts
``y_k = -int phi_k' x_i dt - int phi_k f_i(x, u) dt = int phi_k Theta(x, u) dt theta``:
the rate never appears. Windows overlap, so the rows' noise is correlated; each equation's
rows are whitened by their covariance under white measurement noise on the states
(``Cov = sum_j s_j^2 A_j A_j^T`` with ``A_j = d y / d x_j`` through ``phi'`` and the nominal
Jacobian), so the sampler's iid-noise model holds and its intervals are honest. Input noise
is left out of that covariance (a white input cannot be told from white noise on it).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax import sampler
from dtwin_jax.denoise import auto_half_width, noise_std
from dtwin_jax.errors import DataError
from dtwin_jax.library import Library
from dtwin_jax.measurement import highest_natural_frequency_hz
from dtwin_jax.systems import LinearSecondOrder

__all__ = ["weak_windows", "weak_window_fits", "window_quadrature", "weak_stats", "weak_input_output_stats"]

_POWER = 6


# The dense quadrature matrices (3 x windows x samples) the default route may build; past
# this the automatic choice keeps the Savitzky-Golay route (a banded form would lift it).
_MAX_QUADRATURE_BYTES = 1 << 30


def _period_samples(nominal: LinearSecondOrder, dt: float, num_samples: int) -> float:
    """One period of the nominal's fastest mode in samples (1 % of the record without stiffness)."""
    f_hz = highest_natural_frequency_hz(nominal)
    return 1.0 / (f_hz * dt) if f_hz > 0 else max(16, num_samples // 100)


def weak_windows(nominal: LinearSecondOrder, dt: float, num_samples: int) -> tuple[int, int]:
    """Default window ``(width, stride)`` in samples: one period of the nominal's fastest
    mode (a 1 % of the record without stiffness), moved by an eighth of it.

    ``dt`` s; ``num_samples`` per record. The width is clipped to the record.
    """
    width = int(round(_period_samples(nominal, dt, num_samples)))
    width = int(min(max(width, 2 * _POWER + 3), num_samples))
    return width, max(1, width // 8)


def weak_window_fits(nominal: LinearSecondOrder, dt: float, num_samples: int) -> bool:
    """Whether the default window (:func:`weak_windows`) spans enough samples for the test
    functions, leaves at least two windows in a record of ``num_samples``, and its dense
    quadrature matrices stay under 1 GiB."""
    width = _period_samples(nominal, dt, num_samples)
    if not (2 * _POWER + 3 <= width and width + width // 8 <= num_samples):
        return False
    windows = num_samples // max(1, int(round(width)) // 8) + 1
    return 3 * windows * num_samples * 8 <= _MAX_QUADRATURE_BYTES


def window_quadrature(num_samples: int, dt: float, width: int, stride: int, power: int = _POWER,
                   held: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Quadrature matrices of the test functions over one record.

    **Arguments:** ``num_samples`` N, ``dt`` s, window ``width`` and ``stride`` (samples),
    ``power`` p of ``phi = (s (1 - s))^p`` (scaled to unit integral), ``held``: the input's
    weights integrate ``phi`` exactly over each held step rather than by the trapezoid rule.

    **Returns:** ``(Phi, dPhi, Phi_u)``, each ``(num_windows, N)`` (s and 1/s units folded
    in): ``Phi @ g`` ~ ``int phi_k g dt``, ``dPhi @ g`` ~ ``int phi_k' g dt``, ``Phi_u``
    the input's weights.
    """
    if width < 2 * power + 3 or width > num_samples:
        raise DataError(f"weak-form window of {width} samples must lie in [{2 * power + 3}, {num_samples}]")
    if stride < 1:
        raise DataError(f"weak-form stride must be >= 1 sample, got {stride}")
    starts = np.arange(0, num_samples - width + 1, stride)
    s = np.arange(width) / (width - 1)
    span = (width - 1) * dt
    base = (s * (1 - s)) ** power
    scale = 1.0 / (np.sum(base) * dt)  # the trapezoid's ends are zero
    phi = scale * base * dt
    dphi = scale * power * (s * (1 - s)) ** (power - 1) * (1 - 2 * s) / span * dt
    # Exact integral of the polynomial phi over each step [s_j, s_j+1] (Gauss-Legendre).
    nodes, weights = np.polynomial.legendre.leggauss(power + 1)
    h = 1.0 / (width - 1)
    mid = s[:-1, None] + h * (nodes[None] + 1) / 2
    held_w = np.zeros(width)
    held_w[:-1] = scale * np.sum(weights * (mid * (1 - mid)) ** power, axis=1) * h / 2 * span
    Phi, dPhi, Phi_u = (np.zeros((starts.size, num_samples)) for _ in range(3))
    for k, a in enumerate(starts):
        Phi[k, a:a + width], dPhi[k, a:a + width] = phi, dphi
        Phi_u[k, a:a + width] = held_w if held else phi
    return Phi, dPhi, Phi_u


@jax.jit
def weak_stats(nominal: LinearSecondOrder, lib: Library, Phi, dPhi, Phi_u, x, u, noise_var) -> sampler.SuffStats:
    """Whitened weak-form statistics of every regressed equation, pooled over records.

    **Arguments:** ``Phi, dPhi, Phi_u (W, N)`` from :func:`window_quadrature`; ``x (R, N, m)``
    states, ``u (R, N, n)`` inputs, ``noise_var (m,)`` the states' white-noise variances
    (units of each state squared; only their ratios matter).

    **Returns:** ``SuffStats`` batched over ``nominal.regressed_index`` (``n = R W`` rows).
    """
    x, u, Phi, dPhi, Phi_u = (jnp.asarray(a) for a in (x, u, Phi, dPhi, Phi_u))
    R, N, m = x.shape
    idx = jnp.asarray(nominal.regressed_index)
    zero_u = jnp.zeros_like(u)
    f_x = jax.vmap(nominal.rate_batch)(x, zero_u)  # the states' part (and F0)
    f_u = jax.vmap(nominal.rate_batch)(jnp.zeros_like(x), u) - jax.vmap(nominal.rate_batch)(jnp.zeros_like(x), zero_u)
    Y = -(jnp.einsum("wn,rnm->rwm", dPhi, x) + jnp.einsum("wn,rnm->rwm", Phi, f_x)
          + jnp.einsum("wn,rnm->rwm", Phi_u, f_u))[..., idx]  # (R, W, q)
    L = jax.vmap(lambda a, b: Phi @ lib(a, b))(x, u)  # (R, W, K)
    J = jax.jacfwd(nominal.rate)(jnp.zeros(m, x.dtype), jnp.zeros(u.shape[-1], x.dtype))  # (m, m)
    eye = jnp.eye(m, dtype=x.dtype)

    def one(i):
        # y's noise from state j's noise: -(delta_ij dPhi + J_ij Phi) eps_j.
        A = eye[i][:, None, None] * dPhi[None] + J[i][:, None, None] * Phi[None]  # (m, W, N)
        cov = jnp.einsum("j,jwn,jvn->wv", noise_var, A, A)
        jitter = 1e-10 * jnp.trace(cov) / cov.shape[0] + jnp.finfo(x.dtype).tiny
        chol = jnp.linalg.cholesky(cov + jitter * jnp.eye(cov.shape[0], dtype=x.dtype))
        solve = lambda b: jax.scipy.linalg.solve_triangular(chol, b, lower=True)  # noqa: E731
        Lw = jax.vmap(solve)(L).reshape(-1, L.shape[-1])
        yw = jax.vmap(solve)(Y[..., jnp.searchsorted(idx, i)]).reshape(-1)
        return sampler.SuffStats(Lw.T @ Lw, Lw.T @ yw, yw @ yw, jnp.asarray(float(Lw.shape[0]), x.dtype))

    return jax.vmap(one)(idx)


def weak_input_output_stats(nominal: LinearSecondOrder, lib: Library, t, x, u, *, width: int | None = None,
                            stride: int | None = None, power: int = _POWER, interpolation: str = "held",
                            noise_var=None) -> tuple[sampler.SuffStats, dict]:
    """Weak-form statistics from measured states without rates.

    **Arguments:** ``t (N,)`` s (uniform), ``x (R, N, m)`` every state measured, ``u (R, N, n)``;
    ``width``/``stride`` in samples (default :func:`weak_windows`), ``power`` of the test
    functions, ``interpolation`` of the inputs (``"held"`` integrates them exactly over each
    step), ``noise_var (m,)`` the states' noise variances (default: from the Savitzky-Golay
    residual of each state, pooled over records).

    **Returns:** ``(SuffStats`` batched over the regressed equations``, description dict)``.
    """
    t = np.asarray(t, dtype=np.float64)
    x, u = np.asarray(x, dtype=np.float64), np.asarray(u, dtype=np.float64)
    if x.ndim != 3 or u.ndim != 3 or x.shape[:2] != u.shape[:2] or x.shape[1] != t.size:
        raise DataError(f"weak form needs x (R, N, m) and u (R, N, n) on t (N,), got {x.shape}, {u.shape}, {t.shape}")
    if x.shape[2] != nominal.m:
        raise DataError(f"weak form needs every one of the {nominal.m} states measured, got {x.shape[2]}")
    dt = float(t[1] - t[0])
    default_width, default_stride = weak_windows(nominal, dt, t.size)
    width = default_width if width is None else int(width)
    stride = default_stride if stride is None else int(stride)
    Phi, dPhi, Phi_u = window_quadrature(t.size, dt, width, stride, power, held=interpolation == "held")
    if noise_var is None:
        hw = auto_half_width(nominal, dt, t.size)
        noise_var = np.mean(np.asarray(noise_std(x, hw)) ** 2, axis=0)
    stats = weak_stats(nominal, lib, Phi, dPhi, Phi_u, x, u, jnp.asarray(noise_var, dtype=jnp.float64))
    info = {"method": "weak-form", "width": width, "stride": stride, "power": power, "windows": int(Phi.shape[0]),
            "whitened": "white state noise", "state_noise_std": np.sqrt(np.asarray(noise_var)).tolist()}
    return stats, info
