"""dtwin-jax: update the digital twin of a dynamical system with interpretable physics.

Data flows one way:
measurements -> nominal removed -> targets and library -> sampler -> posterior -> updated twin.

The public names below are imported on first use (PEP 562), so `import dtwin_jax` and
`dtwin-jax --help` cost little more than importing jax.
"""

import importlib

import jax

# The one piece of global state: every computation here is float64.
jax.config.update("jax_enable_x64", True)

# name -> module that defines it
_PUBLIC = {
    "DEFAULT_LIBRARY": "library",
    "Library": "library",
    "parse_library": "library",
    "DataError": "errors",
    "measure": "preprocess.measurement",
    "LinearSecondOrder": "models.systems",
    "PerturbedSystem": "models.systems",
    "simulate": "models.systems",
    "UpdatedTwin": "models.prediction",
    "posterior_twins": "models.prediction",
    "predict": "models.prediction",
    "simulation_error": "models.prediction",
    "with_model_error": "models.prediction",
    "SamplerSettings": "update",
    "UpdateResult": "update",
    "refine_output_error": "update",
    "update_input_output": "update",
    "update_output_only": "update",
    "configure_runtime": "runtime",
}
_SUBMODULES = ("sampler",)

__all__ = sorted([*_PUBLIC, *_SUBMODULES])
__version__ = "0.1.0"


def __getattr__(name: str):
    if name in _SUBMODULES:
        return importlib.import_module(f"dtwin_jax.{name}")
    if name in _PUBLIC:
        value = getattr(importlib.import_module(f"dtwin_jax.{_PUBLIC[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'dtwin_jax' has no attribute {name!r}")


def __dir__():
    return sorted([*globals(), *__all__])
