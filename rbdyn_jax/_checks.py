"""Input checks shared by the pure-function layers (conventions: docs/physics.md#conventions).

Static mistakes (shapes, strings) raise `ValueError` at trace time naming the argument;
value-dependent mistakes go through `eqx.error_if`, whose returned value must be used.
"""

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike


def as_float_array(x: ArrayLike, name: str) -> Array:
    """`jnp.asarray(x)` promoted to a floating dtype (JAX's default float for ints/bools).
    A value that is not traced (NumPy, a list, a concrete array) stays concrete even while
    a caller's function is traced (`jnp.asarray` alone would give a tracer there), so that
    its checks run now, on values, instead of as runtime checks in the caller's program."""
    if isinstance(x, jax.core.Tracer):
        return _as_float_array(x, name)
    with jax.ensure_compile_time_eval():
        return _as_float_array(x, name)


def _as_float_array(x, name):
    try:
        x = jnp.asarray(x)
    except TypeError as e:
        raise ValueError(f"`{name}` must be array-like, got {type(x).__name__}.") from e
    if not jnp.issubdtype(x.dtype, jnp.floating):
        if jnp.issubdtype(x.dtype, jnp.complexfloating):
            raise ValueError(f"`{name}` must be real, got dtype {x.dtype}.")
        x = x.astype(jnp.result_type(float))
    return x


def check_trailing(x: ArrayLike, trailing: tuple[int, ...], name: str) -> Array:
    """Return `x` as a float array whose trailing axes are `trailing`, else `ValueError`."""
    x = as_float_array(x, name)
    n = len(trailing)
    if x.ndim < n or tuple(x.shape[x.ndim - n :]) != trailing:
        want = "(*batch, " + ", ".join(map(str, trailing)) + ")"
        raise ValueError(f"`{name}` must have shape {want}, got {tuple(x.shape)}.")
    return x


def check_scalar(x: ArrayLike, name: str) -> Array:
    """Return `x` as a float array of shape `()`, else `ValueError`. A model's scalar
    parameter takes no batch axes in its constructor: a 3-vector would broadcast against
    the vectors it multiplies and give a wrong field without an error. A batch of models
    is built by `eqx.filter_vmap` over the constructor, which sees one scalar."""
    x = as_float_array(x, name)
    if x.ndim:
        raise ValueError(
            f"`{name}` must be a scalar, got shape {tuple(x.shape)} (for a batch of models, "
            "build them with `eqx.filter_vmap` over the constructor)."
        )
    return x


def check_batch(x: ArrayLike, name: str) -> Array:
    """A `*batch` array of scalars (any shape) as a float array."""
    return as_float_array(x, name)


def holds_now(check, *args) -> bool:
    """Whether `check(*args, xp=np)` (boolean arrays) is true everywhere, evaluated now in
    NumPy (also inside a caller's trace): `False` without evaluating it if any argument is
    traced or not finite.

    The fast path of a value check on concrete input: `check` is written once for an array
    namespace `xp`, runs here in NumPy, and the caller skips `eqx.error_if` when it holds. In
    JAX the first check of a process traces, lowers and compiles a program, a noticeable
    wait for the first model built. Otherwise, and for non-finite input (some NumPy routines
    reject it), the caller takes its usual `eqx.error_if` path, which raises as always."""
    if any(isinstance(a, jax.core.Tracer) for a in jax.tree_util.tree_leaves(args)):
        return False
    args = jax.tree_util.tree_map(np.asarray, args)
    if not all(np.all(np.isfinite(a)) for a in jax.tree_util.tree_leaves(args)):
        return False
    return bool(np.all(check(*args, xp=np)))


def sqrt_eps(dtype) -> float:
    """√(machine epsilon) of `dtype` as a Python float (safe under `jit`): the relative
    tolerance of value checks."""
    return float(jnp.finfo(dtype).eps) ** 0.5
