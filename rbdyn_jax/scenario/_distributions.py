"""The distributions of a scenario's quantities: eqx.Modules whose leaves are arrays, so they
enter the compiled sweep as runtime arguments; `DISTRIBUTIONS`, those a `dist` may name; the
key of a draw by its key path, and the cast of a tree to the scenario's dtype."""

from __future__ import annotations

import abc
import zlib
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import inertia as _inertia, rotation


class AbstractDistribution(eqx.Module):
    """The distribution of one quantity: `sample(key)` gives one draw, `centre()` its
    nominal value (the scenario's nominal model, and the stand-in for a non-finite draw)."""

    @abc.abstractmethod
    def sample(self, key) -> jax.Array: ...

    @abc.abstractmethod
    def centre(self) -> jax.Array: ...


class Fixed(AbstractDistribution):
    """Always `value`."""

    value: jax.Array

    def sample(self, key):
        return self.value

    def centre(self):
        return self.value


class Normal(AbstractDistribution):
    """Independent normal components, `mean + std · N(0, 1)`; centred on `mean`."""

    mean: jax.Array
    std: jax.Array

    def sample(self, key):
        return self.mean + self.std * jax.random.normal(key, self.mean.shape, self.mean.dtype)

    def centre(self):
        return self.mean


class Uniform(AbstractDistribution):
    """Independent uniform components on `[low, high)`; centred on the mid-point."""

    low: jax.Array
    high: jax.Array

    def sample(self, key):
        u = jax.random.uniform(key, self.low.shape, self.low.dtype)
        return self.low + (self.high - self.low) * u

    def centre(self):
        return 0.5 * (self.low + self.high)


class LogNormal(AbstractDistribution):
    """`median · exp(sigma · N(0, 1))`, componentwise (positive quantities); centred on
    `median`."""

    median: jax.Array
    sigma: jax.Array

    def sample(self, key):
        z = jax.random.normal(key, self.median.shape, self.median.dtype)
        return self.median * jnp.exp(self.sigma * z)

    def centre(self):
        return self.median


class UniformSO3(AbstractDistribution):
    """A uniformly distributed attitude: a normalised 4-D Gaussian (Haar measure on SO(3)),
    sign fixed to w ≥ 0. It has no centre: `centre()` is the identity."""

    dtype: Any = eqx.field(static=True, default=jnp.float64)

    def sample(self, key):
        q = jax.random.normal(key, (4,), self.dtype)
        q = q / jnp.linalg.norm(q)
        return jnp.where(q[0] < 0, -q, q)

    def centre(self):
        # A NumPy array of the dtype, made a JAX array of the default float where float64
        # is off: no warning for a dtype JAX does not have.
        return jnp.asarray(np.array([1.0, 0.0, 0.0, 0.0], np.dtype(self.dtype)))


class EulerAttitude(AbstractDistribution):
    """Attitude from Euler angles drawn from `angles` (a distribution) in sequence `seq`;
    centred on the attitude of the centre angles."""

    angles: AbstractDistribution
    seq: str = eqx.field(static=True)

    def sample(self, key):
        return rotation.euler_to_quat(self.angles.sample(key), self.seq)

    def centre(self):
        return rotation.euler_to_quat(self.angles.centre(), self.seq)


class DispersedInertia(AbstractDistribution):
    """A physical inertia around `nominal`: the log-Cholesky coordinates θ of its planar
    tensor J' = L Lᵀ (`inertia.to_log_cholesky`) are perturbed, the log-diagonal by
    `sigma · N(0, 1)` and each off-diagonal `L_ij` by `sigma · sqrt(L_ii L_jj) · N(0, 1)`,
    a relative spread of about `sigma` in every moment and product of inertia. Every sample
    is physical (triangle inequalities hold) by construction
    (docs/physics.md#log-cholesky-parametrisation). Centred on `nominal`."""

    nominal: jax.Array
    sigma: jax.Array

    def sample(self, key):
        theta = _inertia.to_log_cholesky(self.nominal)
        d = jnp.exp(theta[:3])
        scale = jnp.stack(
            [1.0, 1.0, 1.0, jnp.sqrt(d[1] * d[0]), jnp.sqrt(d[2] * d[0]), jnp.sqrt(d[2] * d[1])]
        ).astype(theta.dtype)
        z = jax.random.normal(key, (6,), theta.dtype)
        return _inertia.from_log_cholesky(theta + self.sigma * scale * z)

    def centre(self):
        return self.nominal


# The distributions a quantity's `dist` may name; their fields are the table's keys.
DISTRIBUTIONS: dict[str, type[AbstractDistribution]] = {
    "fixed": Fixed,
    "normal": Normal,
    "uniform": Uniform,
    "lognormal": LogNormal,
}


def _path_key(key, path: str):
    return jax.random.fold_in(key, zlib.crc32(path.encode()) & 0x7FFFFFFF)


def _as_dtype(tree, dtype):
    """`tree` with every floating array in `dtype`. JAX computes in float32 only where every
    input is float32 (a float64 array, with float64 enabled, promotes the whole solve), so
    a float32 scenario's distributions, models and states are cast to it explicitly;
    concrete arrays through NumPy (no JAX program for the cast)."""
    dtype = np.dtype(dtype)

    def cast(x):
        if not eqx.is_array(x) or not jnp.issubdtype(x.dtype, jnp.floating) or x.dtype == dtype:
            return x
        if isinstance(x, jax.core.Tracer):
            return x.astype(dtype)
        return jnp.asarray(np.asarray(x).astype(dtype))

    return jax.tree_util.tree_map(cast, tree)
