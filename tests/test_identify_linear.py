"""identify_linear with known parameters (`fixed=`) and its stability guarantee: an
integrating plant (a positioning stage: 100 kg, no spring), a spring-mass system of known
mass, and the refusals of a bad `fixed`."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dtwin_jax.errors import DataError
from dtwin_jax.models.systems import LinearSecondOrder, PerturbedSystem, simulate
from dtwin_jax.preprocess.estimate import STABLE_RTOL, identify_linear
from dtwin_jax.preprocess.measurement import add_noise

STAGE = LinearSecondOrder.create([[100.0]], [[50.0]], [[0.0]], [[1.0]], F0=[2.0])
N, DT = 2000, 1e-3  # 2 s at 1 kHz


def _stage_record(coulomb: float = 0.0, seed: int = 2):
    """Displacement (0.1% noise) of the stage under a random force held for 20 ms (std 20 N),
    with a smoothed Coulomb friction of `coulomb` N."""
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.normal(size=(N // 20, 1)) * 20.0, 20, axis=0)
    t = np.arange(N) * DT
    accel = coulomb / 100.0  # the perturbation is in acceleration units
    system = PerturbedSystem(STAGE, lambda x, uu, p: jnp.array([0.0, -p * jnp.tanh(x[1] / 1e-3)]), jnp.asarray(accel))
    x = np.asarray(simulate(system, np.zeros(2), t, u)[0])
    y = np.asarray(add_noise(jax.random.PRNGKey(seed), x[:, :1], 0.001))
    return t, y, u


def _max_real_part(nom):
    M, C, K = (np.asarray(a) for a in (nom.M, nom.C, nom.K))
    d = M.shape[0]
    A = np.block([[np.zeros((d, d)), np.eye(d)], [-np.linalg.solve(M, K), -np.linalg.solve(M, C)]])
    lam = np.linalg.eigvals(A)
    return lam.real.max(), STABLE_RTOL * np.abs(lam).max()


@pytest.mark.optimized
def test_the_integrating_stage_with_K_and_M_fixed_comes_back_in_physical_units():
    t, y, u = _stage_record()
    nom = identify_linear(t, y, u, ["x1"], fixed={"K": 0, "M": 100})
    C, K, B, F0 = (float(np.asarray(a).ravel()[0]) for a in (nom.C, nom.K, nom.B, nom.F0))
    print(f"stage, fixed K=0 M=100: C {C:.4g} N s/m, B {B:.4g}, F0 {F0:.4g} N")
    # measured: C +0.3%, B -0.6%, F0 +0.2%
    assert float(nom.M[0, 0]) == 100.0 and K == 0.0
    assert abs(C / 50 - 1) < 0.02 and abs(B - 1) < 0.02 and abs(F0 / 2 - 1) < 0.05


@pytest.mark.optimized
def test_a_fit_that_came_back_unstable_is_clipped_to_a_stable_one_and_says_so():
    # The stage with 20 N Coulomb friction: the free fit was K = -36.9 (per unit mass,
    # -3688 N/m at 100 kg), an eigenvalue at +0.74 1/s, before the clipping.
    t, y, u = _stage_record(coulomb=20.0)
    with pytest.warns(UserWarning, match=r"unstable.*clipped K \(smallest eigenvalue -3") as rec:
        nom = identify_linear(t, y, u, ["x1"])
    assert len(rec) == 1 and "\n" not in str(rec[0].message)
    worst, tol = _max_real_part(nom)
    print(f"stage + Coulomb, free: C {float(nom.C[0, 0]):.4g} K {float(nom.K[0, 0]):.4g} per kg, max Re {worst:.3g}")
    assert worst <= tol and float(nom.K[0, 0]) == 0.0 and float(nom.C[0, 0]) > 0
    # Saying K = 0 up front gives the same model, in N with the mass, and no warning.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        known = identify_linear(t, y, u, ["x1"], fixed={"K": 0.0, "M": [[100.0]]})
    np.testing.assert_allclose(float(known.C[0, 0]) / 100, float(nom.C[0, 0]), rtol=1e-3)
    assert _max_real_part(known)[0] <= _max_real_part(known)[1]


def test_a_known_mass_gives_the_spring_in_newtons_per_metre():
    true = LinearSecondOrder.create([[2.0]], [[4.0]], [[2000.0]], [[1.0]])
    rng = np.random.default_rng(0)
    dt = 2 * np.pi / np.sqrt(1000.0) / 20  # 20 samples per natural period
    t = np.arange(3000) * dt
    u = rng.normal(size=(3000, 1)) * 100.0
    x = np.asarray(simulate(true, np.zeros(2), t, u)[0])
    y = np.asarray(add_noise(jax.random.PRNGKey(0), x[:, :1], 0.01))
    nom = identify_linear(t, y, u, ["x1"], fixed={"M": 2})
    print(f"spring-mass, fixed M=2: K {float(nom.K[0, 0]):.5g} N/m, C {float(nom.C[0, 0]):.4g}, B {float(nom.B[0, 0]):.4g}")
    # measured: K +0.33%, C -0.14%, B -0.02%
    assert float(nom.M[0, 0]) == 2.0
    assert abs(float(nom.K[0, 0]) / 2000 - 1) < 0.01
    assert abs(float(nom.C[0, 0]) / 4 - 1) < 0.05 and abs(float(nom.B[0, 0]) - 1) < 0.01


@pytest.mark.parametrize(
    "fixed, message",
    [
        ({"k": 0}, r"'fixed' has unknown keys \['k'\]"),
        ({"K": [[0.0, 0.0]]}, r"fixed K has shape \(1, 2\), expected \(1, 1\)"),
        ({"B": [1.0, 2.0]}, r"fixed B has shape \(2,\), expected \(1, 1\)"),
        ({"F0": [[1.0]]}, r"fixed F0 has shape \(1, 1\), expected \(1,\)"),
        ({"M": -1.0}, "fixed M must be symmetric positive definite"),
        ({"C": np.nan}, "fixed C has a non-finite entry"),
        ({"K": "0"}, "fixed K must hold real numbers"),
        ([("K", 0)], "'fixed' must be a dict"),
    ],
)
def test_a_bad_fixed_is_refused_in_one_line(fixed, message):
    t = np.arange(100) * 1e-3
    with pytest.raises(DataError, match=message) as e:
        identify_linear(t, np.zeros((100, 1)), np.zeros((100, 1)), ["x1"], fixed=fixed)
    assert "\n" not in str(e.value)


def test_an_unstable_fixed_part_is_refused_rather_than_returned():
    t, y, u = _stage_record()
    with pytest.raises(DataError, match=r"unstable .*fixed=\{'K': 0\}") as e:
        identify_linear(t, y, u, ["x1"], fixed={"K": -10.0, "M": 100.0}, max_iterations=2)  # not converged: fast
    assert "\n" not in str(e.value)
