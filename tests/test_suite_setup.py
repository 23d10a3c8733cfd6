"""The suite's own set-up (tests/conftest.py): XLA's optimizing passes off by default, on for
a test marked ``optimized`` and for the processes it starts, and back as they were after it."""

import os

import jax
import pytest


def _passes_off() -> bool:
    return bool(jax.config.values["jax_disable_most_optimizations"])


@pytest.mark.optimized
def test_a_test_marked_optimized_compiles_with_the_passes_on_and_so_do_its_subprocesses():
    assert not _passes_off()
    assert os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] == "0"  # what a subprocess's JAX reads


def test_an_unmarked_test_compiles_as_the_suite_was_told(suite_passes_off):
    # After the marked test in the same process (file order; pytest-xdist may send it to the
    # other worker), this also shows that the hook put both settings back.
    assert _passes_off() == suite_passes_off
    assert (os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] == "1") == suite_passes_off
