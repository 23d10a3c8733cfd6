"""dtwin-jax: update the digital twin of a dynamical system with interpretable physics.

Data flows one way:
measurements -> nominal removed -> targets and library -> sampler -> posterior -> updated twin.
"""

import jax

# The one piece of global state: every computation here is float64.
jax.config.update("jax_enable_x64", True)

from dtwin_jax.errors import DataError  # noqa: E402

__all__ = ["DataError"]
__version__ = "0.1.0"
