"""Small dense linear algebra that compiles quickly.

`mass_solve` is `M^-1 rhs` for a nominal mass matrix: a division for one degree of
freedom (exact, and no LAPACK call in every stage of every simulation step, filter and drift;
`benchmarks/cold_update.py` times both).

`expm` replaces `jax.scipy.linalg.expm` in the package: that one evaluates the
Padé approximants of degrees 3, 5, 7, 9 and 13 as branches of one `lax.switch` and undoes
the scaling in a 16-step scan of conditionals, which takes about twice as long to compile per
call site as this one; the state-space and Kramers-Moyal programs hold several.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["expm", "mass_solve"]

# Higham (2005), "The scaling and squaring method for the matrix exponential revisited":
# the degree-13 Padé coefficients and the 1-norm up to which it is accurate to double precision.
_B13 = (64764752532480000.0, 32382376266240000.0, 7771770303897600.0, 1187353796428800.0, 129060195264000.0,
        10559470521600.0, 670442572800.0, 33522128640.0, 1323241920.0, 40840800.0, 960960.0, 16380.0, 182.0, 1.0)
_THETA13 = 5.371920351148152


def expm(A: jax.Array) -> jax.Array:
    """The matrix exponential `exp(A)` of a float64 matrix.

    Scaling by `2**-s` to 1-norm at most 5.37, the degree-13 Padé approximant, then `s`
    squarings (a loop of dynamic length). Accurate to a few units of roundoff times the
    condition of the problem; jittable and vmappable.

    **Arguments:**

    - `A`: the matrix, shape `(n, n)`, float64.

    **Returns:** `exp(A)`, shape `(n, n)`, the dtype of `A`.
    """
    A = jnp.asarray(A)
    norm = jnp.max(jnp.sum(jnp.abs(A), axis=0))
    s = jnp.where(norm > _THETA13, jnp.ceil(jnp.log2(norm / _THETA13)), 0.0)
    A = A * jnp.exp2(-s)
    b = _B13
    eye = jnp.eye(A.shape[0], dtype=A.dtype)
    A2 = A @ A
    A4 = A2 @ A2
    A6 = A4 @ A2
    U = A @ (A6 @ (b[13] * A6 + b[11] * A4 + b[9] * A2) + b[7] * A6 + b[5] * A4 + b[3] * A2 + b[1] * eye)
    V = A6 @ (b[12] * A6 + b[10] * A4 + b[8] * A2) + b[6] * A6 + b[4] * A4 + b[2] * A2 + b[0] * eye
    R = jnp.linalg.solve(V - U, V + U)
    return jax.lax.fori_loop(0, s.astype(jnp.int32), lambda _, X: X @ X, R)


def mass_solve(M: jax.Array, rhs: jax.Array) -> jax.Array:
    """`M^-1 rhs` for a nominal mass matrix.

    `rhs / M` when `d = 1` (the shape is static, so this is decided at trace time),
    `jnp.linalg.solve` otherwise.

    **Arguments:**

    - `M`: the mass matrix, shape `(d, d)`.
    - `rhs`: the right-hand side, shape `(d, ...)`.

    **Returns:** `M^-1 rhs`, the shape of `rhs`.
    """
    M, rhs = jnp.asarray(M), jnp.asarray(rhs)
    if M.shape[-1] == 1:
        return rhs / M[0, 0]
    return jnp.linalg.solve(M, rhs)
