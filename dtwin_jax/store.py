"""A twin on disk: save, load, re-update (formats.md, "Saving a twin and predicting with it").

A twin folder holds, format version 1:

* ``twin.json``: ``format`` ("dtwin-jax twin"), ``version``, ``mode``, state and input
  names, the library specs, sampler settings, PIP threshold, preprocessing, checks, the
  ``history`` of updates (time, data size, prior, discovered equations, package version),
  and the output-error ``refinement`` (or null);
* ``nominal.toml``: the nominal model (the nominal file of formats.md);
* ``posterior.nc``: every equation's draws as an arviz DataTree (netCDF, group
  ``posterior``: ``theta_<state>_<kind>``, ``gamma_...``, ``sigma2_...``);
* ``statistics.npz``: the sufficient statistics the sampler saw (``<kind>_gram``,
  ``_xty``, ``_yty``, ``_n``), so that a re-update can use the posterior as its prior;
* ``result.json``: the result file of formats.md for the last update.

The folder is written next to its destination and renamed into place, so a failed save
leaves nothing half-written (an existing twin is replaced only on success).
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from dtwin_jax import sampler
from dtwin_jax.errors import DataError
from dtwin_jax.io import load_nominal, write_json, write_nominal
from dtwin_jax.library import parse_library
from dtwin_jax.posterior import EquationPosterior
from dtwin_jax.resources import check_num_inputs

__all__ = ["FORMAT", "VERSION", "save_twin", "load_twin"]

FORMAT = "dtwin-jax twin"
VERSION = 1
_FILES = ("twin.json", "nominal.toml", "posterior.nc", "statistics.npz", "result.json")


def save_twin(result, path) -> Path:
    """Write the :class:`~dtwin_jax.update.UpdateResult` ``result`` as a twin folder ``path``."""
    path = Path(path)
    lib = result.library
    if parse_library(lib.spec, lib.num_states, lib.num_inputs).names != lib.names:
        raise DataError(f"the library is not described by its spec '{lib.spec}' (a subset?); cannot save it")
    if path.exists() and not path.is_dir():
        raise DataError(f"'{path}' exists and is not a folder")
    if path.exists() and not (path / "twin.json").exists() and any(path.iterdir()):
        raise DataError(f"'{path}' exists and is not a twin folder; not overwriting it")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}."))
    try:
        write_json(tmp / "twin.json", _header(result))
        write_nominal(tmp / "nominal.toml", result.nominal)
        result.to_arviz().to_netcdf(tmp / "posterior.nc", engine="h5netcdf")
        arrays = {f"{kind}_{name}": np.asarray(a) for kind, st in result.statistics.items()
                  for name, a in zip(sampler.SuffStats._fields, st)}
        np.savez(tmp / "statistics.npz", **arrays)
        write_json(tmp / "result.json", result.to_json())
        if path.exists():
            old = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.old."))
            os.replace(path, old / "twin")
            os.replace(tmp, path)
            shutil.rmtree(old)
        else:
            os.replace(tmp, path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)
    return path


def _header(result) -> dict:
    s = result.settings
    return {
        "format": FORMAT,
        "version": VERSION,
        "mode": result.mode,
        "state_names": list(result.state_names),
        "input_names": list(result.input_names),
        "library": result.library.spec,
        "num_inputs": int(result.library.num_inputs),
        "diffusion_library": result.preprocessing.get("diffusion_library"),
        "equations": [{"state": e.state, "kind": e.kind} for e in result.equations],
        "pip_threshold": result.pip_threshold,
        "settings": {
            "num_chains": s.num_chains, "num_draws": s.num_draws, "num_burnin": s.num_burnin,
            "prior": s.prior._asdict(), "p0": s.p0, "v_s": s.v_s, "max_active": s.max_active,
        },
        "seconds": result.seconds,
        "preprocessing": result.preprocessing,
        "checks": result.checks,
        "history": result.history,
        "refinement": result.refinement,
    }


def load_twin(path):
    """Read a twin folder written by :func:`save_twin`; returns an
    :class:`~dtwin_jax.update.UpdateResult` whose twin predicts exactly as the saved one."""
    path = Path(path)
    missing = [f for f in _FILES if not (path / f).is_file()]
    if not path.is_dir() or missing:
        what = "does not exist" if not path.exists() else f"is not a twin folder (no {missing[0]})"
        raise DataError(f"twin '{path}' {what}")
    try:
        head = json.loads((path / "twin.json").read_text())
    except json.JSONDecodeError as e:
        raise DataError(f"'{path / 'twin.json'}' is not valid JSON: {e}") from None
    if head.get("format") != FORMAT:
        raise DataError(f"'{path / 'twin.json'}' is not a dtwin-jax twin (format {head.get('format')!r})")
    if head.get("version") != VERSION:
        raise DataError(f"twin '{path}' has format version {head.get('version')}; this dtwin-jax reads {VERSION}")
    nominal = load_nominal(path / "nominal.toml")
    check_num_inputs(head.get("num_inputs"), nominal.n, f"'{path / 'twin.json'}'")
    lib = parse_library(head["library"], nominal.m, head["num_inputs"])
    # Imported once the header is known good: a bad twin is refused without their cost.
    import arviz as az

    from dtwin_jax.update import SamplerSettings, UpdateResult

    post = az.from_netcdf(path / "posterior.nc", engine="h5netcdf").posterior
    equations = []
    for eq in head["equations"]:
        tag = f"{eq['state']}_{eq['kind']}"
        names = tuple(str(v) for v in post[f"term_{tag}"].values)
        if eq["kind"] == "drift" and names != lib.names:
            raise DataError(f"twin '{path}': the terms of {tag} do not match library '{head['library']}'")
        equations.append(EquationPosterior(
            eq["state"], eq["kind"], names, post[f"gamma_{tag}"].values.astype(bool),
            post[f"theta_{tag}"].values, post[f"sigma2_{tag}"].values, head["pip_threshold"],
        ))
    with np.load(path / "statistics.npz") as z:
        kinds = sorted({k.rsplit("_", 1)[0] for k in z.files})
        statistics = {k: sampler.SuffStats(*(z[f"{k}_{f}"] for f in sampler.SuffStats._fields)) for k in kinds}
    st = head["settings"]
    settings = SamplerSettings(
        num_chains=st["num_chains"], num_draws=st["num_draws"], num_burnin=st["num_burnin"],
        prior=sampler.SpikeSlabPrior(**st["prior"]), p0=st["p0"], v_s=st["v_s"], max_active=st["max_active"],
    )
    return UpdateResult(
        mode=head["mode"], nominal=nominal, library=lib, equations=equations,
        pip_threshold=head["pip_threshold"], settings=settings, seconds=head["seconds"],
        preprocessing=head["preprocessing"], checks=head["checks"], statistics=statistics,
        history=head["history"], refinement=head.get("refinement"),
    )
