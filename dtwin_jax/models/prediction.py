"""The updated twin as a simulator, and its posterior predictive (paper Section 5.6).

`UpdatedTwin` is the nominal model plus the discovered drift terms (and, for an
output-only twin, the discovered diffusion): an equinox module, so its coefficient arrays
may carry a leading axis of posterior draws and the twin vmaps over them.
`posterior_twins` stacks draws of an update's posterior; `predict` simulates
them (an ODE under a given input, or an SDE under Brownian forcing, both with diffrax
through `dtwin_jax.models.systems`) and returns the mean and the 2.5% and 97.5% quantiles of
every state.
"""

from __future__ import annotations

import dataclasses
import math
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax._compile import aot
from dtwin_jax._compile.keys import strong_jit, strong_types
from dtwin_jax.errors import DataError
from dtwin_jax.library import Library, TermTable, eval_terms, parse_library, term_table
from dtwin_jax.models import systems
from dtwin_jax.models.systems import LinearSecondOrder
from dtwin_jax.resources import check_posterior_draws, check_prediction
from dtwin_jax.sampler.driver import batch_map, default_batch_method

__all__ = ["UpdatedTwin", "posterior_twins", "predict", "simulation_error", "with_model_error", "effective_stiffness",
           "degradation_forecast", "divergence_bounds", "fixed_substeps", "is_nonsmooth", "PredictionWarning",
           "DIVERGENCE_FACTOR", "MAX_FAILED"]

# A draw has diverged when a state is farther from the centre of its training range than
# this many times the range's half-width (or than this many times its initial offset).
DIVERGENCE_FACTOR = 100.0
# Without a training range: this many times the scale of the initial state and of the
# nominal model's static response to the input.
FALLBACK_FACTOR = 1e6
# predict drops (with a warning) at most this fraction of draws that diverge or fail;
# more and it raises.
MAX_FAILED = 0.05
# Fixed steps of a non-smooth twin: at most this many radians of its fastest nominal mode
# per step, and at least MIN_SUBSTEPS steps per sample.
STEP_RADIANS, MIN_SUBSTEPS, MAX_SUBSTEPS = 0.05, 4, 256


class PredictionWarning(UserWarning):
    """Some posterior draws diverged or failed and were dropped from a prediction."""


class UpdatedTwin(eqx.Module):
    """Nominal model plus discovered terms: `dx/dt = f(x, u) + S Theta L(x, u)`, and for an
    output-only twin `dx = ... dt + G(x) dB` with the discovered diffusion.

    `coefficients (q, K)` of `library` for the states `regressed` (indices into the state);
    `diffusion_coefficients (d, Kd)` of `diffusion_library` give `Gamma_vv(x)` (velocity^2/s)
    of every velocity, or are None for an input-output twin. Arrays may carry a leading
    batch axis (posterior draws): vmap over it with `eqx.filter_vmap`. `interpolation`:
    how the input behaves between samples (`systems.check_interpolation`), as in the
    data the twin was updated from. `state_range (m, 2)`: the smallest and largest value of
    every state in that data (`preprocessing["state_range"]`), which bounds a prediction
    (`divergence_bounds`), or None. `model_error_sd (m,)`: the twin's free-run error
    on that data (`dtwin_jax.model_error`), added to a prediction's band, or None.
    `terms`: None, or the drift library as data (`library_as_data`), which the
    coefficients' columns then follow.
    """

    nominal: LinearSecondOrder
    library: Library = eqx.field(static=True)
    regressed: tuple[int, ...] = eqx.field(static=True)
    coefficients: jax.Array
    diffusion_library: Library | None = eqx.field(static=True, default=None)
    diffusion_coefficients: jax.Array | None = None
    interpolation: str = eqx.field(static=True, default="held")
    state_range: jax.Array | None = None
    model_error_sd: tuple[float, ...] | None = eqx.field(static=True, default=None)
    terms: TermTable | None = None

    def perturbation(self, x, u):
        """Discovered extra rate at one sample, `S Theta L(x, u)`.

        **Arguments:**

        - `x`: the state `(m,)`.
        - `u`: the input `(n,)` (read only by the library's `input` family).

        **Returns:** the extra rate `(m,)`: the discovered terms in the `regressed` rows, zero
        in the others (coefficients of one draw, unbatched).
        """
        values = self.library.eval_single(x, u) if self.terms is None else eval_terms(self.terms, x, u)
        h = jnp.asarray(self.coefficients) @ values
        return jnp.zeros(self.nominal.m, h.dtype).at[jnp.asarray(self.regressed)].set(h)

    def rate(self, x, u):
        """Updated state rate at one sample: the nominal rate plus `perturbation`.

        **Arguments:**

        - `x`: the state `(m,)`.
        - `u`: the input `(n,)`.

        **Returns:** the rate `(m,)`.
        """
        return self.nominal.rate(x, u) + self.perturbation(x, u)

    @property
    def stochastic(self) -> bool:
        return self.diffusion_coefficients is not None

    @property
    def additive_noise(self) -> bool:
        """True when the diffusion has no state-dependent term (ShARK applies)."""
        return self.diffusion_library is None or set(self.diffusion_library.names) <= {"1"}

    def diffusion_variance(self, x):
        """Discovered diffusion `Gamma_vv(x)` of every velocity at one state, floored at zero.

        **Arguments:**

        - `x`: the state `(m,)`.

        **Returns:** `Gamma_vv(x)`, shape `(d,)`, velocity^2/s.
        """
        gamma = jnp.asarray(self.diffusion_coefficients) @ self.diffusion_library.eval_single(x)
        return jnp.maximum(gamma, 0.0)

    def diffusion(self, x):
        """`G(x)` of the SDE: the nominal force path `M^-1 B`, rescaled to the discovered diffusion.

        Each velocity row is rescaled so that `(G G^T)_vv = Gamma_vv(x)`. The unknown force
        keeps the nominal model's input structure (so one Brownian path drives the truth and
        the twin alike); a velocity the nominal `B` does not force gets no noise.

        **Arguments:**

        - `x`: the state `(m,)`.

        **Returns:** `G(x)`, shape `(m, n)`; zero kinematic and extra rows.
        """
        G = systems.diffusion_matrix(self.nominal)
        vel = jnp.asarray(self.nominal.velocity_index)
        nominal_var = jnp.sum(G[vel] ** 2, axis=1)
        scale = jnp.where(nominal_var > 0, jnp.sqrt(self.diffusion_variance(x) / jnp.where(nominal_var > 0, nominal_var, 1.0)), 0.0)
        return G * jnp.ones(G.shape[0], G.dtype).at[vel].set(scale)[:, None]


def _draw_index(result, num_draws: int, key) -> tuple[np.ndarray, np.ndarray]:
    chains, draws = result.equations[0].theta.shape[:2]
    flat = jax.random.choice(key, chains * draws, (num_draws,), replace=num_draws > chains * draws)
    flat = np.asarray(flat)
    return flat // draws, flat % draws


def posterior_twins(result, num_draws: int = 100, key=None) -> UpdatedTwin:
    """`num_draws` joint posterior draws of an update's twin, stacked on a leading axis.

    Every draw takes all equations' coefficients from one (chain, draw) of the Gibbs run:
    the twin's parameter uncertainty, inclusion included (an excluded term is zero). The
    (chain, draw) pairs are chosen at random, with replacement only when `num_draws` exceeds
    the run's draws. A refined update (`dtwin_jax.update.refine_output_error`) draws the
    selected terms' coefficients from their refined Gaussian posterior instead (the others
    are zero).

    **Arguments:**

    - `result`: the update's `UpdateResult`.
    - `num_draws`: `S`, the number of draws (default 100), positive.
    - `key`: JAX PRNG key of the choice of draws (and of the refined draws); None (default)
      for `jax.random.key(0)`.

    **Returns:** the `UpdatedTwin` with `coefficients (S, q, K)` (and, output-only,
    `diffusion_coefficients (S, d, Kd)` of the diffusion terms some draw uses).
    """
    if num_draws < 1:
        raise DataError(f"num_draws must be positive, got {num_draws}")
    check_posterior_draws(num_draws, sum(e.theta.shape[-1] for e in result.equations))
    key = jax.random.key(0) if key is None else key
    c, k = _draw_index(result, num_draws, key)
    drift = [e for e in result.equations if e.kind == "drift"]
    diffusion = [e for e in result.equations if e.kind == "diffusion"]
    names = result.nominal.state_names
    twin = result.twin
    if result.refinement is not None:
        ref = result.refinement
        mean, cov = np.asarray(ref["mean"]), np.asarray(ref["cov"]).reshape(len(ref["mean"]), -1)
        draws = np.asarray(jax.random.multivariate_normal(jax.random.fold_in(key, 1), mean, cov, (num_draws,),
                                                          method="svd"))
        coef = refined_coefficients((num_draws, *twin.coefficients.shape), ref["index"], draws)
    else:
        coef = np.stack([e.theta[c, k] for e in drift], axis=1)  # (S, q, K)
    if not diffusion:
        return eqx.tree_at(lambda t: t.coefficients, twin, jnp.asarray(coef))
    dcoef = np.stack([e.theta[c, k] for e in diffusion], axis=1)  # (S, d, Kd)
    assert [e.state for e in diffusion] == [names[v] for v in result.nominal.velocity_index]
    return UpdatedTwin(twin.nominal, twin.library, twin.regressed, jnp.asarray(coef), *diffusion_terms(result, dcoef),
                       twin.interpolation, twin.state_range, twin.model_error_sd)


def refined_coefficients(shape, index, values) -> np.ndarray:
    """Coefficients with an output-error refinement's terms set and all others zero.

    **Arguments:**

    - `shape`: the coefficients' shape `(..., q, K)`.
    - `index`: the flat entries `(P,)` of each `(q, K)` block that the refinement holds.
    - `values`: their values `(..., P)`, in each rate's units.

    **Returns:** the coefficients, a float64 array of `shape`.
    """
    flat = np.zeros(tuple(shape[:-2]) + (shape[-2] * shape[-1],))
    flat[..., np.asarray(index, int)] = values
    return flat.reshape(shape)


def diffusion_terms(result, dcoef) -> tuple[Library, jax.Array]:
    """An output-only update's diffusion library, kept to the terms some row of `dcoef` uses.

    A constant-only diffusion then stays additive noise, for ShARK.

    **Arguments:**

    - `result`: the update's `UpdateResult` (its `preprocessing["diffusion_library"]`).
    - `dcoef`: diffusion coefficients `(..., d, Kd)` over the whole diffusion library.

    **Returns:** `(library, coefficients)`: the diffusion `Library` cut to the used terms, and
    `dcoef` cut to them, `(..., d, Kd')`.
    """
    dcoef = np.asarray(dcoef)
    used = _used_columns(dcoef)
    dlib = parse_library(result.preprocessing["diffusion_library"], result.nominal.m, 0).subset(used)
    return dlib, jnp.asarray(dcoef[..., used])


def _one(twins: UpdatedTwin, coef, dcoef) -> UpdatedTwin:
    """The twin of one draw: `twins` with its batched coefficient arrays replaced."""
    if dcoef is None:
        return eqx.tree_at(lambda t: t.coefficients, twins, coef)
    return eqx.tree_at(lambda t: (t.coefficients, t.diffusion_coefficients), twins, (coef, dcoef))


def _used_columns(coef) -> np.ndarray:
    """`(K,)` True where some row of `coef (..., K)` is non-zero."""
    coef = np.asarray(coef)
    return np.any(coef.reshape(-1, coef.shape[-1]) != 0, axis=0)


def used_terms(twins: UpdatedTwin) -> UpdatedTwin:
    """`twins` with the drift library cut to the terms some draw uses.

    The same rate: the others are zero in every draw. The solver then evaluates a handful of
    terms at each stage, not the whole library (example 2: 4 of 256). Traced coefficients:
    unchanged.

    **Arguments:**

    - `twins`: the stacked twins, coefficients `(S, q, K)`.

    **Returns:** the twins with library and coefficients `(S, q, K')` cut to the used terms
    (`twins` itself when all are used).
    """
    try:
        coef = np.asarray(twins.coefficients)
    except jax.errors.TracerArrayConversionError:
        return twins
    used = _used_columns(coef)
    if used.all():
        return twins
    return dataclasses.replace(twins, library=twins.library.subset(used), coefficients=jnp.asarray(coef[..., used]))


def library_as_data(twins: UpdatedTwin) -> UpdatedTwin:
    """`twins` with the drift library as data and the coefficients padded to its size class.

    The drift library becomes a table (`dtwin_jax.library.term_table`) and the coefficients
    are padded with zeros to the table's size class: the same rate, and a solver program that
    depends on that size class alone, not on which terms (a monitored structure's twin
    compiles its simulation once, whatever its selection becomes). Traced coefficients, or
    twins already holding their terms as data: unchanged.

    **Arguments:**

    - `twins`: the stacked twins, coefficients `(S, q, K)`.

    **Returns:** the twins with `terms` set, an empty `library` and coefficients padded with
    zero columns to the table's size.
    """
    try:
        coef = np.asarray(twins.coefficients)
    except jax.errors.TracerArrayConversionError:
        return twins
    if twins.terms is not None:
        return twins
    table = term_table(twins.library)
    coef = np.concatenate([coef, np.zeros(coef.shape[:-1] + (table.family.shape[0] - coef.shape[-1],))], axis=-1)
    blank = Library((), twins.library.num_states, twins.library.num_inputs, "", ())
    return dataclasses.replace(twins, library=blank, terms=table, coefficients=jnp.asarray(coef))


def is_nonsmooth(twins: UpdatedTwin) -> bool:
    """Whether a term of a non-smooth family is selected in some draw of `twins`.

    The non-smooth families are `systems.NONSMOOTH_FAMILIES`: `sign`, `Abs`, `x*Abs`. With
    traced coefficients, any such term in the library counts.

    **Arguments:**

    - `twins`: the stacked twins.

    **Returns:** True when such a term is used (or, traced, present), else False.
    """
    families = [f for f, idx in twins.library.blocks for _ in idx]
    rough = np.array([f in systems.NONSMOOTH_FAMILIES for f in families])
    if not rough.any():
        return False
    try:
        coef = np.asarray(twins.coefficients)
    except jax.errors.TracerArrayConversionError:
        return True
    return bool(np.any(_used_columns(coef) & rough))


def fixed_substeps(nominal: LinearSecondOrder, t) -> int:
    """Fixed solver steps per sample interval for a non-smooth twin.

    At most `STEP_RADIANS` (0.05 rad) of the nominal model's fastest mode per step, at least
    `MIN_SUBSTEPS` (4) and at most `MAX_SUBSTEPS` (256); 8 when the model or `t` is traced.

    **Arguments:**

    - `nominal`: the twin's nominal model.
    - `t`: sample times `(N,)`, s (the longest interval counts).

    **Returns:** the number of steps per sample interval, an int.
    """
    try:
        M, C, K = (np.asarray(a) for a in (nominal.M, nominal.C, nominal.K))
        dt = float(np.max(np.diff(np.asarray(t))))
    except jax.errors.TracerArrayConversionError:
        return 8
    d = M.shape[0]
    A = np.block([[np.zeros((d, d)), np.eye(d)], [-np.linalg.solve(M, K), -np.linalg.solve(M, C)]])
    rho = float(np.max(np.abs(np.linalg.eigvals(A))))
    return int(min(max(math.ceil(rho * dt / STEP_RADIANS), MIN_SUBSTEPS), MAX_SUBSTEPS))


def divergence_bounds(twins: UpdatedTwin, x0, u=None) -> tuple[jax.Array, jax.Array]:
    """The box a prediction must stay in; a draw that leaves it has diverged.

    With a training range (`twins.state_range`, centre `c`, half-width `w`): `c +- 100
    max(w, |x0 - c|)` (`DIVERGENCE_FACTOR`), unbounded for a state that never moved.
    Without: `+- 1e6` (`FALLBACK_FACTOR`) times the scale of every state, the larger
    of `|x0|` and the nominal model's static response to the largest input (displacements;
    times the fastest nominal frequency for velocities); unbounded where that scale is 0.
    Jittable.

    **Arguments:**

    - `twins`: the twins (their `state_range`, or their nominal model).
    - `x0`: the prediction's initial state `(m,)`.
    - `u`: the prediction's input `(N, n)` or `(S, N, n)`, or None (default; output-only).

    **Returns:** `(lower, upper)`: the bounds of every state, each `(m,)`, the states' units
    (infinite where unbounded).
    """
    x0 = jnp.asarray(x0, dtype=float)
    if twins.state_range is not None:
        return _range_bounds(jnp.asarray(twins.state_range, dtype=float), x0)
    return _fallback_bounds(twins.nominal, x0, None if u is None else jnp.asarray(u, dtype=float))


# Each bound one program: eagerly (the prediction's set-up), each operation was one.
@jax.jit
def _range_bounds(r, x0):
    centre, half = r.mean(axis=1), (r[:, 1] - r[:, 0]) / 2
    half = jnp.where(half > 0, DIVERGENCE_FACTOR * jnp.maximum(half, jnp.abs(x0 - centre)), jnp.inf)
    return centre - half, centre + half


@eqx.filter_jit
def _fallback_bounds(nominal: LinearSecondOrder, x0, u):
    d = nominal.d
    scale = jnp.abs(x0)
    if u is not None:
        umax = jnp.max(jnp.abs(u).reshape(-1, nominal.n), axis=0)
        static = jnp.abs(jnp.linalg.pinv(nominal.K) @ nominal.B) @ umax
        omega = jnp.sqrt(jnp.linalg.norm(jnp.linalg.solve(nominal.M, nominal.K)))
        scale = scale.at[:d].max(static).at[d : 2 * d].max(omega * static)
    half = jnp.where(scale > 0, FALLBACK_FACTOR * scale, jnp.inf)
    return -half, half


@strong_jit
def _paths(twins: UpdatedTwin, x0, t, u, keys, lower, upper, substeps):
    """`paths (S, N, m)`, `status (S,)` and `stop_time (S,)` of every draw."""
    if twins.stochastic:
        run = lambda c, dc, k: systems.simulate_sde_checked(_one(twins, c, dc), x0, t, k, lower, upper)
        return jax.vmap(run)(twins.coefficients, twins.diffusion_coefficients, keys)
    # The adaptive solve one draw after another on the CPU: vmapped, every draw takes every
    # draw's steps, through selects (example 1's 30 draws over 10 s: 6.4 s vmapped, 3.1 s
    # mapped, one core). Fixed steps (the SDE above, non-smooth or band-limited twins) vmap.
    adaptive = substeps is None and twins.interpolation != "bandlimited"
    method = default_batch_method() if adaptive else "vectorized"
    run = lambda c, uu: systems.simulate_checked(
        _one(twins, c, None), x0, t, uu, lower, upper, rtol=1e-8, atol=1e-10, interpolation=twins.interpolation,
        substeps=substeps,
    )
    if u.ndim == 3:
        return batch_map(run, method, twins.coefficients, u)
    return batch_map(lambda c: run(c, u), method, twins.coefficients)


def _run_paths(twins: UpdatedTwin, x0, t, u, keys, lower, upper, substeps):
    """`_paths` through an exported program where the process keeps them (the command
    line): a new process then skips tracing the diffrax solve (time that a warm update's
    model-error check would otherwise spend)."""
    args = strong_types(jax.tree.map(jnp.asarray, (twins, x0, t, u, keys, lower, upper)))
    return aot.call("paths", lambda *a: _paths(*a, substeps), args, (substeps,))


@jax.jit  # one program (eagerly, each operation was one)
def _summary(paths, status) -> dict:
    """Mean and 95% band over the draws that finished (failed draws' paths become NaN)."""
    ok = status == systems.OK
    paths = jnp.where(ok[:, None, None], paths, jnp.nan)
    lower, upper = jnp.nanquantile(paths, jnp.array([0.025, 0.975]), axis=0)
    return {"mean": jnp.nanmean(paths, axis=0), "lower": lower, "upper": upper, "paths": paths}


def _chunks(S: int, progress: bool) -> int:
    """Draws per compiled call: all at once, or about a tenth each for a progress bar."""
    return S if not progress else max(1, math.ceil(S / 10))


def predict(twins: UpdatedTwin, x0, t, u=None, *, key=None, shared_path: bool = False, substeps: int | None = None,
            progress: bool = False, max_failed: float = MAX_FAILED, model_error: bool = True) -> dict:
    """Posterior-predictive simulation of stacked twins (`posterior_twins`).

    An input-output twin is simulated under the given input; an output-only twin is driven
    by Brownian forcing. A draw diverges when a state leaves `divergence_bounds` (100x the
    training range) or becomes non-finite: a diffrax `Event` ends its solve there, so an
    unstable twin is reported in seconds; running out of solver steps is reported the same
    way. Smooth input-output twins take adaptive Dopri8.

    **Arguments:**

    - `twins`: the stacked twins, `S` draws on the leading axis of their coefficients.
    - `x0`: the initial state `(m,)`.
    - `t`: sample times `(N,)`, s.
    - `u`: the input `(N, n)` of an input-output twin (held over each step or interpolated,
      as `twins.interpolation`), or `(S, N, n)`, one input per draw (future loads that are
      themselves uncertain); required for an input-output twin, ignored for an output-only
      one.
    - `key`: JAX PRNG key of an output-only twin's Brownian paths, an independent path per
      draw (the band holds the process noise too); None (default) for `jax.random.key(0)`.
    - `shared_path`: one Brownian path for all draws (the band holds the parameter
      uncertainty only; the truth driven by `systems.simulate_sde(..., key)` sees the same
      path). Default False.
    - `substeps`: fixed solver steps per sample interval for a twin with a non-smooth term
      (`is_nonsmooth`: `sign`, `Abs`), which an adaptive solver chatters on; None (default)
      for `fixed_substeps`.
    - `progress`: a tqdm bar on standard error, advanced by chunks of about a tenth of the
      draws (each chunk one call of the same compiled program). Default False.
    - `max_failed`: the largest fraction of draws that may diverge or fail (dropped from
      mean and band with a `PredictionWarning`); more raise a one-line `DataError` saying
      when and in how many draws. Default `MAX_FAILED` (0.05).
    - `model_error`: widen the band by the twin's model error (`twins.model_error_sd`, its
      free-run error on its training data; `with_model_error`) when it has one. Default True.

    **Returns:** a dict: `t (N,)` s; `mean`, `lower`, `upper` (2.5% and 97.5% quantiles),
    each `(N, m)` over the draws that finished; `paths (S, N, m)` (NaN for a failed draw);
    `status (S,)` (`systems.OK`, `DIVERGED`, `MAX_STEPS`, `FAILED`); `stop_time (S,)` s; and
    `warnings` (list of str). Jittable with `progress=False`: under `jax.jit` nothing is
    raised or warned, and `status` says which draws failed.
    """
    from dtwin_jax.progress import Bar, tick

    S = jnp.shape(twins.coefficients)[0]
    check_prediction(S, np.shape(t)[0], twins.nominal.m, option="draws")
    twins = used_terms(twins)
    # Not part of the solve: a static field in the program's key would compile one program
    # per fitted twin.
    error_sd, twins = twins.model_error_sd, dataclasses.replace(twins, model_error_sd=None)
    t = jnp.asarray(t, dtype=float)
    x0 = jnp.asarray(x0, dtype=float)
    if twins.stochastic:
        key = jax.random.key(0) if key is None else key
        keys = jnp.stack([key] * S) if shared_path else jax.random.split(key, S)
        u = None
    else:
        if u is None:
            raise DataError("an input-output twin needs the input u (N, n) to predict")
        u = jnp.asarray(u, dtype=float)
        u = u.reshape((S, t.shape[0], -1) if u.ndim == 3 else (t.shape[0], -1))
        keys = None
    lower, upper = divergence_bounds(twins, x0, u)
    if substeps is None and not twins.stochastic and is_nonsmooth(twins):
        substeps = fixed_substeps(twins.nominal, t)
    twins = library_as_data(twins)
    size = _chunks(S, progress)
    if size >= S:
        paths, status, stop = _run_paths(twins, x0, t, u, keys, lower, upper, substeps)
    else:
        parts = []
        with Bar(True, S, "predict (draws)"):
            for start in range(0, S, size):
                # Every chunk the same size (the last padded with draw 0): one compilation.
                idx = np.minimum(np.arange(start, start + size), S - 1)
                dcoef = twins.diffusion_coefficients[idx] if twins.stochastic else None
                uc = u[idx] if u is not None and u.ndim == 3 else u
                part = jax.block_until_ready(_run_paths(_one(twins, twins.coefficients[idx], dcoef), x0, t, uc,
                                                        None if keys is None else keys[idx], lower, upper, substeps))
                parts.append(jax.tree.map(lambda a: a[: min(size, S - start)], part))
                tick(min(size, S - start))
        paths, status, stop = (jnp.concatenate(p) for p in zip(*parts))
    out = {"t": t, **_summary(paths, status), "status": status, "stop_time": stop, "warnings": []}
    if model_error and error_sd is not None:
        out = with_model_error(out, jnp.asarray(error_sd))
    if not isinstance(status, jax.core.Tracer):
        message = failure_message(np.asarray(status), np.asarray(stop))
        if message and np.sum(np.asarray(status) != systems.OK) > max_failed * S:
            raise DataError(f"{message}: the twin is unstable under this input (or far outside the range it was "
                            "updated on)")
        if message:
            message += ": those draws are left out of the mean and band"
            warnings.warn(message, PredictionWarning, stacklevel=2)
            out["warnings"] = [message]
    return out


def failure_message(status: np.ndarray, stop_time: np.ndarray) -> str:
    """One line on the draws of a prediction that did not finish, or "" when all did.

    **Arguments:**

    - `status`: the draws' status codes `(S,)` from `predict`.
    - `stop_time`: the times `(S,)` s their solves reached, from `predict`.

    **Returns:** the message (when, and in how many draws, the twin diverged, ran out of
    solver steps or failed), or "".
    """
    S, parts = status.size, []
    for code, what in ((systems.DIVERGED, "the twin diverged at t = {t:.4g} s in {n} of {S} posterior draws (a state "
                                          f"left {DIVERGENCE_FACTOR:g}x its training range, or became non-finite)"),
                       (systems.MAX_STEPS, "the solver ran out of steps at t = {t:.4g} s in {n} of {S} posterior draws "
                                           "(a very stiff or chattering twin)"),
                       (systems.FAILED, "the solver failed at t = {t:.4g} s in {n} of {S} posterior draws")):
        hit = status == code
        if hit.any():
            parts.append(what.format(t=float(np.min(stop_time[hit])), n=int(hit.sum()), S=S))
    return "; ".join(parts)


def simulation_error(predicted, measured) -> dict:
    """Free-run simulation errors of a prediction against a measurement, per state.

    **Arguments:**

    - `predicted`: the simulated states `(N, m)`.
    - `measured`: the measured states `(N, m)`, the same units.

    **Returns:** `{"rmse": (m,), "nrmse": (m,)}`: the RMS error (the signal's units) and the
    normalised RMS error (RMS error / std of `measured`, dimensionless).
    """
    predicted, measured = np.asarray(predicted), np.asarray(measured)
    rms = np.sqrt(np.mean((predicted - measured) ** 2, axis=0))
    return {"rmse": rms, "nrmse": rms / np.std(measured, axis=0)}


def with_model_error(prediction: dict, model_sd) -> dict:
    """`prediction` with its 95% band widened by a Gaussian model error of std `model_sd`.

    A posterior over the library's coefficients does not carry the model error: the
    half-widths add in quadrature, `sqrt(((upper - lower) / 2)^2 + (1.96 model_sd)^2)`
    around the mean. `model_sd` is typically the twin's free-run error on its own training
    data (`simulation_error`'s `rmse`, after the start transient): on the Silverbox, within
    the training amplitude, the widened band covers the arrow close to its nominal 95%, the
    parameter band alone far less.

    **Arguments:**

    - `prediction`: the dict of `predict` (its `mean`, `lower`, `upper`, `(N, m)`).
    - `model_sd`: the model error's std, `(m,)` or a scalar, the states' units.

    **Returns:** a copy of `prediction` with `lower` and `upper` `(N, m)` replaced.
    """
    mean, lower, upper = (jnp.asarray(prediction[k]) for k in ("mean", "lower", "upper"))
    half = jnp.sqrt(((upper - lower) / 2) ** 2 + (1.96 * jnp.asarray(model_sd)) ** 2)
    return {**prediction, "lower": mean - half, "upper": mean + half}


def effective_stiffness(twins: UpdatedTwin, x) -> jax.Array:
    """The linear stiffness `K_eff` of each twin draw at a state.

    `K_eff = -M d(acceleration)/d(displacement)` at zero input (force per displacement);
    equals the nominal `K` where the perturbation adds no stiffness.

    **Arguments:**

    - `twins`: the stacked twins, `S` draws.
    - `x`: the state `(m,)`, or one per draw `(S, m)`.

    **Returns:** `K_eff`, shape `(S, d, d)`, the nominal `K`'s units.
    """
    nominal = twins.nominal
    d = nominal.d
    x = jnp.broadcast_to(jnp.asarray(x, dtype=float), (jnp.shape(twins.coefficients)[0], nominal.m))
    u = jnp.zeros(nominal.n)

    def one(c, dc, xx):
        twin = _one(twins, c, dc if twins.stochastic else None)
        jac = jax.jacfwd(lambda z: twin.rate(z, u))(xx)
        return -nominal.M @ jac[d : 2 * d, :d]

    return jax.vmap(one)(twins.coefficients, _diffusion_or_zeros(twins), x)


def _diffusion_or_zeros(twins):
    S = jnp.shape(twins.coefficients)[0]
    return twins.diffusion_coefficients if twins.stochastic else jnp.zeros((S, 0))


def degradation_forecast(twins: UpdatedTwin, prediction: dict, damage: int, critical: float,
                         *, every: int = 10) -> dict:
    """Damage, stiffness loss and failure probability over a long prediction.

    The failure probability at each time is the fraction of draws whose damage has passed
    `critical` by then, with a 95% Jeffreys interval for its Monte Carlo error. The
    stiffness loss is the relative loss `1 - K_eff / K` of the diagonal of
    `effective_stiffness`, along each draw's own damage path with the other states at zero.

    **Arguments:**

    - `twins`: the stacked twins the prediction was made with.
    - `prediction`: the dict of `predict` (its `t (N,)` s and `paths (S, N, m)`).
    - `damage`: the index of the damage state among the `m` states.
    - `critical`: the damage's failure level, in its units.
    - `every`: the stiffness loss at every `every`-th sample (default 10).

    **Returns:** a dict: `t (N,)` s; `critical`; `damage_mean`, `damage_lower`,
    `damage_upper` `(N,)` (mean, 2.5% and 97.5% over draws); `probability`,
    `probability_lower`, `probability_upper` `(N,)`; `loss_t (N',)` s, the times of the
    stiffness loss; and `loss_mean`, `loss_lower`, `loss_upper` `(N', d)` (mean, 2.5% and
    97.5% over draws).
    """
    from scipy.stats import beta

    paths = np.asarray(prediction["paths"])
    S = paths.shape[0]
    dmg = paths[:, :, damage]
    passed = np.maximum.accumulate(dmg, axis=1) > critical
    k = passed.sum(axis=0)
    lower = np.where(k > 0, beta.ppf(0.025, k + 0.5, S - k + 0.5), 0.0)
    upper = np.where(k < S, beta.ppf(0.975, k + 0.5, S - k + 0.5), 1.0)
    # Stiffness along each draw's own damage path (the other states at zero).
    nominal = twins.nominal
    idx = np.arange(0, paths.shape[1], every)
    states = np.zeros((idx.size, S, nominal.m))
    states[:, :, damage] = dmg[:, idx].T
    K0 = np.diagonal(np.asarray(nominal.K))
    stiff = jax.lax.map(lambda xs: effective_stiffness(twins, xs), jnp.asarray(states))  # (N', S, d, d)
    loss = 1.0 - np.diagonal(np.asarray(stiff), axis1=-2, axis2=-1) / K0  # (N', S, d)
    q = lambda a, p: np.quantile(a, p, axis=0)
    return {
        "t": np.asarray(prediction["t"]),
        "critical": float(critical),
        "damage_mean": dmg.mean(axis=0), "damage_lower": q(dmg, 0.025), "damage_upper": q(dmg, 0.975),
        "probability": k / S, "probability_lower": lower, "probability_upper": upper,
        "loss_t": np.asarray(prediction["t"])[idx],
        "loss_mean": loss.mean(axis=1), "loss_lower": np.quantile(loss, 0.025, axis=1),
        "loss_upper": np.quantile(loss, 0.975, axis=1),
    }
