"""The installed package as a user meets it: its version in one place."""

import importlib.metadata

import rbdyn_jax as rb


def test_version_is_the_installed_distributions():
    assert rb.__version__ == importlib.metadata.version("rbdyn_jax")
