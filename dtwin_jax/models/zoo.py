"""A seeded zoo of randomly perturbed SDOF and 2-DOF systems, to judge the updates on
systems they were not tuned to.

Every member is a `systems.Example`: a random linear nominal model plus one perturbation
from one of the `FAMILIES`, with `true_terms` named as `library.parse_library` names them,
so `systems.simulate_example` (input-output) and `systems.simulate_example_sde`
(output-only) work unchanged.

| family | dof | perturbation force (rate = -force / mass) | true term |
|---|---|---|---|
| `cubic-hardening` | 1 | `a q^3`, `a > 0` | `x1**3` |
| `cubic-softening` | 1 | `a q^3`, `a < 0`, stable | `x1**3` |
| `quadratic-stiffness` | 1 | `a q^2`, either sign | `x1**2` |
| `abs-stiffness` | 1 | `a q |q|`, either sign | `x1*Abs(x1)` |
| `coulomb` | 1 | `F sign(v)` | `sign(x2)` |
| `quadratic-drag` | 1 | `d v |v|` | `x2*Abs(x2)` |
| `cubic-damping` | 1 | `c3 v^3` | `x2**3` |
| `amplitude-damping` | 1 | `e q^2 v` | `x1**2*x2` |
| `coupling-cubic` | 2 | `a (q1 - q2)^3` between the masses | four cubic monomials in `x3`, `x4` |
| `chain-coulomb` | 2 | `F sign(v_j)` on one mass `j` | `sign(x3)` or `sign(x4)` |

**Nominal models.** Masses 0.5-5 kg; SDOF natural frequency log-uniform in 2-15 Hz; 2-DOF
chains (ground-k1-m1-k2-m2, both masses forced, Rayleigh damping) with modal frequencies in
2-15 Hz; damping ratios 2-10%; the force gain `B` set so that the stationary RMS displacement
(largest over the masses) is log-uniform in 0.01-0.3. Stationary covariances come from the
Lyapunov equation of the nominal model under the unit-intensity forcing `B dB`, which the
held white input of `simulate_example` (`u_k ~ N(0, 1/dt)`) matches. `x0`: every displacement
at 1-3 stationary RMS with a random sign (independent signs excite both modes of a chain),
velocities 0. 1 kHz, 1 s.

**Magnitude rule.** The size of a perturbation is a ratio `r` to a reference force, drawn
per family; `s` is the nominal stationary RMS displacement, `s_v` the velocity's:

* hardening stiffness (`cubic-hardening`, hardening `abs-stiffness`, `coupling-cubic`): the
  perturbation force at `q = s` (at `q1 - q2 = RMS(q1 - q2)` for the coupling) is `r` times
  the nominal restoring force there (`k s`, or `k2 RMS(q1 - q2)`), `r ~ U(0.1, 0.5)`;
* softening stiffness (`cubic-softening`, `quadratic-stiffness`, softening `abs-stiffness`):
  the restoring force must stay monotone for `|q| <= 5 s` (`STABLE_RANGE`), which caps `r`
  at `1/75` for `q^3` and at `0.1` for `q^2` and `q|q|`; `r ~ U(0.6, 0.95)` times the cap,
  so the force stays monotone up to 5.1-6.5 `s`;
* smooth damping (`quadratic-drag`, `cubic-damping`, `amplitude-damping`): the damping
  force at `q = s`, `v = s_v` is `r` times the restoring force `k s`, `r ~ U(0.1, 0.5)`
  (the nominal damping force `c s_v = 2 zeta k s` is only 4-20% of `k s`, and the white
  force dwarfs it, so a ratio to it would not be identifiable);
* Coulomb friction (`coulomb`, `chain-coulomb`): `F` is `r` times the per-sample standard
  deviation of the force, `B / sqrt(dt)`, `r ~ U(0.05, 0.125)`. Above ~0.125 the mass sticks
  at a good share of its velocity reversals, and the sticking samples do not follow `sign(v)`.

Then **identifiability** is checked: a noise-free pilot simulation (`simulate_example`,
key `seed`) gives the expected z-score `|theta| / se` of every true coefficient in a
least-squares fit on the true terms, `1`, the states and the inputs, with the target noise
of 5% noise on the measured accelerations and inputs (`expected_z`). While the smallest is
below `Z_MIN = 8` the ratio is scaled up (to at most 1.0, or the stability or sticking cap),
and when the cap is reached, or the pilot's solver fails, the nominal model is redrawn. So
cubic-softening members (below `Z_MIN` at the stability cap for a typical nominal model)
lean to lightly damped, stiff nominal models. The z-score on the whole library
(`Member.z_full`, in the description) is much lower: telling `x1**3` from
`x1*Abs(x1)` or `x2*Abs(x2)` from `x2**3` in 1 s is the hard part, and is what the zoo
measures, not what it screens for.

**Coulomb friction in the simulator.** `sign(v)` makes the adaptive Dopri8 solver of
`systems.simulate` grind to a halt when the mass sticks (a sliding mode: the step shrinks to
the tolerance and stays there), so the simulated friction is `F tanh(v / w)` with the
slip width `w = (F / m) * FRICTION_TIME` (0.25 ms, so ShARK's 0.25 ms SDE steps are stable):
`w` is a small fraction of the RMS velocity, and `tanh(v / w)` differs from `sign(v)` only on
the few samples within a few `w` of zero velocity (most of them when stuck), where a physical
friction balances the applied force rather than following `sign(v)`.

All SDOF families share one perturbation function (`sdof_perturbation`, every force
coefficient in `params`, zeros for the absent ones) and both chain families another
(`chain_perturbation`), so members compile one simulation per chain size.

`noise_level(seed)` draws the measurement noise level of a member, uniform in 2-5%.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from dtwin_jax.library import parse_library
from dtwin_jax.models import systems
from dtwin_jax.output_only.kramers_moyal import state_matrix

__all__ = [
    "FAMILIES",
    "LIBRARY",
    "Z_MIN",
    "Member",
    "draw",
    "draw_member",
    "drag_and_coulomb",
    "members",
    "noise_level",
    "expected_z",
    "stationary_covariance",
    "sdof_perturbation",
    "chain_perturbation",
]

FAMILIES: tuple[str, ...] = (
    "cubic-hardening",
    "cubic-softening",
    "quadratic-stiffness",
    "abs-stiffness",
    "coulomb",
    "quadratic-drag",
    "cubic-damping",
    "amplitude-damping",
    "coupling-cubic",
    "chain-coulomb",
)
_CHAIN_FAMILIES = ("coupling-cubic", "chain-coulomb")

# Input-output library; `Example.library_output_only` strips `input`.
LIBRARY = "poly:3,sign,abs,xabs,input"
DT, DURATION = 1e-3, 1.0
_WHITE_STD = DT**-0.5  # u_k ~ N(0, 1/dt): unit-intensity white noise held over each sample

Z_MIN = 8.0  # smallest expected z-score of a true coefficient (`expected_z`, 5% noise)
PILOT_NOISE = 0.05  # noise level the z-score assumes: the top of NOISE_RANGE
NOISE_RANGE = (0.02, 0.05)
STABLE_RANGE = 5.0  # softening: restoring force monotone for |q| <= 5 nominal RMS
FRICTION_TIME = 2.5e-4  # s: friction slip width w = (F / m) * FRICTION_TIME
RATIO_MAX = 1.0  # no perturbation above the reference force at nominal RMS

_HARD_RATIO = (0.1, 0.5)
_SOFT_FRACTION = (0.6, 0.95)  # of the stability cap
_FRICTION_RATIO = (0.05, 0.125)  # of the per-sample force std B / sqrt(dt)
_CUBIC_SOFT_CAP = 1.0 / (3.0 * STABLE_RANGE**2)  # k + 3 a q^2 > 0 for |q| <= 5 s
_SQUARE_SOFT_CAP = 1.0 / (2.0 * STABLE_RANGE)  # k - 2 |a| |q| > 0 for |q| <= 5 s
_NOISE_STREAM = 1_000  # rng stream of noise_level, apart from the families' streams
_MAX_ATTEMPTS = 300  # nominal redraws before giving up
_MAX_SCALINGS = 6  # ratio scale-ups per nominal

# Force coefficients of the SDOF perturbation, in the order of `_SDOF_TERMS`.
_SDOF_FORCES = ("cubic", "square", "abs", "friction", "drag", "cubic_damping", "amplitude")
_SDOF_TERMS = {
    "cubic": "x1**3",
    "square": "x1**2",
    "abs": "x1*Abs(x1)",
    "friction": "sign(x2)",
    "drag": "x2*Abs(x2)",
    "cubic_damping": "x2**3",
    "amplitude": "x1**2*x2",
}
_SDOF_FAMILY_FORCE = {
    "cubic-hardening": "cubic",
    "cubic-softening": "cubic",
    "quadratic-stiffness": "square",
    "abs-stiffness": "abs",
    "coulomb": "friction",
    "quadratic-drag": "drag",
    "cubic-damping": "cubic_damping",
    "amplitude-damping": "amplitude",
}


# ---------------------------------------------------------------------------
# Perturbations (module level: static and hashable, one compile per chain size)


def sdof_perturbation(x, u, params):
    """Extra rate of an SDOF member at one state: `-force / mass`.

    The force sums every family's term, each with its coefficient in `params` (zero for the
    absent ones), so all SDOF members share this one function.

    **Arguments:**

    - `x`: the state `[q, v]`, shape `(2,)`, m and m/s.
    - `u`: the input (unused).
    - `params`: a dict of 0-d arrays, SI units: `mass` kg and the force coefficients `cubic`
      (q^3), `square` (q^2), `abs` (q|q|), `friction` (`tanh(v / friction_width)`, Coulomb),
      `drag` (v|v|), `cubic_damping` (v^3), `amplitude` (q^2 v), and `friction_width` m/s.

    **Returns:** the extra rate `(2,)`: 0 for `q`, `-force / mass` (m/s^2) for `v`.
    """
    q, v = x[0], x[1]
    p = params
    force = (
        p["cubic"] * q**3
        + p["square"] * q**2
        + p["abs"] * q * jnp.abs(q)
        + p["friction"] * jnp.tanh(v / p["friction_width"])
        + p["drag"] * v * jnp.abs(v)
        + p["cubic_damping"] * v**3
        + p["amplitude"] * q**2 * v
    )
    return jnp.stack([jnp.zeros_like(q), -force / p["mass"]])


def chain_perturbation(x, u, params):
    """Extra rate of a 2-DOF chain member at one state: `-force / mass` on each mass.

    **Arguments:**

    - `x`: the state `[q1, q2, v1, v2]`, shape `(4,)`, m and m/s.
    - `u`: the input (unused).
    - `params`: a dict of arrays, SI units: `mass (2,)` kg, `coupling` (force
      `a (q1 - q2)^3` on mass 1, its opposite on mass 2), `friction (2,)` N and
      `friction_width (2,)` m/s (Coulomb `F_j tanh(v_j / w_j)`).

    **Returns:** the extra rate `(4,)`: 0 for the displacements, `-force / mass` (m/s^2) for
    the velocities.
    """
    q, v = x[:2], x[2:4]
    p = params
    spring = p["coupling"] * (q[0] - q[1]) ** 3
    force = jnp.stack([spring, -spring]) + p["friction"] * jnp.tanh(v / p["friction_width"])
    return jnp.concatenate([jnp.zeros_like(q), -force / p["mass"]])


# ---------------------------------------------------------------------------
# Nominal models


class _Nominal(NamedTuple):
    model: systems.LinearSecondOrder
    cov: np.ndarray  # (m, m) stationary covariance under B dB
    x0: np.ndarray  # (m,)
    text: str  # its numbers, for the description


def stationary_covariance(nominal: systems.LinearSecondOrder) -> np.ndarray:
    """The stationary state covariance of a nominal model under the Brownian force `B dB`.

    `P` solves the Lyapunov equation `A P + P A^T + G G^T = 0`, with
    `G = diffusion_matrix(nominal)`.

    **Arguments:**

    - `nominal`: the nominal model (stable, so that `P` exists).

    **Returns:** `P`, shape `(m, m)`, in the states' units squared.
    """
    A = np.asarray(state_matrix(nominal))
    G = np.asarray(systems.diffusion_matrix(nominal))
    return scipy.linalg.solve_continuous_lyapunov(A, -G @ G.T)


def _log_uniform(rng, low, high):
    return float(np.exp(rng.uniform(np.log(low), np.log(high))))


def _start(rng, cov, d):
    """`x0 (2d,)`: displacements at 1-3 stationary RMS with random signs, velocities 0."""
    rms = np.sqrt(np.diag(cov)[:d])
    q0 = rng.choice([-1.0, 1.0], d) * rng.uniform(1.0, 3.0, d) * rms
    return np.concatenate([q0, np.zeros(d)])


def _draw_sdof(rng) -> _Nominal:
    mass = rng.uniform(0.5, 5.0)
    freq = _log_uniform(rng, 2.0, 15.0)
    zeta = rng.uniform(0.02, 0.10)
    omega = 2 * np.pi * freq
    k, c = mass * omega**2, 2 * zeta * mass * omega
    rms = _log_uniform(rng, 0.01, 0.3)
    gain = rms * np.sqrt(2 * c * k)  # var(q) = B^2 / (2 c k) under B dB
    model = systems.LinearSecondOrder.create([[mass]], [[c]], [[k]], [[gain]])
    cov = stationary_covariance(model)
    text = (f"SDOF m={mass:.3g} kg, f_n={freq:.3g} Hz, zeta={100 * zeta:.3g}%, "
            f"k={k:.4g}, c={c:.4g}, B={gain:.4g}")
    return _Nominal(model, cov, _start(rng, cov, 1), text)


def _rayleigh(omegas, zetas):
    """`(a, b)` of `C = a M + b K` with modal damping ratios `zetas` at `omegas`."""
    lhs = np.array([[1 / (2 * w), w / 2] for w in omegas])
    return np.linalg.solve(lhs, np.asarray(zetas))


def _draw_chain(rng) -> _Nominal:
    """Ground-k1-m1-k2-m2 chain, both masses forced; redrawn until its modes are in 2-15 Hz."""
    while True:
        mass = rng.uniform(0.5, 5.0, 2)
        k1 = mass[0] * (2 * np.pi * _log_uniform(rng, 3.0, 10.0)) ** 2
        k2 = mass[1] * (2 * np.pi * _log_uniform(rng, 3.0, 10.0)) ** 2
        M, K = np.diag(mass), np.array([[k1 + k2, -k2], [-k2, k2]])
        omegas = np.sqrt(np.sort(np.linalg.eigvals(np.linalg.solve(M, K)).real))
        if 2.0 <= omegas[0] / (2 * np.pi) and omegas[1] / (2 * np.pi) <= 15.0:
            break
    zetas = rng.uniform(0.02, 0.10, 2)
    a, b = _rayleigh(omegas, zetas)
    C = a * M + b * K  # modal ratios zetas > 0, so C is positive definite even when a < 0
    shape = np.diag([1.0, rng.uniform(0.5, 2.0)])
    unit = systems.LinearSecondOrder.create(M, C, K, shape)
    rms = _log_uniform(rng, 0.01, 0.3)
    B = shape * rms / np.sqrt(np.max(np.diag(stationary_covariance(unit))[:2]))
    model = systems.LinearSecondOrder.create(M, C, K, B)
    cov = stationary_covariance(model)
    freqs = omegas / (2 * np.pi)
    text = (f"2-DOF chain m=[{mass[0]:.3g}, {mass[1]:.3g}] kg, k1={k1:.4g}, k2={k2:.4g}, "
            f"modes {freqs[0]:.3g} and {freqs[1]:.3g} Hz, zeta=[{100 * zetas[0]:.3g}, "
            f"{100 * zetas[1]:.3g}]%, B=diag({B[0, 0]:.4g}, {B[1, 1]:.4g})")
    return _Nominal(model, cov, _start(rng, cov, 2), text)


# ---------------------------------------------------------------------------
# Magnitudes


class _Size(NamedTuple):
    ratio: float  # of the reference force
    cap: float  # largest ratio a scale-up may reach
    sign: float  # +1 hardening (force with the restoring force), -1 softening
    reference: str  # what the ratio is relative to
    mass_index: int = 0  # chain-coulomb: the mass with friction


def _draw_size(rng, family) -> _Size:
    restoring = "the nominal restoring force at RMS displacement"
    friction = "the per-sample force std B/sqrt(dt)"
    if family == "cubic-softening":
        cap = _CUBIC_SOFT_CAP * _SOFT_FRACTION[1]
        return _Size(_CUBIC_SOFT_CAP * rng.uniform(*_SOFT_FRACTION), cap, -1.0, restoring)
    if family == "quadratic-stiffness" or (family == "abs-stiffness" and rng.uniform() < 0.5):
        sign = -1.0 if family == "abs-stiffness" else float(rng.choice([-1.0, 1.0]))
        cap = _SQUARE_SOFT_CAP * _SOFT_FRACTION[1]
        return _Size(_SQUARE_SOFT_CAP * rng.uniform(*_SOFT_FRACTION), cap, sign, restoring)
    if family in ("coulomb", "chain-coulomb"):
        mass_index = int(rng.integers(2)) if family == "chain-coulomb" else 0
        return _Size(rng.uniform(*_FRICTION_RATIO), _FRICTION_RATIO[1], 1.0, friction, mass_index)
    return _Size(rng.uniform(*_HARD_RATIO), RATIO_MAX, 1.0, restoring)


def _sdof_force(family, size: _Size, nominal: _Nominal) -> tuple[str, float]:
    """`(force name, coefficient)` of an SDOF family at `size`, SI units."""
    model = nominal.model
    k, mass, gain = (float(a[0, 0]) for a in (model.K, model.M, model.B))
    s, s_v = np.sqrt(np.diag(nominal.cov))
    restoring = size.ratio * k * s
    name = _SDOF_FAMILY_FORCE[family]
    coef = {
        "cubic": restoring / s**3,
        "square": restoring / s**2,
        "abs": restoring / s**2,
        "friction": size.ratio * gain * _WHITE_STD,
        "drag": restoring / s_v**2,
        "cubic_damping": restoring / s_v**3,
        "amplitude": restoring / (s**2 * s_v),
    }[name]
    return name, size.sign * coef


def _friction_width(force, mass):
    # Slip width of tanh(v / w); 1.0 where there is no friction (any positive width works).
    return np.where(force > 0, force / mass * FRICTION_TIME, 1.0)


def _sdof_example(family, size, nominal: _Nominal, name) -> tuple[systems.Example, str]:
    mass = float(nominal.model.M[0, 0])
    force, coef = _sdof_force(family, size, nominal)
    values = {f: 0.0 for f in _SDOF_FORCES} | {force: coef}
    params = {f: jnp.asarray(v) for f, v in values.items()}
    params["mass"] = jnp.asarray(mass)
    params["friction_width"] = jnp.asarray(_friction_width(values["friction"], mass))
    term = _SDOF_TERMS[force]
    system = systems.PerturbedSystem(nominal.model, sdof_perturbation, params)
    law = f"force {coef:.5g} {term} (rate {-coef / mass:.5g} {term})"
    return _example(name, system, nominal, {"x2": {term: -coef / mass}}), law


def _chain_example(family, size, nominal: _Nominal, name) -> tuple[systems.Example, str]:
    model = nominal.model
    mass = np.diag(np.asarray(model.M))
    coupling, friction = 0.0, np.zeros(2)
    if family == "coupling-cubic":
        k2 = -float(model.K[0, 1])
        rel = np.array([1.0, -1.0, 0.0, 0.0])
        s_rel = np.sqrt(rel @ nominal.cov @ rel)
        coupling = size.ratio * k2 / s_rel**2
        a = coupling
        # -force/m expanded: (q1 - q2)^3 = x1^3 - 3 x1^2 x2 + 3 x1 x2^2 - x2^3.
        cubic = {"x1**3": 1.0, "x1**2*x2": -3.0, "x1*x2**2": 3.0, "x2**3": -1.0}
        true_terms = {"x3": {t: -a * c / mass[0] for t, c in cubic.items()},
                      "x4": {t: a * c / mass[1] for t, c in cubic.items()}}
        law = f"cubic spring {a:.5g} (q1-q2)^3 between the masses"
    else:
        j = size.mass_index
        friction[j] = size.ratio * float(model.B[j, j]) * _WHITE_STD
        state = f"x{3 + j}"
        true_terms = {"x3": {}, "x4": {}} | {state: {f"sign({state})": -friction[j] / mass[j]}}
        law = (f"Coulomb friction {friction[j]:.5g} sign({state}) on mass {j + 1} "
               f"(rate {-friction[j] / mass[j]:.5g} sign({state}))")
    params = {
        "mass": jnp.asarray(mass),
        "coupling": jnp.asarray(coupling),
        "friction": jnp.asarray(friction),
        "friction_width": jnp.asarray(_friction_width(friction, mass)),
    }
    system = systems.PerturbedSystem(model, chain_perturbation, params)
    return _example(name, system, nominal, true_terms), law


def _example(name, system, nominal: _Nominal, true_terms) -> systems.Example:
    return systems.Example(
        name=name,
        system=system,
        x0=jnp.asarray(nominal.x0),
        dt=DT,
        duration=DURATION,
        input_std=_WHITE_STD,
        true_terms=true_terms,
        library=LIBRARY,
        description="",
    )


# ---------------------------------------------------------------------------
# Identifiability


def expected_z(
    example: systems.Example, key, level: float = PILOT_NOISE, *, full: bool = False
) -> dict[str, dict[str, float]]:
    """Expected z-score `|theta| / se` of every true coefficient.

    From one noise-free input-output simulation (`simulate_example(example, key)`): the
    standard error of a least-squares fit, with the target noise of `level` on the measured
    rates and inputs; the input noise enters the target through the removed nominal
    `M^-1 B u`. The fit's columns are the true terms, `1`, the states and the inputs (is the
    term detectable above the noise and the linear terms?), or with `full` the whole
    `example.library` (can it also be told from every look-alike, e.g. `x1**3` from
    `x1*Abs(x1)`?). Non-finite simulation: 0.

    **Arguments:**

    - `example`: the `systems.Example` (a zoo member's).
    - `key`: JAX PRNG key of the simulation's input.
    - `level`: measurement noise std as a fraction of each signal's std (default
      `PILOT_NOISE`, 0.05).
    - `full`: fit on the whole library instead of the true terms, `1`, the states and the
      inputs (default False).

    **Returns:** `{state: {term: z}}` for every true term, dimensionless.
    """
    return _z_scores(example, systems.simulate_example(example, key), level, full)


def _z_scores(example, sim, level, full):
    x, xdot, u = (np.asarray(sim[k]) for k in ("x", "xdot", "u"))
    nominal = example.system.nominal
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(xdot))):
        return {s: {t: 0.0 for t in terms} for s, terms in example.true_terms.items()}
    lib = parse_library(example.library, nominal.m, nominal.n)
    L = np.asarray(lib(x, u))
    names = list(lib.names)
    if not full:
        basis = {"1", *nominal.state_names, *nominal.input_names}
        basis |= {t for terms in example.true_terms.values() for t in terms}
        keep = [k for k, name in enumerate(names) if name in basis]
        L, names = L[:, keep], [names[k] for k in keep]
    scale = np.sqrt(np.mean(L * L, axis=0))
    inverse = np.linalg.pinv((L / scale).T @ (L / scale))
    gain = np.asarray(np.linalg.solve(nominal.M, nominal.B))  # (d, n)
    z = {}
    for state, terms in example.true_terms.items():
        i = nominal.state_names.index(state)
        noise_var = (level * xdot[:, i].std()) ** 2
        noise_var += np.sum((level * u.std(axis=0) * gain[i - nominal.d]) ** 2)
        z[state] = {}
        for term, coef in terms.items():
            k = names.index(term)
            se = np.sqrt(noise_var * max(inverse[k, k], 0.0)) / scale[k]
            z[state][term] = float(abs(coef) / se) if se > 0 else float("inf")
    return z


def _min_z(z: dict[str, dict[str, float]]) -> float:
    return min(v for terms in z.values() for v in terms.values())


def _pilot(example, key) -> tuple[float, float] | None:
    """`(z, z_full)`: smallest expected z-scores of a pilot run; None if the solver fails
    (the same member would fail in `simulate_example`)."""
    try:
        sim = systems.simulate_example(example, key)
    except RuntimeError:  # equinox's max_steps error
        return None
    return (_min_z(_z_scores(example, sim, PILOT_NOISE, False)),
            _min_z(_z_scores(example, sim, PILOT_NOISE, True)))


# ---------------------------------------------------------------------------
# Members


class Member(NamedTuple):
    """One zoo member and the numbers it was drawn with."""

    example: systems.Example
    family: str
    seed: int
    noise_level: float  # measurement noise, fraction of each signal's std
    ratio: float  # perturbation size relative to `reference` (see the module docstring)
    reference: str
    z_min: float  # smallest expected z-score of a true coefficient (`expected_z`)
    z_full: float  # the same on the whole library (`expected_z(..., full=True)`)


def noise_level(seed: int) -> float:
    """Measurement noise level of member `seed`, uniform in `NOISE_RANGE` (2-5%).

    **Arguments:**

    - `seed`: the member's seed.

    **Returns:** the noise std as a fraction of each signal's std.
    """
    return float(np.random.default_rng([seed, _NOISE_STREAM]).uniform(*NOISE_RANGE))


def _family_of(seed: int, family: str | None) -> str:
    if family is None:
        return FAMILIES[seed % len(FAMILIES)]
    if family not in FAMILIES:
        raise ValueError(f"unknown zoo family {family!r} (known: {', '.join(FAMILIES)})")
    return family


def _build(family, size, nominal, name):
    if family in _CHAIN_FAMILIES:
        return _chain_example(family, size, nominal, name)
    return _sdof_example(family, size, nominal, name)


def draw_member(seed: int, family: str | None = None) -> Member:
    """Draw member `seed` of `family`.

    Deterministic in `(seed, family)`. Redraws the magnitude up to its cap, then the
    nominal model, until every true coefficient has an expected z-score >= `Z_MIN`; raises
    `RuntimeError` when no nominal model in 300 draws gives one.

    **Arguments:**

    - `seed`: the member's seed, a non-negative integer.
    - `family`: one of `FAMILIES`, or None (default) for `FAMILIES[seed % len(FAMILIES)]`;
      another name raises `ValueError`.

    **Returns:** the `Member`: its `systems.Example` and the numbers it was drawn with.
    """
    family = _family_of(seed, family)
    rng = np.random.default_rng([seed, FAMILIES.index(family)])
    name = f"zoo-{seed:04d}-{family}"
    pilot_key = jax.random.key(seed)
    for _ in range(_MAX_ATTEMPTS):
        nominal = _draw_chain(rng) if family in _CHAIN_FAMILIES else _draw_sdof(rng)
        size = _draw_size(rng, family)
        for _ in range(_MAX_SCALINGS):
            example, law = _build(family, size, nominal, name)
            pilot = _pilot(example, pilot_key)
            if pilot is None:
                break  # the solver failed: redraw the nominal model
            z = pilot[0]
            if z >= Z_MIN:
                return _finish(example, family, seed, size, law, nominal, pilot)
            ratio = min(size.ratio * 1.25 * Z_MIN / max(z, 1e-3), size.cap)
            if ratio <= size.ratio:
                break  # at the cap: redraw the nominal model
            size = size._replace(ratio=ratio)
    raise RuntimeError(f"{name}: no identifiable member in {_MAX_ATTEMPTS} nominal draws")


def _finish(example, family, seed, size, law, nominal, pilot) -> Member:
    level = noise_level(seed)
    x0 = ", ".join(f"{v:.4g}" for v in nominal.x0)
    description = (
        f"{example.name}: {nominal.text}; perturbation {law}, {size.ratio:.3g} x "
        f"{size.reference}; x0 = [{x0}]; expected z-score {pilot[0]:.3g} "
        f"({pilot[1]:.3g} on the whole library) at 5% noise; "
        f"measurement noise {100 * level:.2f}%"
    )
    example = example._replace(description=description)
    return Member(example, family, seed, level, float(size.ratio), size.reference, *pilot)


def draw(seed: int, family: str | None = None) -> systems.Example:
    """The `Example` of `draw_member(seed, family)`.

    **Arguments:**

    - `seed`: the member's seed.
    - `family`: one of `FAMILIES`, or None (default) for `FAMILIES[seed % len(FAMILIES)]`.

    **Returns:** the member's `systems.Example`.
    """
    return draw_member(seed, family).example


def members(num: int, seed: int = 0) -> list[systems.Example]:
    """`num` members with consecutive seeds, every family in turn.

    The family cycles with the seed, so any `len(FAMILIES)` consecutive members hold every
    family once.

    **Arguments:**

    - `num`: the number of members.
    - `seed`: the first seed (default 0); the others are `seed + 1, seed + 2, ...`.

    **Returns:** the members' `systems.Example`s, a list of `num`.
    """
    return [draw(seed + i) for i in range(num)]


def drag_and_coulomb(seed: int, friction_ratio: float = 0.08, level: float = 0.02) -> Member:
    """A near-equivalent member: a `quadratic-drag` member with Coulomb friction added.

    The member is `draw_member(seed, "quadratic-drag")` plus Coulomb friction by the coulomb
    family's rule. Over the measured velocity range `x2*Abs(x2) + sign(x2)` and
    `x2 + x2**3 + sign(x2)` are close (issue 26 item 2; `benchmarks/ambiguity.py`).

    **Arguments:**

    - `seed`: the seed of the quadratic-drag member.
    - `friction_ratio`: the friction force as a fraction of the per-sample force std
      `B / sqrt(dt)` (default 0.08).
    - `level`: the measurement noise level, a fraction of each signal's std (default 0.02).

    **Returns:** the `Member`, family `"drag+coulomb"`, with `sign(x2)` added to its true
    terms and `noise_level` set to `level`.
    """
    import jax.numpy as jnp

    member = draw_member(seed, "quadratic-drag")
    ex = member.example
    params = dict(ex.system.params)
    mass, gain = float(params["mass"]), float(ex.system.nominal.B[0, 0])
    force = friction_ratio * gain * _WHITE_STD
    params["friction"] = jnp.asarray(force)
    params["friction_width"] = jnp.asarray(force / mass * FRICTION_TIME)
    truth = dict(ex.true_terms["x2"]) | {"sign(x2)": -force / mass}
    system = systems.PerturbedSystem(ex.system.nominal, sdof_perturbation, params)
    ex = ex._replace(system=system, true_terms={"x2": truth}, name=f"drag-coulomb-{seed:04d}",
                     description=ex.description + f"; plus Coulomb friction {force:.5g} sign(x2)")
    return member._replace(example=ex, family="drag+coulomb", noise_level=level)
