"""Small helpers shared by the analytic modules: the inputs' conversion, broadcasting and
checks (`common`, `broadcast_batch`, `check_times`), and arithmetic that stays finite in
the discarded branches of a `where` (`safe_div`, `safe_sqrt`, `sign`)."""

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from .._checks import as_float_array


def safe_div(x: Array, y: Array) -> Array:
    """`x / y`, with 0 where `y == 0` (value and gradient finite in discarded branches)."""
    ok = y != 0
    return jnp.where(ok, x / jnp.where(ok, y, 1.0), 0.0)


def safe_sqrt(x: Array) -> Array:
    """`√max(x, 0)` with a finite gradient at 0 (for discarded `where` branches)."""
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)


def sign(x: Array) -> Array:
    """+1 for x ≥ 0, −1 otherwise (never 0: a sign to multiply a magnitude by)."""
    return jnp.where(x >= 0, 1.0, -1.0).astype(x.dtype)


def common(*xs: ArrayLike, names: tuple[str, ...]) -> list[Array]:
    """Float arrays of one dtype broadcast to one shape (elementwise special functions)."""
    arrs = [as_float_array(x, n) for x, n in zip(xs, names)]
    dtype = arrs[0].dtype
    for a in arrs[1:]:
        dtype = jnp.promote_types(dtype, a.dtype)
    shape = jnp.broadcast_shapes(*(a.shape for a in arrs))
    return [jnp.broadcast_to(a.astype(dtype), shape) for a in arrs]


def broadcast_batch(*pairs: tuple[Array, int]) -> list[Array]:
    """Broadcast the leading (batch) axes of arrays with the given numbers of core axes.

    Done explicitly so that `jnp.vectorize` sees equal batch ranks (no rank promotion).
    """
    batch = jnp.broadcast_shapes(*(x.shape[: x.ndim - k] for x, k in pairs))
    return [jnp.broadcast_to(x, batch + x.shape[x.ndim - k :]) for x, k in pairs]


def check_times(ts: ArrayLike, name: str = "ts", batched: bool = False) -> Array:
    ts = as_float_array(ts, name)
    if batched and ts.ndim < 1:
        raise ValueError(f"`{name}` must have shape (*batch, n), got shape {tuple(ts.shape)}.")
    if not batched and ts.ndim != 1:
        raise ValueError(f"`{name}` must be a 1-D array of times, got shape {tuple(ts.shape)}.")
    return ts
