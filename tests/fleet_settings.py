"""The fleet's static settings, shared by tests/test_fleet.py and its sharded subprocess."""

import dtwin_jax  # noqa: F401  (float64)
from dtwin_jax.library import parse_library
from dtwin_jax.sampler import SamplerSettings

STATIC = dict(lib=parse_library("poly:3,sign,abs,xabs,input", 2, 1), dt=1e-3, half_width=20,
              settings=SamplerSettings(num_chains=2, num_draws=300, num_burnin=150))
