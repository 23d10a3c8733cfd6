"""Updating a digital twin from measurements: the public entry points, and what both
frameworks share. Data flows one way:

    measurements (t, x, u, xdot)                      data.check_records
      -> states denoised or estimated, nominal removed  preprocess, input_output.update / output_only.update
      -> targets and library -> sufficient statistics   input_output.targets, output_only.stats
      -> (+ the previous update's statistics: re-update) update.lifecycle
      -> spike-and-slab sampler, every equation in one call  update.sampling
      -> posterior per equation -> updated twin         update.result (UpdateResult.twin)
      -> (optional: coefficients refined by output error)  input_output.output_error

Framework 1, `update_input_output` (`dtwin_jax.input_output`): states, inputs and
rates measured. Framework 2, `update_output_only` (`dtwin_jax.output_only`): the
response alone. Both return an `UpdateResult` (`result`), which a later update takes
as `previous` (`lifecycle`) and `dtwin_jax.io.store` saves and loads.
"""

import importlib

# name -> submodule that defines it, imported on first use (PEP 562): an input-output update
# need not import framework 2's modules.
_PUBLIC = {
    "UpdatedTwin": "dtwin_jax.models.prediction",
    "denoise_states": "dtwin_jax.input_output.update",
    "update_input_output": "dtwin_jax.input_output.update",
    "update_output_only": "dtwin_jax.output_only.update",
    "OUTPUT_ONLY_LIBRARY": "dtwin_jax.output_only.update",
    "DIFFUSION_LIBRARY": "dtwin_jax.output_only.update",
    "refine_output_error": "dtwin_jax.input_output.output_error",
    "SamplerSettings": "dtwin_jax.update.result",
    "UpdateResult": "dtwin_jax.update.result",
}
__all__ = list(_PUBLIC)


def __getattr__(name: str):
    if name not in _PUBLIC:
        raise AttributeError(f"module 'dtwin_jax.update' has no attribute {name!r}")
    value = getattr(importlib.import_module(_PUBLIC[name]), name)
    globals()[name] = value
    return value
