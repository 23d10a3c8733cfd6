import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import sympy

import dtwin_jax  # noqa: F401  (float64)
from dtwin_jax.errors import DataError
from dtwin_jax.models.systems import (
    EXAMPLES,
    LinearSecondOrder,
    example1,
    example2,
    example3,
    simulate,
    simulate_example,
)

N = 1000  # one shape for every example-1 simulation, so jit compiles are shared
DT = 1e-3


def _zero_perturbation(x, u, params):
    return jnp.zeros_like(x)


def _state_matrix(nominal):
    d = nominal.d
    Minv = jnp.linalg.inv(nominal.M)
    return jnp.block([[jnp.zeros((d, d)), jnp.eye(d)], [-Minv @ nominal.K, -Minv @ nominal.C]])


def _grid_and_input(seed, n=1):
    t = jnp.arange(N) * DT
    u = jax.random.normal(jax.random.PRNGKey(seed), (N, n))
    return t, u


def test_nominal_properties_and_rate():
    nominal = example3().system.nominal
    assert (nominal.d, nominal.n, nominal.m) == (1, 1, 3)
    assert nominal.state_names == ("x1", "x2", "x3")
    assert nominal.input_names == ("u1",)
    assert nominal.velocity_index == (1,)
    assert nominal.regressed_index == (1, 2)
    rate = nominal.rate(jnp.array([0.1, 2.0, 5.0]), jnp.array([3.0]))
    np.testing.assert_allclose(rate, [2.0, 3.0 - 2 * 2.0 - 2000 * 0.1, 0.0], rtol=1e-14)
    two = example2().system.nominal
    assert two.velocity_index == (2, 3) and two.regressed_index == (2, 3)
    x = jax.random.normal(jax.random.PRNGKey(0), (5, 4))
    u = jax.random.normal(jax.random.PRNGKey(1), (5, 2))
    np.testing.assert_allclose(two.rate_batch(x, u)[3], two.rate(x[3], u[3]))
    # State order [q1, q2, v1, v2]: the rate is the usual first-order state matrix.
    forced = jnp.concatenate([jnp.zeros((5, 2)), u @ jnp.linalg.solve(two.M, two.B).T], axis=1)
    np.testing.assert_allclose(
        two.rate_batch(x, u), x @ _state_matrix(two).T + forced, rtol=1e-12, atol=1e-9
    )


def test_linear_free_response_matches_matrix_exponential():
    # Example 1 with alpha = 0: the perturbation is identically zero, and the
    # compiled simulation is shared with the other example-1 tests.
    ex = example1()
    system = eqx.tree_at(lambda s: s.params["alpha"], ex.system, jnp.asarray(0.0))
    nominal = system.nominal
    x0 = jnp.array([0.1, 1.0])
    t = jnp.arange(N) * DT
    x, xdot = simulate(system, x0, t, jnp.zeros((N, 1)))

    exact = jax.vmap(lambda s: jax.scipy.linalg.expm(_state_matrix(nominal) * s) @ x0)(t)
    err = float(jnp.max(jnp.abs(x - exact)))
    print(f"linear free response: max |x - expm| = {err:.2e}")
    assert err < 1e-8
    np.testing.assert_allclose(xdot, exact @ _state_matrix(nominal).T, atol=1e-7, rtol=0)


def test_example1_rates_and_energy_balance():
    ex = example1()
    t, u = _grid_and_input(0)
    x, xdot = simulate(ex.system, ex.x0, t, u)
    q, v = x[:, 0], x[:, 1]

    # Kinematic row is smooth: central differences agree with the rate.
    central = (x[2:] - x[:-2]) / (2 * DT)
    rel = jnp.sqrt(jnp.mean((central - xdot[1:-1]) ** 2, axis=0) / jnp.mean(xdot**2, axis=0))
    print(f"central difference vs xdot, relative RMS per state: {np.asarray(rel)}")
    assert rel[0] < 1e-3 and rel[1] < 1e-2

    # Over one sample the input is held, so the trapezoid rule with u[i] at both
    # ends must match the increment to O(dt^3).
    left = ex.system.rate_batch(x[1:], u[:-1])
    trap = 0.5 * DT * (xdot[:-1] + left)
    incr = x[1:] - x[:-1]
    rel_trap = jnp.sqrt(jnp.mean((trap - incr) ** 2, axis=0) / jnp.mean(incr**2, axis=0))
    print(f"trapezoid (held input) vs increment, relative RMS: {np.asarray(rel_trap)}")
    assert jnp.all(rel_trap < 1e-3)

    # Energy balance: dE/dt = sigma u v - c v^2 with E = v^2/2 + k q^2/2 + alpha q^4/4.
    sigma, c, k, alpha = 0.5, 2.0, 1000.0, 1e5
    energy = 0.5 * v**2 + 0.5 * k * q**2 + 0.25 * alpha * q**4
    work = sigma * u[:-1, 0] * (q[1:] - q[:-1])  # exact: u constant on each interval
    dissipated = c * 0.5 * DT * (v[1:] ** 2 + v[:-1] ** 2)
    predicted = energy[0] + jnp.concatenate([jnp.zeros(1), jnp.cumsum(work - dissipated)])
    balance = float(jnp.max(jnp.abs(energy - predicted)) / jnp.max(energy))
    print(f"energy balance error / max energy: {balance:.2e}")
    assert balance < 1e-3
    assert float(jnp.max(jnp.abs(q))) < 0.2


def test_piecewise_constant_input_matches_two_piece_solve():
    ex = example1()
    t = jnp.arange(N) * DT
    half = N // 2
    u = jnp.where(jnp.arange(N) < half, 1.0, 0.0)[:, None]
    x, _ = simulate(ex.system, ex.x0, t, u)

    @jax.jit
    def piece(x0, ts, level):
        term = diffrax.ODETerm(lambda s, y, a: ex.system.rate(y, jnp.reshape(a, (1,))))
        sol = diffrax.diffeqsolve(
            term, diffrax.Dopri8(), ts[0], ts[-1], None, x0, args=level,
            saveat=diffrax.SaveAt(ts=ts),
            stepsize_controller=diffrax.PIDController(rtol=1e-12, atol=1e-14),
            max_steps=100_000,
        )
        return sol.ys

    # Both pieces save at half + 1 times so the reference compiles once.
    first = piece(ex.x0, t[: half + 1], 1.0)
    second = piece(first[-1], t[half] + jnp.arange(half + 1) * DT, 0.0)[: N - half]
    reference = jnp.concatenate([first[:-1], second])
    err = jnp.max(jnp.abs(x - reference), axis=0)
    print(f"two-piece reference: max error per state {np.asarray(err)}")
    assert jnp.all(err < 1e-9)


def test_vmap_over_records_matches_loop():
    ex = example1()
    t = jnp.arange(N) * DT
    x0s = jnp.array([[0.1, 0.0], [-0.05, 1.0], [0.0, -2.0]])
    us = jax.random.normal(jax.random.PRNGKey(3), (3, N, 1))
    xb, xdotb = jax.vmap(simulate, in_axes=(None, 0, None, 0))(ex.system, x0s, t, us)
    assert xb.shape == (3, N, 2) and xdotb.shape == (3, N, 2)
    for r in range(3):
        x, xdot = simulate(ex.system, x0s[r], t, us[r])
        np.testing.assert_allclose(xb[r], x, rtol=0, atol=1e-11)
        np.testing.assert_allclose(xdotb[r], xdot, rtol=0, atol=1e-8)


def test_vmap_over_system_parameters():
    ex = example1()
    t, u = _grid_and_input(4)
    alphas = jnp.array([0.0, 5e4, 2e5])
    systems = eqx.filter_vmap(
        lambda a: eqx.tree_at(lambda s: s.params["alpha"], ex.system, a)
    )(alphas)
    assert systems.params["alpha"].shape == (3,)
    xb, _ = jax.vmap(lambda s: simulate(s, ex.x0, t, u))(systems)
    for i, a in enumerate(alphas):
        single = eqx.tree_at(lambda s: s.params["alpha"], ex.system, a)
        x, _ = simulate(single, ex.x0, t, u)
        np.testing.assert_allclose(xb[i], x, rtol=0, atol=1e-11)
    # A stiffer cubic spring means a smaller peak displacement.
    peaks = jnp.max(jnp.abs(xb[:, :, 0]), axis=1)
    assert peaks[0] >= peaks[1] >= peaks[2]


def test_example3_damage_grows():
    ex = example3()
    out = simulate_example(ex, jax.random.PRNGKey(0))
    assert out["t"].shape == (N,) and out["x"].shape == (N, 3) and out["u"].shape == (N, 1)
    np.testing.assert_allclose(out["t"][1] - out["t"][0], DT)
    damage = out["x"][:, 2]
    print(f"example3 damage x3: {float(damage[0]):.3f} -> {float(damage[-1]):.3f}")
    assert float(damage[0]) == 0.0
    assert float(damage[-1]) > 1.0
    assert bool(jnp.all(jnp.diff(damage) >= -1e-12))


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_true_terms_reproduce_the_perturbation(name):
    ex = EXAMPLES[name]()
    nominal = ex.system.nominal
    symbols = sympy.symbols(nominal.state_names)
    x = np.array(jax.random.uniform(jax.random.PRNGKey(5), (20, nominal.m), minval=-1.0))
    if name == "example3":
        x[:, 2] = np.abs(x[:, 2]) * 3  # damage is non-negative
    u = np.zeros((20, nominal.n))
    h = np.asarray(jax.vmap(ex.system.perturbation, (0, 0, None))(x, u, ex.system.params))
    names = nominal.state_names
    for row, terms in ex.true_terms.items():
        assert names.index(row) in nominal.regressed_index
        for term in terms:
            assert str(sympy.sympify(term)) == term  # canonical sympy form
        expr = sum(c * sympy.sympify(term) for term, c in terms.items())
        f = sympy.lambdify(symbols, expr, "numpy")
        np.testing.assert_allclose(f(*x.T), h[:, names.index(row)], rtol=1e-12, atol=1e-9)
    # Rows with no true terms carry no perturbation.
    others = [i for i, s in enumerate(names) if s not in ex.true_terms]
    assert np.all(h[:, others] == 0.0)


def test_example2_terms_are_the_sympy_expansion():
    q1, q2 = sympy.symbols("x1 x2")
    alpha = 50000
    rows = {
        "x3": -(alpha * q1**3 + alpha * (q1 - q2) ** 3),
        "x4": -(alpha * (q2 - q1) ** 3),
    }
    expected = {
        row: {str(term): float(c) for term, c in sympy.expand(expr).as_coefficients_dict().items()}
        for row, expr in rows.items()
    }
    assert example2().true_terms == expected


def test_create_validates_with_one_line_errors():
    with pytest.raises(DataError, match="singular") as err:
        LinearSecondOrder.create([[1.0, 1.0], [1.0, 1.0]], np.eye(2), np.eye(2))
    assert "\n" not in str(err.value) and "cond=" in str(err.value)
    with pytest.raises(DataError, match="C has shape") as err:
        LinearSecondOrder.create(np.eye(2), np.eye(3), np.eye(2))
    assert "\n" not in str(err.value)
    with pytest.raises(DataError, match="B has shape"):
        LinearSecondOrder.create(np.eye(2), np.eye(2), np.eye(2), np.ones((3, 1)))
    with pytest.raises(DataError, match="square"):
        LinearSecondOrder.create(np.ones((2, 3)), np.eye(2), np.eye(2))
    with pytest.raises(DataError, match="non-finite"):
        LinearSecondOrder.create(np.eye(2), np.eye(2), [[np.nan, 0.0], [0.0, 1.0]])
    default_b = LinearSecondOrder.create(np.eye(2), np.eye(2), np.eye(2))
    assert default_b.n == 2 and np.array_equal(default_b.B, np.eye(2))


def test_simulate_rejects_bad_shapes():
    ex = example1()
    t = jnp.arange(10) * DT
    with pytest.raises(DataError, match="input u"):
        simulate(ex.system, ex.x0, t, jnp.zeros((9, 1)))
