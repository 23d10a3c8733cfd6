"""Spike-and-slab Gibbs sampler for sparse Bayesian linear regression, from sufficient
statistics: the kernel (`dtwin_jax.sampler.kernel`, blackjax-style `init` / `step`),
the chains' starts (`dtwin_jax.sampler.starts`) and the drivers that run them
(`dtwin_jax.sampler.driver`). Every public name of the three is importable from here."""

from dtwin_jax.sampler import driver, kernel, starts
from dtwin_jax.sampler.driver import *  # noqa: F403
from dtwin_jax.sampler.kernel import *  # noqa: F403
from dtwin_jax.sampler.starts import *  # noqa: F403

__all__ = [*kernel.__all__, *starts.__all__, *driver.__all__]
