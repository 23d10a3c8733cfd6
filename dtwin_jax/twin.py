"""Compatibility: the update code now lives in :mod:`dtwin_jax.update` (``result``,
``lifecycle``, ``sampling``, ``input_output``, ``output_only``, ``output_only_stats``);
this module re-exports its names for code that imports them from here."""

from dtwin_jax.prediction import UpdatedTwin
from dtwin_jax.update.input_output import denoise_states, update_input_output
from dtwin_jax.update.output_only import (
    DIFFUSION_LIBRARY,
    MARGIN_WARN,
    OUTPUT_ONLY_LIBRARY,
    update_output_only,
)
from dtwin_jax.update.output_only_stats import (
    FIRST_PASS_ROWS,
    brownian_variance,
    correction_margin,
    output_only_drift_stats,
)
from dtwin_jax.update.result import SamplerSettings, UpdateResult

__all__ = [
    "SamplerSettings",
    "UpdateResult",
    "UpdatedTwin",
    "denoise_states",
    "update_input_output",
    "update_output_only",
    "OUTPUT_ONLY_LIBRARY",
    "DIFFUSION_LIBRARY",
    "MARGIN_WARN",
    "FIRST_PASS_ROWS",
    "brownian_variance",
    "correction_margin",
    "output_only_drift_stats",
]
