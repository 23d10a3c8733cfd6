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
``previous`` (``lifecycle``) and :mod:`dtwin_jax.store` saves and loads.
"""

from dtwin_jax.prediction import UpdatedTwin
from dtwin_jax.update.input_output import denoise_states, update_input_output
from dtwin_jax.update.output_only import DIFFUSION_LIBRARY, OUTPUT_ONLY_LIBRARY, update_output_only
from dtwin_jax.update.output_error import refine_output_error
from dtwin_jax.update.result import SamplerSettings, UpdateResult

__all__ = [
    "SamplerSettings",
    "UpdateResult",
    "UpdatedTwin",
    "denoise_states",
    "update_input_output",
    "update_output_only",
    "refine_output_error",
    "OUTPUT_ONLY_LIBRARY",
    "DIFFUSION_LIBRARY",
]
