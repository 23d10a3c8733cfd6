"""Measurements of some of the states (x_names), input interpolation, F0, and the
identification of a nominal linear model: dtwin_jax.preprocess.estimate, systems.upsample."""

import json

import jax.numpy as jnp
import numpy as np
import pytest

from dtwin_jax import SamplerSettings, simulate, update_input_output
from dtwin_jax.errors import DataError
from dtwin_jax.io import load_measurements, load_nominal, write_nominal
from dtwin_jax.models.systems import LinearSecondOrder, PerturbedSystem, upsample
from dtwin_jax.preprocess.estimate import discretize

SHORT = SamplerSettings(num_chains=2, num_draws=500, num_burnin=300)


def test_upsample_passes_through_the_samples_and_reconstructs_a_bandlimited_signal():
    t = np.arange(200) / 9.0  # 9 samples per unit-frequency period
    u = np.stack([np.sin(2 * np.pi * t), np.cos(2 * np.pi * 2.7 * t / 9 * 3)], axis=1)
    fine = np.asarray(upsample(u, 8))
    assert fine.shape == (199 * 8 + 1, 2)
    np.testing.assert_allclose(fine[::8], u, atol=1e-12)
    tf = np.arange(fine.shape[0]) / 72.0
    truth = np.sin(2 * np.pi * tf)
    core = slice(400, -400)  # the mirror extension is exact only for a periodic record
    assert np.max(np.abs(fine[core, 0] - truth[core])) < 2e-3  # linear interpolation: 6e-2


ATOL_BANDLIMITED = 1e-10  # measured 7e-12 (states ~0.5)


def test_simulate_and_the_smoothers_discretization_agree_for_every_interpolation():
    nominal = LinearSecondOrder.create([[2.0]], [[0.4]], [[50.0]], [[1.5]], F0=[0.3])
    t = np.arange(300) * 0.05
    u = np.sin(1.3 * t)[:, None] + 0.2 * np.cos(7 * t)[:, None]
    for interpolation in ("held", "linear"):
        x, _ = simulate(nominal, np.array([0.1, 0.0]), t, u, interpolation=interpolation)
        F, W = (np.asarray(a) for a in discretize(nominal, 0.05, interpolation)[:2])
        s = np.zeros(3)
        s[:2] = [0.1, 0.0]
        u1 = np.concatenate([u, np.ones((300, 1))], axis=1)
        for k in range(299):
            s = F @ s + W[0] @ u1[k] + W[1] @ u1[k + 1]
        np.testing.assert_allclose(s[:2], np.asarray(x[-1]), rtol=1e-7, atol=1e-9)
    # Band-limited: fixed Tsit5 steps on the 8x fine grid against the exact discretization.
    x, _ = simulate(nominal, np.array([0.1, 0.0]), t, u, interpolation="bandlimited")
    F, W = (np.asarray(a) for a in discretize(nominal, 0.05, "bandlimited")[:2])
    uf = np.concatenate([np.asarray(upsample(u)), np.ones((299 * 8 + 1, 1))], axis=1)
    s = np.array([0.1, 0.0, 0.0])
    for k in range(299):
        s = F @ s + np.einsum("jsn,jn->s", W, uf[8 * k : 8 * k + W.shape[0]])
    np.testing.assert_allclose(s[:2], np.asarray(x[-1]), rtol=0, atol=ATOL_BANDLIMITED)


def test_F0_round_trips_through_the_nominal_toml(tmp_path):
    nominal = LinearSecondOrder.create([[1.0]], [[2.0]], [[3.0]], F0=[0.25])
    write_nominal(tmp_path / "n.toml", nominal)
    again = load_nominal(tmp_path / "n.toml")
    assert float(again.F0[0]) == 0.25
    assert float(again.rate(jnp.zeros(2), jnp.zeros(1))[1]) == 0.25
    (tmp_path / "bad.toml").write_text("M = [[1.0]]\nC = [[0.0]]\nK = [[1.0]]\nF0 = [1.0, 2.0]\n")
    with pytest.raises(DataError, match="F0 has 2 entries, expected 1"):
        load_nominal(tmp_path / "bad.toml")


def _duffing(seed: int):
    """A randomly drawn hardening or softening Duffing oscillator sampled at ~9 samples
    per natural period, its input held over each step."""
    rng = np.random.default_rng(seed)
    mass, k = rng.uniform(0.5, 3.0), rng.uniform(200.0, 2000.0)
    c = 2 * 0.03 * np.sqrt(k * mass)
    nominal = LinearSecondOrder.create([[mass]], [[c]], [[k]], [[1.0]])
    omega = np.sqrt(k / mass)
    dt = 2 * np.pi / omega / 9
    u = rng.normal(size=(4000, 1)) * k * 0.05
    amplitude = 0.05 * 2  # the response's scale: u std / k, twice
    k3 = rng.choice([-1, 1]) * rng.uniform(0.2, 0.5) * k / amplitude**2 / mass  # acceleration units
    system = PerturbedSystem(nominal, lambda x, uu, p: jnp.array([0.0, p * x[0] ** 3]), jnp.asarray(k3))
    t = np.arange(4000) * dt
    x, _ = simulate(system, np.zeros(2), t, u)
    return nominal, system, t, np.asarray(x), u, k3


def test_displacement_alone_finds_the_cubic_of_a_randomly_drawn_duffing_at_nine_samples_per_period(seed=0):
    nominal, system, t, x, u, k3 = _duffing(seed)
    y = x[:, :1] + 0.01 * x[:, :1].std() * np.random.default_rng(seed + 10).normal(size=(t.size, 1))
    res = update_input_output(nominal, t, y, u, x_names=["x1"], library="poly:3,input", settings=SHORT)
    eq = res.equations[0]
    assert res.preprocessing["rates"] == "state-space smoother"
    assert res.preprocessing["measured_states"] == ["x1"]
    assert any("Savitzky-Golay" in w for w in res.warnings())  # auto switched, and says so
    mean = dict(zip(eq.names, eq.coefficients))
    print(f"seed {seed}: k3 {k3:.4g}, found {mean["x1**3"]:.4g}; PIPs {dict(zip(eq.names, eq.pip.round(2)))}")
    # Measured: x1**3 within 1.4% (seed 0); x1**2, x2**2, x1*x2**2 also selected there (small
    # terms from the velocity estimate's error, a known limitation): the twin's prediction
    # below is the check that they do no harm.
    assert eq.selected[eq.names.index("x1**3")]
    assert abs(mean["x1**3"] / k3 - 1) < 0.02
    # The twin on a new input: measured 7.0% / 6.8% (the spurious terms above cost accuracy;
    # the paper's examples reach 0.2-2.5%), the nominal model far off.
    new_u = np.random.default_rng(99).normal(size=(2000, 1)) * float(nominal.K[0, 0]) * 0.05
    truth = np.asarray(simulate(system, np.zeros(2), t[:2000], new_u)[0])
    pred = np.asarray(simulate(res.twin, np.zeros(2), t[:2000], new_u)[0])
    nrmse = np.sqrt(np.mean((pred - truth) ** 2, axis=0)) / truth.std(axis=0)
    assert np.all(nrmse < 0.075), nrmse


def test_measurement_files_carry_state_names_and_the_input_interpolation(tmp_path):
    t = np.arange(50) * 0.01
    np.savez(tmp_path / "d.npz", t=t, x=np.zeros((50, 1)), u=np.zeros((50, 1)), x_names=np.array(["x1"]),
             u_interpolation=np.array("bandlimited"))
    data = load_measurements(tmp_path / "d.npz")
    assert data["x_names"] == ["x1"] and data["u_interpolation"] == "bandlimited"
    (tmp_path / "d.csv").write_text("t,x1,u1\n" + "\n".join(f"{a},0,0" for a in t) + "\n")
    assert load_measurements(tmp_path / "d.csv")["x_names"] == ["x1"]
    (tmp_path / "v.csv").write_text("t,x2,u1\n" + "\n".join(f"{a},0,0" for a in t) + "\n")
    assert load_measurements(tmp_path / "v.csv")["x_names"] == ["x2"]


def test_cli_discovers_from_a_displacement_only_file_and_refuses_unknown_state_names(tmp_path, capsys):
    # In-process (main(argv)): a second randomly drawn system, the compiled code reused.
    from dtwin_jax.cli import main

    nominal, system, t, x, u, k3 = _duffing(1)
    write_nominal(tmp_path / "n.toml", nominal)
    np.savez(tmp_path / "d.npz", t=t, x=x[:, :1], u=u, x_names=np.array(["x1"]))
    out = tmp_path / "r.json"
    argv = ["discover", str(tmp_path / "d.npz"), "--nominal", str(tmp_path / "n.toml"), "--library", "poly:3,input",
            "--chains", "2", "--draws", "500", "--burn-in", "300", "--quiet", "--out", str(out)]
    assert main(argv) == 0
    doc = json.loads(out.read_text())
    terms = {t["expr"]: t["mean"] for t in doc["equations"][0]["terms"]}
    print("seed 1: k3", k3, "selected", terms)
    assert abs(terms["x1**3"] / k3 - 1) < 0.02
    assert doc["preprocessing"]["measured_states"] == ["x1"]
    np.savez(tmp_path / "bad.npz", t=t, x=x[:, :1], u=u, x_names=np.array(["x9"]))
    capsys.readouterr()
    assert main(argv[:1] + [str(tmp_path / "bad.npz")] + argv[2:-1] + [str(tmp_path / "r2.json")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "x9" in err and not (tmp_path / "r2.json").exists()


@pytest.mark.optimized
def test_identify_linear_recovers_a_lightly_damped_system_from_displacement_at_nine_samples_per_period():
    from dtwin_jax.preprocess.estimate import identify_linear

    true = LinearSecondOrder.create([[1.0]], [[3.0]], [[900.0]], [[450.0]], F0=[12.0])
    rng = np.random.default_rng(0)
    dt = 2 * np.pi / 30 / 9
    u = rng.normal(size=(5000, 1))
    t = np.arange(5000) * dt
    y = np.asarray(simulate(true, np.zeros(2), t, u)[0][:, :1])
    y = y + 0.01 * y.std() * rng.normal(size=y.shape)
    nom = identify_linear(t, y, u, ["x1"])
    # measured: C -0.8%, K +0.04%, B -0.5%, F0 +1.3% (4 fixed rounds gave C -8%, B -4%)
    err = [float(a[0, 0]) / b - 1 for a, b in ((nom.C, 3.0), (nom.K, 900.0), (nom.B, 450.0))]
    err.append(float(nom.F0[0]) / 12.0 - 1)
    assert abs(err[0]) < 0.015 and abs(err[1]) < 0.002 and abs(err[2]) < 0.01 and abs(err[3]) < 0.02, err
