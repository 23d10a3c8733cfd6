"""dtwin_jax.linalg: the matrix exponential against SciPy's, the mass solve against NumPy's."""

import jax
import numpy as np
import scipy.linalg

import dtwin_jax  # noqa: F401  (float64)
from dtwin_jax.linalg import expm, mass_solve


def test_expm_matches_scipy_from_tiny_to_large_norms():
    rng = np.random.default_rng(0)
    run = jax.jit(expm)
    worst = 0.0
    for n in (1, 3, 6):
        for scale in (1e-6, 1e-2, 0.5, 3.0, 30.0, 300.0):
            A = rng.normal(size=(n, n)) * scale / np.sqrt(n)
            ref = scipy.linalg.expm(A)
            worst = max(worst, np.max(np.abs(np.asarray(run(A)) - ref)) / np.max(np.abs(ref)))
    print("largest relative error", worst)  # measured 1.7e-12 (at norm 300)
    assert worst < 5e-12
    # An oscillator over one sample (Van Loan block, as kramers_moyal.propagators builds it).
    A = np.array([[0.0, 1.0], [-1000.0, -2.0]]) * 1e-3
    assert np.max(np.abs(np.asarray(run(A)) - scipy.linalg.expm(A))) < 1e-15


def test_mass_solve_is_a_division_for_one_dof_and_a_solve_otherwise():
    rng = np.random.default_rng(1)
    rhs = rng.normal(size=(1, 4))
    np.testing.assert_array_equal(np.asarray(mass_solve(np.array([[2.5]]), rhs)), rhs / 2.5)
    M = rng.normal(size=(3, 3)) + 3 * np.eye(3)
    rhs = rng.normal(size=(3, 2))
    np.testing.assert_allclose(np.asarray(mass_solve(M, rhs)), np.linalg.solve(M, rhs), rtol=1e-13)
