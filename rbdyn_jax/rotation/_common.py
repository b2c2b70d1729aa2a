"""Arithmetic the rotation modules share: the broadcast of the batch axes of arrays with
given trailing sizes, the dot product over the last axis, and a norm, `atan2` and `hypot`
whose gradients stay finite at zero (a double `where`).
"""

import jax.numpy as jnp
from jaxtyping import Array


def _dot(a: Array, b: Array) -> Array:
    return jnp.sum(a * b, axis=-1)


def _broadcast(*xs: Array, trailing: tuple[int, ...]) -> list[Array]:
    """Broadcast the leading (batch) axes of arrays with the given trailing sizes."""
    batch = jnp.broadcast_shapes(*(x.shape[: x.ndim - n] for x, n in zip(xs, trailing)))
    return [jnp.broadcast_to(x, batch + x.shape[x.ndim - n :]) for x, n in zip(xs, trailing)]


def _safe_norm(v: Array, small: float) -> tuple[Array, Array]:
    """(|v|, |v|² < small²) with a gradient that is finite at v = 0 (double where)."""
    n2 = _dot(v, v)
    is_small = n2 < small * small
    n = jnp.sqrt(jnp.where(is_small, 1.0, n2))
    return jnp.where(is_small, 0.0, n), is_small


def _safe_atan2(y: Array, x: Array) -> Array:
    """`atan2(y, x)`, 0 at the origin, with a finite gradient there."""
    origin = (y == 0) & (x == 0)
    return jnp.where(origin, 0.0, jnp.arctan2(y, jnp.where(origin, 1.0, x)))


def _safe_hypot(x: Array, y: Array) -> Array:
    """`hypot(x, y)` with a finite (zero) gradient at the origin."""
    r2 = x * x + y * y
    zero = r2 == 0
    return jnp.where(zero, 0.0, jnp.sqrt(jnp.where(zero, 1.0, r2)))
