"""Noise sweeps (dtwin_jax.studies): one compiled program over levels x replicates x chains.

Short settings (3 levels, 2 replicates, 2 chains x 300 draws); the CLI test reuses the same
shapes, so it hits the compiled program of the fixture.
"""

import jax
import numpy as np
import pytest

from dtwin_jax import sampler, studies
from dtwin_jax.cli import main
from dtwin_jax.errors import DataError
from dtwin_jax.input_output import targets
from dtwin_jax.library import parse_library
from dtwin_jax.models import systems
from dtwin_jax.preprocess.denoise import auto_half_width
from dtwin_jax.preprocess.measurement import measure
from dtwin_jax.update import SamplerSettings

LEVELS = [0.0, 0.05, 0.45]
SETTINGS = SamplerSettings(num_chains=2, num_draws=300, num_burnin=150)


@pytest.fixture(scope="module")
def sweep():
    return studies.noise_sweep("example1", LEVELS, replicates=2, settings=SETTINGS, seed=0, progress=False)


def test_sweep_finds_the_cubic_term(sweep):
    s = sweep.summary
    assert s.pip.shape == (3, 2, 1, 46) and s.support_exact.shape == (3, 2, 1)
    err = sweep.term_errors()["x2: x1**3"]  # (L, Rp)
    print("x1**3 relative errors (level x replicate):\n", err)
    assert np.all(s.support_exact[:2])  # 0% and 5%: exactly x1**3, every replicate
    assert np.all(err[0] < 0.002) and np.all(err[1] < 0.02)
    assert np.all(err[2] < 0.1)  # 45%
    k = sweep.names.index("x1**3")
    assert np.all((s.lower[:2, :, 0, k] < -1e5) & (s.upper[:2, :, 0, k] > -1e5) | (err[:2] < 0.005))
    assert list(sweep.support_recovery[:2]) == [1.0, 1.0]


def test_sweep_equals_one_level_through_the_same_pipeline(sweep):
    # Replicate 1 at 5%, rebuilt outside the sweep from the same keys: same stats, same draws.
    ex = systems.example1()
    nominal = ex.system.nominal
    lib = parse_library(ex.library, nominal.m, nominal.n)
    sim_keys, noise_keys, chain_keys = studies.study_keys(0, 2, 1)
    sim = systems.simulate_example(ex, sim_keys[1])
    meas = measure(noise_keys[1], sim["t"], sim["x"], sim["xdot"], sim["u"], level=0.05)
    hw = auto_half_width(nominal, ex.dt, 1000)
    stats = targets.input_output_stats(nominal, lib, ex.dt, meas.x, meas.u, meas.xdot, hw)
    trace = sampler.sample(chain_keys[1, 0], jax.tree.map(lambda a: a[0], stats), num_draws=300,
                           num_burnin=150, num_chains=2)
    truth, support = studies._truth(ex, lib.names, ("x2",))
    one = studies.summarise(trace, truth[0], support[0])
    np.testing.assert_allclose(np.asarray(one.pip), sweep.summary.pip[1, 1, 0], atol=1e-12)
    np.testing.assert_allclose(np.asarray(one.mean), sweep.summary.mean[1, 1, 0], rtol=1e-7, atol=1e-9)


def test_cli_sweep_writes_three_files(tmp_path, capsys):
    out = tmp_path / "sw"
    code = main(["sweep", "--levels", ",".join(map(str, LEVELS)), "--replicates", "2", "--chains", "2",
                 "--draws", "300", "--burn-in", "150", "--out-dir", str(out), "--quiet"])
    assert code == 0
    assert sorted(p.name for p in out.iterdir()) == ["sweep.csv", "sweep.json", "sweep.png"]
    text = capsys.readouterr().out
    assert "support" in text and "wall time" in text
    assert (out / "sweep.csv").read_text().count("\n") == 1 + 3 * 2


@pytest.mark.parametrize("argv", [["--levels", "0,1.5"], ["--replicates", "0"], ["--levels", "a,b"],
                                  ["--max-level", "2"]])
def test_cli_sweep_bad_input_exits_2_and_writes_nothing(tmp_path, capsys, argv):
    out = tmp_path / "sw"
    assert main(["sweep", *argv, "--out-dir", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("dtwin-jax: error:") and "\n" not in err
    assert not out.exists()


def test_sweep_bad_batch_size_is_a_data_error():
    with pytest.raises(DataError, match="batch_size must be a positive integer, got 0"):
        studies.noise_sweep("example1", [0.05], framework="output-only", batch_size=0, progress=False)


# Its parts run by default: output_only_drift_stats and the diffusion statistics against the
# update (tests/test_output_only.py), the vmapped sampler and summaries in the sweeps above.
@pytest.mark.slow
def test_output_only_sweep_small():
    res = studies.noise_sweep("example1", [0.05], replicates=1, framework="output-only", records=20,
                              settings=SETTINGS, seed=0, progress=False)
    drift = res.term_errors()["x2: x1**3"]
    gamma = res.diffusion.term_errors()["x2: 1"]
    print("output-only 5%, 20 records: x1**3 error", drift, "Gamma error", gamma, res.timings)
    assert bool(res.summary.support_exact.all()) and drift[0, 0] < 0.05
    assert bool(res.diffusion.summary.support_exact.all()) and gamma[0, 0] < 0.15
