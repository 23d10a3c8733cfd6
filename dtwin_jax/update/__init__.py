"""Updating a digital twin from measurements. Data flows one way:

    measurements (t, x, u, xdot)                      Records            data.check_records
      -> states denoised or estimated, nominal removed                 input_output / output_only
      -> targets and library -> sufficient statistics                  targets, output_only_stats
      -> (+ the previous update's statistics: re-update)                lifecycle
      -> spike-and-slab sampler, every equation in one call             sampling
      -> posterior per equation -> updated twin                         result (UpdateResult.twin)
      -> (optional: selected coefficients refined by output error)      output_error

Framework 1, :func:`update_input_output` (``input_output``): states, inputs and rates
measured. Framework 2, :func:`update_output_only` (``output_only``): states only; drift by
Kramers-Moyal targets, then diffusion by the Kalman likelihood (``output_only_stats``).
Both return an :class:`UpdateResult` (``result``), which a later update takes as
``previous`` (``lifecycle``) and :mod:`dtwin_jax.io.store` saves and loads.
"""

import importlib

# name -> submodule that defines it, imported on first use (PEP 562): an input-output update
# need not import framework 2's modules.
_PUBLIC = {
    "UpdatedTwin": "dtwin_jax.models.prediction",
    "denoise_states": "dtwin_jax.update.input_output",
    "update_input_output": "dtwin_jax.update.input_output",
    "update_output_only": "dtwin_jax.update.output_only",
    "OUTPUT_ONLY_LIBRARY": "dtwin_jax.update.output_only",
    "DIFFUSION_LIBRARY": "dtwin_jax.update.output_only",
    "refine_output_error": "dtwin_jax.update.output_error",
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
