"""dtwin_jax._compile.aot: a jitted function run through its exported program, exported once and
loaded from disk afterwards, gives what the function gives; inside another trace, or where
no process set-up enabled it (the library's default, and the rest of this suite), it is a
plain call."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dtwin_jax  # noqa: F401  (float64)
from dtwin_jax import sampler
from dtwin_jax._compile import aot
from dtwin_jax.models import systems
from dtwin_jax.preprocess.denoise import kinematic_smoother
from dtwin_jax.preprocess.measurement import measure


@pytest.fixture
def folder(tmp_path):
    """Exports enabled for one test, as `configure_runtime` enables them for a process."""
    aot.enable(tmp_path / "dtwin-export")
    yield tmp_path / "dtwin-export"
    aot.enable(None)
    aot._LOADED.clear()


def test_export_then_load_gives_the_same_draws(folder):
    rng = np.random.default_rng(0)
    L = rng.normal(size=(300, 6))
    stats = sampler.suff_stats(L, L[:, 0] - 0.5 * L[:, 1] + rng.normal(size=300))
    key = jax.random.key(3)
    # Random starts (a key in, a while loop) and the states they give (a pytree out): the
    # sampler's set-up, small enough to compile in a fraction of a second.
    fn = jax.jit(lambda k, st: jax.vmap(lambda g: sampler.init(st, gamma=g))(sampler.initial_indicators(k, st, 3)))
    direct = fn(key, stats)
    name = "draws"
    exported = aot.call(name, fn, (key, stats))
    aot._LOADED.clear()  # as a new process: read from disk
    loaded = aot.call(name, fn, (key, stats))
    assert isinstance(loaded, sampler.GibbsState)  # the export holds the output's structure
    assert len(list(folder.glob(f"{name}-*.bin"))) == 1
    assert np.asarray(direct.gamma).sum(axis=1).min() >= 1  # the starts differ from empty
    for got in (exported, loaded):
        np.testing.assert_array_equal(np.asarray(got.gamma), np.asarray(direct.gamma))
        np.testing.assert_array_equal(np.asarray(got.theta), np.asarray(direct.theta))


def test_the_chunked_sampler_through_exports_gives_the_plain_draws(folder):
    # Its set-up program compiles with its own XLA options when called from Python; an
    # export traces it inside another program, which takes the plain function.
    rng = np.random.default_rng(1)
    L = rng.normal(size=(200, 5))
    stats = sampler.suff_stats(L, L[:, 0] + rng.normal(size=200))
    kwargs = dict(num_draws=120, num_burnin=30, num_chains=2)
    exported = sampler.sample_in_chunks(jax.random.key(4), stats, **kwargs)
    aot.enable(None)
    plain = sampler.sample_in_chunks(jax.random.key(4), stats, **kwargs)
    assert {p.name.split("-")[0] for p in folder.glob("*.bin")} == {"sampler_setup", "sampler_chunk"}
    np.testing.assert_array_equal(exported.gamma, plain.gamma)
    np.testing.assert_allclose(exported.theta, plain.theta, rtol=1e-12, atol=1e-300)


def test_not_enabled_it_is_the_plain_function():
    fn = jax.jit(lambda a: (2.0 * a,))
    (got,) = aot.call("plain", fn, (jnp.arange(3.0),))
    np.testing.assert_array_equal(np.asarray(got), [0.0, 2.0, 4.0])
    assert not aot._LOADED


def test_inside_a_trace_it_is_the_plain_function(folder):
    ex = systems.example1()
    sim = systems.simulate_example(ex, jax.random.key(0), duration=0.2)
    meas = measure(jax.random.key(1), sim["t"], sim["x"], sim["xdot"], sim["u"], level=0.05)
    args = (jnp.asarray(meas.x), jnp.asarray(meas.xdot), jnp.asarray(meas.u))
    top = kinematic_smoother(ex.system.nominal, ex.dt, *args)  # through aot
    traced = jax.jit(lambda a, b, c: kinematic_smoother(ex.system.nominal, ex.dt, a, b, c))(*args)
    np.testing.assert_allclose(np.asarray(top), np.asarray(traced), rtol=1e-12, atol=1e-15)


def test_a_program_exported_for_another_platform_is_exported_again(folder):
    """A cache shared between a GPU run and a CPU run (seen on a GPU machine: `discover` on the
    GPU after one on the CPU failed with "exported for platforms ('cpu',) but it is used on
    ('cuda',)"): the key holds the platform, and a file for another platform found at the
    key's path is not run."""
    from jax import export

    x = jnp.arange(3.0)
    fn = jax.jit(lambda a: (2.0 * a,))
    path = aot._path(folder, "double", (), jax.tree.structure((x,)), [x])
    assert export.default_export_platform() == "cpu"
    foreign = export.export(jax.jit(lambda a: (3.0 * a,)), platforms=("cuda",))(x)
    folder.mkdir(parents=True)
    path.write_bytes(foreign.serialize())
    (got,) = aot.call("double", fn, (x,))
    np.testing.assert_array_equal(np.asarray(got), [0.0, 2.0, 4.0])
    assert export.deserialize(bytearray(path.read_bytes())).platforms == ("cpu",)  # exported again


def _duffing_twins(draws: int, stochastic: bool):
    """`draws` twins of example 1's nominal model plus its cubic spring (1% spread), with the
    constant diffusion of an output-only twin when `stochastic`."""
    from dtwin_jax.library import parse_library
    from dtwin_jax.models.prediction import UpdatedTwin

    ex = systems.example1()
    lib = parse_library("poly:3", 2, 0 if stochastic else 1)
    coef = np.zeros((draws, 1, lib.K))
    coef[:, 0, lib.names.index("x1**3")] = -1e5 * (1 + 0.01 * np.random.default_rng(0).standard_normal(draws))
    extra = {}
    if stochastic:
        extra = dict(diffusion_library=parse_library("terms:1", 2, 0), diffusion_coefficients=jnp.full((draws, 1, 1), 0.25))
    return UpdatedTwin(ex.system.nominal, lib, (1,), jnp.asarray(coef), **extra), ex


@pytest.mark.parametrize("stochastic", [False, True], ids=["input-output", "output-only"])
def test_a_prediction_through_its_export_gives_the_plain_paths(folder, stochastic):
    """The prediction's solve (the model-error check of every update) is exported with
    equinox's run-time checks as NaN outputs: the paths, status and stop times equal the plain
    call's, exported and loaded as by a new process."""
    from dtwin_jax.models.prediction import predict

    twins, ex = _duffing_twins(3, stochastic)
    t = jnp.arange(300) * 1e-3
    u = None if stochastic else 10.0 * jax.random.normal(jax.random.key(2), (300, 1))
    run = lambda: predict(twins, ex.x0, t, u, key=jax.random.key(5))  # noqa: E731
    exported = run()
    assert [p.name.split("-")[0] for p in folder.glob("*.bin")] == ["paths"]
    aot._LOADED.clear()  # as a new process: read from disk
    loaded = run()
    aot.enable(None)
    plain = run()
    assert np.all(np.asarray(plain["status"]) == systems.OK)
    assert np.ptp(np.asarray(plain["paths"])[:, -1, 0]) > 0  # the draws differ
    for got in (exported, loaded):
        for name in ("paths", "status", "stop_time"):
            np.testing.assert_allclose(np.asarray(got[name]), np.asarray(plain[name]), rtol=1e-12, atol=1e-15)


def test_a_program_with_a_host_callback_runs_as_a_plain_call(folder):
    seen = []
    fn = jax.jit(lambda a: (jax.debug.callback(lambda v: seen.append(float(v)), a.sum()), 2.0 * a)[1:])
    (got,) = aot.call("callback", fn, (jnp.arange(3.0),))
    np.testing.assert_array_equal(np.asarray(got), [0.0, 2.0, 4.0])
    assert seen == [3.0] and not list(folder.glob("*.bin"))
