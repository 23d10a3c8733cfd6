"""Framework 2 (output-only): Kramers-Moyal regression targets for drift and diffusion.

The measured states are a diffusion `dX = (A X + S h(X)) dt + G dB` (Eq. 18): `A X` the
linear nominal model, `h` the perturbation of the regressed rows (`S` puts them in place),
`G G^T` the diffusion. Measured states carry white noise `eps ~ N(0, diag(s^2))`.

Drift (Eq. 20a, 23a), with what makes it hold on stiff, noisy data:

* The nominal model is removed with its exact one-step propagator, not an Euler step:
  `dZ_k = X_{k+1} - Phi X_k` with `Phi = exp(A dt)`, and `Y_k = Psi^-1 dZ_k` with
  `Psi = int_0^dt exp(A s) ds`, so `E[Y_k | X_k] = h(X_k) + dt/2 (Lh)(X_k) + O(dt^2)`.
* The library at sample `k` is regressed on the target of the step `k+1 -> k+2`, which holds
  no noise of sample `k` (with the same sample, moderate noise makes a spurious damping term).
  The shift and the drift's change over the step go into the regressors,
  `L + 3/2 dt dL/dt + 7/6 dt^2 d^2L/dt^2`, with the time derivatives taken along the model's
  drift (nominal plus the current estimate of `h`; two passes): not small when `h` is stiff,
  and not to be taken from the measured path, whose Brownian velocity would put noise into a
  velocity term's regressor (and attenuate a cubic damping).
* Errors in variables: `E[L_a L_b (X + eps)] = L_a L_b + 1/2 sum_j s_j^2 d_j^2 (L_a L_b)`
  to second order, and likewise for `L^T Y`; both are subtracted. For monomials up to
  degree 3 this is exact (`x^3 -> x^3 - 3 s^2 x`).

Diffusion (Eq. 20b, 23b): the squared increment `dZ_i^2 / dt` of a velocity after the drift
is removed. White noise adds `2 s^2 / dt` to it, many times the diffusion itself at moderate
noise, so raw squared increments are useless. Here the increments are pre-averaged over
a triangular window of `K ~ sqrt(48 s^2 / (Gamma dt))` samples (Jacod et al. 2009), which
balances signal and noise, and the known noise part is subtracted. That is a fast first
guess; the diffusion itself is the likelihood maximum of `dtwin_jax.output_only.statespace`.

The noise variances `s_j^2` come from the data: `Var(X_{k+L} - X_k) = 2 s^2 + L Gamma dt +
L^2 D` for lags `L = 1, 2, 3` cancels the diffusion `Gamma` and the drift `D`.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax import sampler
from dtwin_jax.library import Library, monomials
from dtwin_jax.linalg import expm, mass_solve
from dtwin_jax.models.systems import LinearSecondOrder

__all__ = [
    "state_matrix",
    "propagators",
    "noise_variance",
    "drift_targets",
    "drift_statistics",
    "preaveraged_diffusion",
    "unit_gramian",
    "process_covariances",
    "gramians",
]


def state_matrix(nominal: LinearSecondOrder) -> jax.Array:
    """The state matrix `A (m, m)` of the nominal model, `dX/dt = A X + B_x u`.

    **Arguments:**

    - `nominal`: the nominal model `LinearSecondOrder`.

    **Returns:** `A`, shape `(m, m)`: the identity in the displacements' rows (their rates are
    the velocities), `-M^-1 [K C]` in the velocities' rows, zero rows for any further states."""
    d, m = nominal.d, nominal.m
    gain = mass_solve(nominal.M, jnp.concatenate([nominal.K, nominal.C], axis=1))
    A = jnp.zeros((m, m), gain.dtype)
    return A.at[:d, d : 2 * d].set(jnp.eye(d)).at[d : 2 * d, : 2 * d].set(-gain)


def trapezoid_propagators(nominal: LinearSecondOrder, dt: float) -> tuple[jax.Array, jax.Array]:
    """The trapezoid propagators of the nominal model's forced response over one step (Van Loan).

    **Arguments:**

    - `nominal`: the nominal model `LinearSecondOrder`.
    - `dt`: the step, s.

    **Returns:** `(Psi_0, Psi_1)`, `(m, m)` each: `int_0^dt exp(A (dt - s)) h(s) ds =
    Psi_0 h(0) + Psi_1 h(dt)` for `h` linear over the step."""
    A = state_matrix(nominal)
    m = A.shape[0]
    eye = jnp.eye(m, dtype=A.dtype)
    block = jnp.zeros((3 * m, 3 * m), A.dtype)
    block = block.at[:m, :m].set(A).at[:m, m : 2 * m].set(eye).at[m : 2 * m, 2 * m :].set(eye)
    E = expm(block * dt)
    Psi, ramp = E[:m, m : 2 * m], E[:m, 2 * m :] / dt
    return Psi - ramp, ramp


def propagators(nominal: LinearSecondOrder, dt: float) -> tuple[jax.Array, jax.Array]:
    """The nominal model's one-step propagators (Van Loan).

    **Arguments:**

    - `nominal`: the nominal model `LinearSecondOrder`.
    - `dt`: the step, s.

    **Returns:** `(Phi, Psi)`: `Phi = exp(A dt)` and `Psi = int_0^dt exp(A s) ds`, both `(m, m)`."""
    A = state_matrix(nominal)
    m = A.shape[0]
    block = jnp.zeros((2 * m, 2 * m), A.dtype).at[:m, :m].set(A).at[:m, m:].set(jnp.eye(m))
    E = expm(block * dt)
    return E[:m, :m], E[:m, m:]


@functools.partial(jax.jit, static_argnames="per_record")  # one program: op by op, ten compile
def noise_variance(x, per_record: bool = False) -> jax.Array:
    """White measurement-noise variances of measured states.

    Third and fourth differences: white noise adds `C(2p, p) s^2` to the mean square of the
    `p`-th difference, a Brownian velocity `C(2p-2, p-1) Gamma dt`, and a smooth signal only
    `O((omega dt)^(2p))`; `V_4 - (10/3) V_3 = (10/3) s^2` cancels the Brownian part.

    **Arguments:**

    - `x`: measured states, shape `(R, N, m)`.
    - `per_record`: False (default) to pool over records, True for one estimate per record.

    **Returns:** the noise variances `s^2` (the states' units squared, floored at zero), shape
    `(m,)` pooled, or `(R, m)` with `per_record`.
    """
    x = jnp.asarray(x)
    axis = 1 if per_record else (0, 1)
    V3 = jnp.mean(jnp.diff(x, n=3, axis=1) ** 2, axis=axis)
    V4 = jnp.mean(jnp.diff(x, n=4, axis=1) ** 2, axis=axis)
    return jnp.maximum(0.3 * V4 - V3, 0.0)


def drift_targets(nominal: LinearSecondOrder, x, dt: float) -> jax.Array:
    """Kramers-Moyal drift targets `Y_k = [Psi^-1 (X_{k+1} - Phi X_k)]_r` of the regressed rows.

    **Arguments:**

    - `nominal`: the nominal model `LinearSecondOrder` (its exact propagators `Phi`, `Psi`).
    - `x`: measured states, shape `(R, N, m)`.
    - `dt`: the sample interval, s.

    **Returns:** `Y`, shape `(R, N - 1, r)`, in rate units (the regressed states' units / s)."""
    Phi, Psi = propagators(nominal, dt)
    x = jnp.asarray(x)
    dZ = x[:, 1:] - x[:, :-1] @ Phi.T
    Y = jnp.linalg.solve(Psi, dZ.reshape(-1, nominal.m).T).T.reshape(dZ.shape)
    return Y[..., jnp.asarray(nominal.regressed_index)]


def _directional(fn, x, e):
    """First and second derivatives of `fn` at `x` along `e` (forward over forward)."""
    g = lambda z: jax.jvp(fn, (z,), (e,))[1]
    return jax.jvp(g, (x,), (e,))


def _derivatives(lib: Library, x, smoothing=None):
    """Per state `j`, `d_j L` and `d_j^2 L`, each `(m, P, K)`, at `x (P, m)`, block by block
    in library order: monomials in closed form, the other families by differentiation (on
    a large monomial library that took most of the drift statistics' time)."""
    d1, d2, start = [], [], 0
    for family, idx in lib.blocks:
        if family == "poly":
            p1, p2 = _monomial_derivatives(x, np.asarray(idx, dtype=int).reshape(len(idx), -1))
        else:
            p1, p2 = _differentiated(lib.subset(np.arange(start, start + len(idx))), x, smoothing)
        d1.append(p1)
        d2.append(p2)
        start += len(idx)
    return jnp.concatenate(d1, axis=-1), jnp.concatenate(d2, axis=-1)


def _differentiated(lib: Library, x, smoothing=None):
    """`d_j L` and `d_j^2 L`, each `(m, P, K)`, at `x (P, m)`, forward over forward."""
    f = lambda z: lib.eval_single(z, None, smoothing)
    eye = jnp.eye(x.shape[-1], dtype=x.dtype)
    d1, d2 = jax.vmap(lambda xk: jax.vmap(lambda e: _directional(f, xk, e))(eye))(x)
    return jnp.moveaxis(d1, 1, 0), jnp.moveaxis(d2, 1, 0)


def _monomial_derivatives(x, exponents):
    """`d_j x^e = e_j x^(e - u_j)` and `d_j^2 x^e = e_j (e_j - 1) x^(e - 2 u_j)`, each
    `(m, P, Kp)`, of the monomials `exponents (Kp, m)` at `x (P, m)`."""
    unit = np.eye(x.shape[-1], dtype=int)
    d1, d2 = [], []
    for j, e in enumerate(exponents.T):
        d1.append(e * monomials(x, np.maximum(exponents - unit[j], 0)))
        d2.append(e * (e - 1) * monomials(x, np.maximum(exponents - 2 * unit[j], 0)))
    return jnp.stack(d1), jnp.stack(d2)


def _along_flow(nominal: LinearSecondOrder, f, x, L, d1, coef):
    """First and second time derivatives of the library along the drift
    `F(x) = A x + S coef L(x)` at `x (P, m)`: `J_L F` and `D^2 L[F, F] + J_L J_F F`, each
    `(P, K)`, from the library's values `L (P, K)` and first derivatives `d1 (m, P, K)`
    (`_derivatives`), `coef (r, K)` the drift perturbation's coefficients, `f` the
    library at one sample. `J_F F = A F + S coef J_L F` needs no derivative of the drift, so
    only `D^2 L[F, F]` takes a second-order forward pass, its tangent held fixed
    (differentiating the drift inside it evaluated the whole library twice more)."""
    reg = jnp.asarray(nominal.regressed_index)
    zero_u = jnp.zeros(nominal.n, x.dtype)
    F = jax.vmap(lambda z: nominal.rate(z, zero_u))(x).at[:, reg].add(L @ coef.T)
    first = jnp.einsum("jpk,pj->pk", d1, F)
    JF = (F @ state_matrix(nominal).T).at[:, reg].add(first @ coef.T)
    curvature = jax.vmap(lambda z, v: jax.jvp(lambda y: jax.jvp(f, (y,), (v,))[1], (z,), (v,))[1])(x, F)
    return first, curvature + jnp.einsum("jpk,pj->pk", d1, JF)


def drift_statistics(
    nominal: LinearSecondOrder,
    lib: Library,
    x,
    dt: float,
    noise_var,
    coef=None,
    *,
    smoothing=None,
    chunk: int = 20000,
    rows=None,
) -> sampler.SuffStats:
    """Noise-corrected sufficient statistics of every regressed drift equation.

    The library at sample `k` is regressed on the target of the step `k+1 -> k+2`, which
    holds no noise of sample `k`; the shift and the drift's change over the step are taken
    into the regressors, `L + 3/2 dt dL/dt + 7/6 dt^2 d^2L/dt^2`, the time derivatives taken
    along the model's drift `A x + S h(x)` at `x_k`. A derivative estimated from the measured
    path instead (a Savitzky-Golay filter) sees a Brownian velocity's roughness, which for a
    velocity term such as `x2**3` acts as noise in the regressor and attenuates it.

    With `smoothing`, the non-smooth families become their Gaussian averages over these
    variances (`Library.__call__`): over the step the velocity moves by a Brownian increment,
    and `E[sign(v_{k+1.5}) | v_k]` is a smoothed sign, which `sign(v_k)` with derivatives that
    vanish almost everywhere cannot see (Coulomb friction came out far off beside spurious
    `x2`, `x2**3`).

    **Arguments:**

    - `nominal`: the nominal model `LinearSecondOrder`.
    - `lib`: the drift `Library` (no inputs).
    - `x`: measured states, shape `(R, N, m)`.
    - `dt`: the sample interval, s.
    - `noise_var`: the states' white-noise variances, shape `(m,)` (the states' units squared).
    - `coef`: `(r, K)` the current estimate of the drift perturbation `S h`, the coefficients
      of `lib`'s terms (smoothed by `smoothing`) in the regressed rows, or None (default) for
      zero.
    - `smoothing`: variances `(m,)` over which the non-smooth families are averaged, or None
      (default) for exact terms. Pass `Gamma tau - s^2` to also undo the measurement noise's
      own smoothing; those columns then get no correction of their mean, only of their
      scatter.
    - `chunk`: samples per chunk of the compiled loop body (default 20000).
    - `rows`: use only the first `rows` samples (of the `R (N - 2)` in record order; may be
      traced), or None (default) for all; chunks past them are skipped, not computed.

    **Returns:** `SuffStats` batched over the `r` regressed states (see the module docstring):
    `gram (r, K, K)`, `xty (r, K)`, `yty (r,)`, `n (r,)` the samples used.
    """
    x = jnp.asarray(x)
    R, N, m = x.shape
    reg = jnp.asarray(nominal.regressed_index)
    Y = drift_targets(nominal, x, dt)[:, 1:].reshape(-1, reg.size)  # steps k+1 -> k+2
    X = x[:, : N - 2].reshape(-1, m)
    coef = jnp.zeros((reg.size, lib.K), X.dtype) if coef is None else jnp.asarray(coef)
    f = lambda z: lib.eval_single(z, None, smoothing)
    s2 = jnp.asarray(noise_var)
    K = lib.K
    poly, exponents, pairs, pair_index = _monomials(lib)
    corrected = jnp.ones(K) if smoothing is None else 1.0 - _smoothed_columns(lib, smoothing)

    def chunk_sums(Xc, Yc, w):
        """Moment sums of one chunk of samples `Xc (c, m)`, `Yc (c, r)`, weights `w (c,)`
        (0 for padding): every term is a product of two per-sample factors."""
        d1, d2 = _derivatives(lib, Xc, smoothing)
        L = lib(Xc, None, smoothing)
        first, second = _along_flow(nominal, f, Xc, L, d1, coef)
        Lt = L + 1.5 * dt * first + (7.0 / 6.0) * dt**2 * second
        # E[L_a L_b (X + eps)] = L_a L_b + 1/2 sum_j s_j^2 (d_j^2 L_a L_b + 2 d_j L_a d_j L_b
        # + L_a d_j^2 L_b): subtract the noise's part, estimated at the noisy states.
        # A smoothed column's mean shift is already undone by its smaller smoothing (no W2);
        # its noise still scatters it (D1, from the smoothed column's derivatives).
        W2 = jnp.einsum("j,jpk->pk", s2, d2) * corrected
        wLt, wW2 = w[:, None] * Lt, w[:, None] * W2
        D1 = (jnp.sqrt(s2)[:, None, None] * d1 * jnp.sqrt(w)[None, :, None]).reshape(-1, K)
        cross = wLt.T @ W2
        plain = wLt.T @ Lt
        gram = plain - 0.5 * (cross + cross.T) - _gram_outside(D1, poly)
        raw_xty = (wLt.T @ Yc).T
        xty = ((wLt - 0.5 * wW2).T @ Yc).T
        if poly.size:
            # Monomials and their products: exact unbiased moments (Hermite), in place of the
            # second-order ones of the L L part (x^5 at 20% noise needs the 4th-order terms).
            T = _hermite_table(Xc, s2, int(exponents.sum(axis=1).max()) * 2)
            Lp, Wp = L[:, poly], W2[:, poly]
            wLp, wWp = w[:, None] * Lp, w[:, None] * Wp
            # (D1's monomial block is left out of both: see _gram_outside.)
            second_order = wLp.T @ Lp - 0.5 * (wLp.T @ Wp + wWp.T @ Lp)
            exact = _hermite_sums(T, pairs, w)[pair_index]
            gram = gram.at[np.ix_(poly, poly)].add(exact - second_order)
            unbiased = _hermite_products(T, exponents)
            xty = xty.at[:, poly].add(((w[:, None] * (unbiased - (Lp - 0.5 * Wp))).T @ Yc).T)
        return gram, plain, xty, raw_xty

    # One compiled chunk body in a loop (a Python loop would compile it once per chunk); the
    # loop's length is dynamic, so a pass over the leading rows shares the program.
    P = X.shape[0]
    size = min(chunk, P)
    count = -(-P // size)
    pad = count * size - P
    used = P if rows is None else jnp.minimum(rows, P)
    w = (jnp.arange(count * size) < used).astype(X.dtype).reshape(count, size)
    Xp = jnp.concatenate([X, jnp.broadcast_to(X[:1], (pad, m))]).reshape(count, size, m)
    Yp = jnp.concatenate([Y, jnp.zeros((pad, reg.size), Y.dtype)]).reshape(count, size, reg.size)

    def add(i, acc):
        return jax.tree.map(jnp.add, acc, chunk_sums(Xp[i], Yp[i], w[i]))

    zeros = (jnp.zeros((K, K)), jnp.zeros((K, K)), jnp.zeros((reg.size, K)), jnp.zeros((reg.size, K)))
    gram, raw_gram, xty, raw_xty = jax.lax.fori_loop(0, -(-used // size), add, zeros)
    # A second-order correction only holds while it is small: exp(-x2) of a velocity with
    # noise std ~1 needs exp(2 s^2), not 1 + 2 s^2. Such columns keep their raw moments;
    # monomials' moments are exact at any noise level.
    valid = (jnp.diagonal(gram) > 0.5 * jnp.diagonal(raw_gram)) | jnp.zeros(K, bool).at[poly].set(True)
    both = valid[:, None] & valid[None, :]
    gram = jnp.where(both, gram, raw_gram)
    xty = jnp.where(valid[None, :], xty, raw_xty)
    q = reg.size
    return sampler.SuffStats(
        jnp.broadcast_to(gram, (q, K, K)), xty, jnp.einsum("p,pr->r", w.reshape(-1)[:P], Y * Y),
        jnp.full(q, 1.0) * used,
    )


def _gram_outside(D, block):
    """`D^T D` `(K, K)` of `D (n, K)`, less its `block x block` part (zero there): the
    noise's scatter term of the monomial pairs, whose exact Hermite moments replace the
    second-order ones whole, so it would only be added and subtracted again. That block
    holds most of the work for the polynomial libraries (example 2: 210 of 256 columns)."""
    K = D.shape[1]
    if not block.size:
        return D.T @ D
    other = np.setdiff1d(np.arange(K), block)
    part = D.T @ D[:, other]  # (K, K - Kp): every pair with a column outside the block
    return jnp.zeros((K, K), D.dtype).at[:, other].set(part).at[other, :].set(part.T)


def _smoothed_columns(lib: Library, smoothing) -> jax.Array:
    """`(K,)` 1.0 where a non-smooth column (`sign`, `Abs`, `x*Abs(y)`) is smoothed (its
    variable's variance in `smoothing (m,)` is positive), else 0.0."""
    variable = []
    for family, idx in lib.blocks:
        variable += [t[-1] if family in ("sign", "abs", "xabs") else -1 for t in idx]
    variable = np.asarray(variable)
    c = jnp.asarray(smoothing)[np.maximum(variable, 0)]
    return jnp.where((variable >= 0) & (c > 0), 1.0, 0.0)


def _monomials(lib: Library):
    """The library's monomial columns: indices `(Kp,)`, exponents `(Kp, m)`, the distinct
    exponents of their pairwise products `(G, m)`, and each pair's row in it `(Kp, Kp)`."""
    index, exponents, start = [], [], 0
    for family, idx in lib.blocks:
        if family == "poly":
            index += range(start, start + len(idx))
            exponents += idx
        start += len(idx)
    exponents = np.asarray(exponents, dtype=int).reshape(len(index), lib.num_states)
    sums = (exponents[:, None, :] + exponents[None, :, :]).reshape(-1, lib.num_states)
    pairs, inverse = np.unique(sums, axis=0, return_inverse=True)
    return np.asarray(index, dtype=int), exponents, pairs, inverse.reshape(len(index), len(index))


def _hermite_table(x, s2, degree: int):
    """`T (P, m, degree + 1)`: `T_n(x_j) = s_j^n He_n(x_j / s_j)`, the polynomials whose
    expectation over `x_j + N(0, s_j^2)` is `x_j^n` (`T_{n+1} = x T_n - n s^2 T_{n-1}`)."""
    rows = [jnp.ones_like(x), x]
    for n in range(1, degree):
        rows.append(x * rows[n] - n * s2 * rows[n - 1])
    return jnp.stack(rows[: degree + 1], axis=-1)


def _hermite_products(T, exponents):
    """`(P, G)`: the unbiased estimate of each monomial `prod_j x_j^e_j` at every sample."""
    m = T.shape[1]
    return jnp.prod(T[:, np.arange(m)[None, :], exponents], axis=-1)


def _hermite_sums(T, exponents, weights):
    """`(G,)`: the `weights (P,)`-weighted sum over samples of `_hermite_products`.

    Each product splits into a factor of the first half of the states and one of the
    second; the sums of all pairs of distinct half-products are one matrix product
    (example 2: 1820 sums from 91 x 91 half-products), unless the halves have so many
    distinct products that the direct sums are cheaper."""
    half = T.shape[1] // 2
    first, i = np.unique(exponents[:, :half], axis=0, return_inverse=True)
    second, j = np.unique(exponents[:, half:], axis=0, return_inverse=True)
    if not half or first.shape[0] * second.shape[0] > 8 * exponents.size:
        return jnp.concatenate([weights @ _hermite_products(T, exponents[k : k + 256])
                                for k in range(0, exponents.shape[0], 256)])
    left = (weights[:, None] * _hermite_products(T[:, :half], first)).T
    sums = left @ _hermite_products(T[:, half:], second)
    return sums[i.reshape(-1), j.reshape(-1)]


def _noise_corrected(fn, s2):
    """`f(x) - 1/2 sum_j s_j^2 d_j^2 f(x)`: unbiased to second order for `f` of noisy `x`."""
    m = s2.shape[0]
    eye = jnp.eye(m)

    def corrected(x):
        second = jax.vmap(lambda e: _directional(fn, x, e)[1])(eye)
        return fn(x) - 0.5 * jnp.einsum("j,j...->...", s2, second)

    return corrected


def preaveraged_diffusion(
    nominal: LinearSecondOrder,
    x,
    dt: float,
    noise_var,
    perturbation,
    *,
    window: int | None = None,
):
    """Pre-averaged, noise-corrected quadratic variation of the velocities, a fast first guess
    for `statespace.diffusion_mle`.

    The drift perturbation is removed over each step by the trapezoid rule (an Euler step
    leaves `dt^2/2 (Lh)`, which for example 2 exceeds the Brownian increment). `h` is
    evaluated at the measured states with its second-order noise bias removed: a smoothed
    state would be better per sample, but its error is slow and adds up over the
    pre-averaging window. Good while the noise per sample stays within a couple of orders of
    magnitude of the Brownian increment; far beyond, the drift's residual dominates.

    **Arguments:**

    - `nominal`: the nominal model `LinearSecondOrder`.
    - `x`: measured states, shape `(R, N, m)`.
    - `dt`: the sample interval, s.
    - `noise_var`: the states' white-noise variances, shape `(m,)` (the states' units squared).
    - `perturbation`: `perturbation(x (m,)) -> (m,)`, the fitted drift perturbation `S h`
      (rate units), like `statespace.DriftStep.perturbation`.
    - `window`: the pre-averaging window `K` in samples, or None (default) to pick it from the
      increments' noise-to-signal ratio (clipped to `[2, (N - 1) // 8]`; needs concrete values).

    **Returns:** `(Gamma, window)`: the diffusion `Gamma (d,)` (velocity^2 / s), floored at
    1e-3 of the targets' mean magnitude so that it can start a search in `log Gamma`, and the
    window `K` in samples (an int).
    """
    x = jnp.asarray(x)
    e, A_n, B_n, C_n, unit, ratio = _residual_increments(nominal, x, dt, noise_var, perturbation)
    if window is None:
        N = x.shape[1]
        window = int(np.clip(np.round(np.sqrt(24.0 * float(ratio))), 2, max((N - 1) // 8, 2)))
    return _preaverage(e, A_n, B_n, C_n, unit, window), window


@eqx.filter_jit
def _residual_increments(nominal: LinearSecondOrder, x, dt: float, noise_var, perturbation):
    """The velocities' increments after the drift `e (R, N-1, d)`, the noise's share in them
    per sample (`A_n`, `B_n`, `C_n`, `(R, N, d)` each, see below), the one-step variance
    per unit diffusion `(d,)` and the noise-to-signal ratio `()` of one increment, which sets
    the pre-averaging window. One compiled program: eagerly every primitive compiles apart."""
    R, N, m = x.shape
    d = nominal.d
    Phi, Psi = propagators(nominal, dt)
    Psi0, Psi1 = trapezoid_propagators(nominal, dt)
    vel = jnp.arange(d, 2 * d)
    s2 = jnp.asarray(noise_var)
    h = jax.vmap(jax.vmap(_noise_corrected(perturbation, s2)))(x)  # (R, N, m)
    dZ = x[:, 1:] - x[:, :-1] @ Phi.T  # (R, N-1, m)
    e = (dZ - h[:, :-1] @ Psi0.T - h[:, 1:] @ Psi1.T)[..., vel]  # residual velocity increments
    # Noise eps_n enters e_{n-1} as a_n eps_n and e_n as -b_n eps_n (to first order), with
    # a_n = I_v - Psi1 J_n, b_n = Phi_v + Psi0 J_n, J_n the Jacobian of h at X_n. Through a
    # stiff h, displacement noise adds up over a window like an extra diffusion (example 1 at
    # 10% noise: +10%), so the whole first-order structure is kept.
    jac = jax.vmap(jax.vmap(jax.jacfwd(perturbation)))(x)  # (R, N, m, m)
    a = jnp.eye(m)[vel] - jnp.einsum("vi,rnij->rnvj", Psi1[vel], jac)  # (R, N, d, m)
    b = Phi[vel] + jnp.einsum("vi,rnij->rnvj", Psi0[vel], jac)
    # Velocity noise from the lag-one covariance of e (its only source besides the drift,
    # which is gone): E[e_{n-1} e_n] = -sum_i s_i^2 a_{n,vi} b_{n,vi}; the other s_i^2 are known.
    ab = jnp.mean(a[:, 1:-1] * b[:, 1:-1], axis=(0, 1))  # (d, m)
    lag1 = jnp.mean(e[:, :-1] * e[:, 1:], axis=(0, 1))
    known = s2.at[vel].set(0.0)
    s2_v = jnp.linalg.solve(ab[:, vel], -lag1 - ab @ known)
    s2 = s2.at[vel].set(jnp.maximum(s2_v, 0.0))
    A_n = jnp.einsum("rnvi,i->rnv", a * a, s2)
    B_n = jnp.einsum("rnvi,i->rnv", b * b, s2)
    C_n = jnp.einsum("rnvi,i->rnv", a * b, s2)
    second = jnp.mean(e * e, axis=(0, 1))
    noise = jnp.mean(A_n[:, 1:] + B_n[:, :-1], axis=(0, 1))
    pilot = jnp.maximum(second - noise, 1e-3 * second)
    ratio = jnp.where(jnp.max(noise) > 0, jnp.max(noise / pilot), 0.0)
    return e, A_n, B_n, C_n, unit_gramian(nominal, dt), ratio


@functools.partial(jax.jit, static_argnums=5)
def _preaverage(e, A_n, B_n, C_n, unit, window: int):
    """Noise-corrected squares of increments `e` pre-averaged over `window` samples, in units
    of diffusion (`unit (d,)` the one-step variance per unit diffusion): `Gamma (d,)`."""
    j = np.arange(1, window) / window
    g = np.minimum(j, 1.0 - j)  # (K-1,) triangular weights
    # Pre-averaged increments ebar_k = sum_i g_i e_{k+i}, k = 0..P-1.
    ebar = _window_sum(e, g)
    # Noise eps_{k+j}, j = 0..K-1, carries g_{j-1} a - g_j b in ebar_k (g = 0 outside).
    before, after = np.concatenate([[0.0], g]), np.concatenate([g, [0.0]])  # g_{j-1}, g_j
    bias = (
        _window_sum(A_n, before**2) - 2 * _window_sum(C_n, before * after) + _window_sum(B_n, after**2)
    )
    g2 = float(np.sum(g * g))
    # The diffusion part: g2 times the velocity part of the one-step Gramian (~ Gamma dt).
    Y = (ebar**2 - bias) / (g2 * unit[None, None, :])
    gamma = jnp.mean(Y, axis=(0, 1))
    return jnp.maximum(gamma, 1e-3 * jnp.mean(jnp.abs(Y), axis=(0, 1)))


@jax.jit
def _window_sum(series, weights):
    """`out_k = sum_i weights_i series_{k+i}` along axis 1 (valid part): `(R, n, c)` ->
    `(R, n - len(weights) + 1, c)`, as one convolution over time."""
    w = jnp.asarray(weights, series.dtype)[::-1]
    conv = lambda s: jnp.convolve(s, w, mode="valid")
    return jax.vmap(jax.vmap(conv, in_axes=1, out_axes=1))(series)


def process_covariances(nominal: LinearSecondOrder, dt: float) -> jax.Array:
    """The one-step state covariance per unit diffusion of each velocity under the nominal dynamics.

    **Arguments:**

    - `nominal`: the nominal model `LinearSecondOrder`.
    - `dt`: the step, s.

    **Returns:** `(d, m, m)`: `int_0^dt exp(A s) e_v e_v^T exp(A^T s) ds` for each velocity `v`."""
    return gramians(state_matrix(nominal), nominal.velocity_index, dt)


def gramians(A, velocity_index, dt: float) -> jax.Array:
    """The one-step covariance per unit diffusion of each velocity under linear dynamics (Van
    Loan's matrix exponential).

    **Arguments:**

    - `A`: the state matrix, shape `(m, m)`.
    - `velocity_index`: the `d` velocities' positions in the state, a sequence of ints.
    - `dt`: the step, s.

    **Returns:** `(d, m, m)`: `int_0^dt exp(A s) e_v e_v^T exp(A^T s) ds` for each velocity `v`."""
    m = A.shape[0]
    out = []
    for v in velocity_index:
        source = jnp.zeros((m, m), A.dtype).at[v, v].set(1.0)
        block = jnp.zeros((2 * m, 2 * m), A.dtype)
        block = block.at[:m, :m].set(-A).at[:m, m:].set(source).at[m:, m:].set(A.T)
        E = expm(block * dt)
        out.append(E[m:, m:].T @ E[:m, m:])
    return jnp.stack(out)


def unit_gramian(nominal: LinearSecondOrder, dt: float) -> jax.Array:
    """The one-step variance of each velocity per unit diffusion, the velocity entry of
    `process_covariances` (`dt (1 - c dt / m + ...)`).

    **Arguments:**

    - `nominal`: the nominal model `LinearSecondOrder`.
    - `dt`: the step, s.

    **Returns:** `(d,)`, in s."""
    Q = process_covariances(nominal, dt)
    v = jnp.asarray(nominal.velocity_index)
    return Q[jnp.arange(v.size), v, v]
