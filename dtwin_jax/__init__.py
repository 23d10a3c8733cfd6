"""dtwin-jax: update the digital twin of a dynamical system with interpretable physics.

Data flows one way:
measurements -> nominal removed -> targets and library -> sampler -> posterior -> updated twin.
"""

import jax

# The one piece of global state: every computation here is float64.
jax.config.update("jax_enable_x64", True)

from dtwin_jax import sampler, systems  # noqa: E402
from dtwin_jax.errors import DataError  # noqa: E402
from dtwin_jax.library import DEFAULT_LIBRARY, Library, parse_library  # noqa: E402
from dtwin_jax.measurement import measure  # noqa: E402
from dtwin_jax.systems import LinearSecondOrder, PerturbedSystem, simulate  # noqa: E402
from dtwin_jax.predict import UpdatedTwin, posterior_twins, predict, simulation_error, with_model_error  # noqa: E402
from dtwin_jax.update import (  # noqa: E402
    SamplerSettings,
    UpdateResult,
    update_input_output,
    update_output_only,
)

__all__ = [
    "DEFAULT_LIBRARY",
    "DataError",
    "Library",
    "LinearSecondOrder",
    "PerturbedSystem",
    "SamplerSettings",
    "UpdateResult",
    "UpdatedTwin",
    "measure",
    "parse_library",
    "posterior_twins",
    "predict",
    "with_model_error",
    "sampler",
    "simulate",
    "simulation_error",
    "systems",
    "update_input_output",
    "update_output_only",
]
__version__ = "0.1.0"
