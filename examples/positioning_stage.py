"""A positioning stage in closed loop (`dtwin_jax.models.plants.positioning_stage`): update its twin
from the encoder position and the motor force alone, and compare free runs on a held-out
record with the textbook friction model fitted by least squares (issue 26, item 6).

    python examples/positioning_stage.py [--duration 25] [--library SPEC] [--draws 100]

The stage: 100 kg, viscous 50 N s/m, Coulomb 20 N, offset 5 N, PD control following a
smooth random reference around 5 cm, a 1 um encoder and the commanded force (0.5 N noise),
both at 1 kHz. Training record: key 0; held-out record: key 1.

* **Textbook model**: `m q'' + Fv q' + Fc sign(q') + F0 = u`, its four parameters by least
  squares on Savitzky-Golay velocity and acceleration of the encoder position (half width
  25 samples, order 4).
* **Twin**: `update_input_output` on the default route from `x_names = ["x1"]` with the
  nominal a user would write (`plants.stage_nominal`: mass and viscous friction), the
  library `--library` (default: the package's default library); the free run is the mean of
  `--draws` posterior draws (`predict`).

Both free runs are open loop under the held-out record's measured force, from its first
measured position at rest. Prints each model's parameters or terms and the RMS free-run
error (mm) of each.
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

import dtwin_jax  # noqa: F401 (float64)
from dtwin_jax import posterior_twins, predict, simulate, update_input_output
from dtwin_jax.models.plants import StageParams, positioning_stage, stage_nominal
from dtwin_jax.models.systems import LinearSecondOrder, PerturbedSystem
from dtwin_jax.preprocess.measurement import smooth


def textbook_fit(d, dt):
    """`(m, Fv, Fc, F0)` by least squares of `u = m a + Fv v + Fc sign(v) + F0`."""
    q = d["x"][:, 0]
    v = np.asarray(smooth(q, 25, 4, 1, dt))
    a = np.asarray(smooth(q, 25, 4, 2, dt))
    A = np.stack([a, v, np.sign(v), np.ones_like(v)], axis=1)
    return np.linalg.lstsq(A, d["u"][:, 0], rcond=None)[0]


def textbook_free_run(theta, d):
    m, Fv, Fc, F0 = (float(v) for v in theta)
    nominal = LinearSecondOrder.create([[m]], [[Fv]], [[0.0]], [[1.0]])
    system = PerturbedSystem(nominal, _friction_rate, (Fc, F0, m))
    x0 = np.array([d["x"][0, 0], 0.0])
    return np.asarray(simulate(system, x0, d["t"], d["u"], substeps=16)[0][:, 0])


def _friction_rate(x, u, params):
    Fc, F0, m = params
    return jax.numpy.stack([0.0 * x[0], -(Fc * jax.numpy.sign(x[1]) + F0) / m])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=25.0)
    parser.add_argument("--library", default=None)
    parser.add_argument("--draws", type=int, default=100)
    args = parser.parse_args()
    p = StageParams()
    train = positioning_stage(jax.random.key(0), args.duration, params=p)
    test = positioning_stage(jax.random.key(1), args.duration, params=p)
    dt = float(train["t"][1])
    rms = lambda est: 1e3 * float(np.sqrt(np.mean((est - test["q"]) ** 2)))  # noqa: E731

    theta = textbook_fit(train, dt)
    print(f"textbook model: m {theta[0]:.2f} kg, Fv {theta[1]:.2f} N s/m, Fc {theta[2]:.2f} N, F0 {theta[3]:.2f} N "
          f"(truth {p.mass}, {p.viscous}, {p.coulomb}, {p.offset})")
    print(f"textbook free run on the held-out record: {rms(textbook_free_run(theta, test)):.3f} mm")

    start = time.perf_counter()
    try:
        result = update_input_output(stage_nominal(p), train["t"], train["x"], train["u"], x_names=["x1"],
                                     library=args.library)
    except dtwin_jax.DataError as e:  # the default library on an axis that never crosses 0
        print(f"twin: refused: {e}")
        return
    print(f"twin ({time.perf_counter() - start:.1f} s, library '{result.library.spec}'):")
    print(result.summary())
    print(f"truth: x2: {-p.coulomb / p.mass:g} sign(x2) + {-p.offset / p.mass:g} (1)")
    for w in result.warnings():
        print(f"warning: {w}")
    twins = posterior_twins(result, args.draws, jax.random.key(2))
    x0 = np.array([test["x"][0, 0], 0.0])
    start = time.perf_counter()
    try:
        pred = predict(twins, x0, test["t"], test["u"])
        print(f"twin free run on the held-out record: {rms(np.asarray(pred['mean'])[:, 0]):.3f} mm "
              f"(predict {time.perf_counter() - start:.1f} s)")
    except dtwin_jax.DataError as e:
        print(f"twin free run failed: {e}")


if __name__ == "__main__":
    main()
