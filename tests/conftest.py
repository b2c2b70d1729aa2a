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


# The suite's core (marked `core`): the physics, the solves, their derivatives and the
# compile layer, run again under the next JAX (`make test-jax-next`). The sweep store, the
# Dask cluster, the CLI, the docs and the benchmarks are checked on the locked versions.
CORE = {
    "test_analytic.py",
    "test_batching.py",
    "test_cheapest.py",
    "test_compat.py",
    "test_dynamics.py",
    "test_float32.py",
    "test_frames.py",
    "test_identify.py",
    "test_inertia.py",
    "test_integrate.py",
    "test_lanes.py",
    "test_layering.py",
    "test_models.py",
    "test_program.py",
    "test_reference.py",
    "test_rotation.py",
    "test_rows.py",
    "test_splitting.py",
    "test_torques.py",
    "test_vector.py",
    "test_xla.py",
}


def pytest_collection_modifyitems(config, items):
    """Marks the core's tests `core`. Tests marked `gpu` run where JAX's default backend is
    a GPU, and are skipped elsewhere (CI has none)."""
    for item in items:
        if item.path.name in CORE:
            item.add_marker(pytest.mark.core)
    marked = [item for item in items if "gpu" in item.keywords]
    if marked and jax.default_backend() != "gpu":
        skip = pytest.mark.skip(
            reason=f"needs a GPU (JAX's default backend is {jax.default_backend()})"
        )
        for item in marked:
            item.add_marker(skip)
