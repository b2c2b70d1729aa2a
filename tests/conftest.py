"""Test configuration: float64 and strict promotion, so that silent bugs fail loudly.

The library itself never flips `jax_enable_x64`; only tests, benchmarks and the CLI do.
"""

import jax
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")


@pytest.fixture
def rng():
    """A seeded NumPy generator: every random test is reproducible."""
    return np.random.default_rng(20261121)
