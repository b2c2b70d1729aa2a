"""Small vector helpers shared by the pure-function layers (rotation, dynamics, torques,
frames), below every public module: it imports only JAX and jaxtyping.

The products are written out on a vector's three components, kept as separate arrays
(`split`), instead of `jnp.cross` / `jnp.matmul` / `jnp.einsum`: XLA:CPU runs a batched
3×3 product as a slow library call, and a stack (a concatenation) between two operations
is one that XLA cannot cancel against the slices that follow, so that the `*_parts` forms
are chained on components and stacked once, where a function returns (the comment at the
top of `dynamics.py` says more). Replacing them by the library calls changes the rounding
of every right-hand side and its speed; keep their arithmetic as it is.

Also the parsing of an Euler-angle sequence string (`parse_seq`), shared by every module
that validates a `seq`.
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array

# The precision of every matrix product rbdyn_jax writes as one (`einsum`, `matmul`): at
# JAX's default, NVIDIA GPUs since Ampere multiply float32 in TF32 (10-bit mantissas, ~1e-3
# relative), which a float32 solve's 1e-6 cannot afford. No effect on a CPU or in float64.
HIGHEST = jax.lax.Precision.HIGHEST

# ---------------------------------------------------------------------------------------
# vectors as their components
# ---------------------------------------------------------------------------------------


def split(x: Array) -> list[Array]:
    """The components of `x` along its last axis, as separate arrays."""
    return [x[..., i] for i in range(x.shape[-1])]


def cross_parts(a: list[Array], b: list[Array]) -> list[Array]:
    """`a × b` on vectors given as their three components (`split`); returns the three
    components of the product."""
    ax, ay, az = a
    bx, by, bz = b
    return [ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx]


def cross(a: Array, b: Array) -> Array:
    """`a × b` for arrays `(…, 3)`, written out."""
    return jnp.stack(cross_parts(split(a), split(b)), axis=-1)


def matvec_parts(J: Array, v: list[Array]) -> list[Array]:
    """`J v` for a matrix `(…, 3, 3)` and a vector given as its three components (`split`);
    returns the three components of the product."""
    # Written out: XLA:CPU runs a batched 3×3 einsum as a slow library call, which can cost
    # more than the rest of the right-hand side.
    return [J[..., i, 0] * v[0] + J[..., i, 1] * v[1] + J[..., i, 2] * v[2] for i in range(3)]


def matvec(J: Array, v: Array) -> Array:
    """`J v` for arrays `(…, 3, 3)` and `(…, 3)`, written out."""
    return jnp.stack(matvec_parts(J, split(v)), axis=-1)


# ---------------------------------------------------------------------------------------
# Euler-angle sequences
# ---------------------------------------------------------------------------------------

AXIS_INDEX = {"x": 0, "y": 1, "z": 2}


def parse_seq(seq: str) -> tuple[list[int], bool]:
    """Axis indices of the Euler sequence `seq` ("ZXZ" intrinsic, "zxz" extrinsic, as
    `scipy.spatial.transform.Rotation`) and whether it is extrinsic; a `ValueError` naming
    `seq` for a bad string."""
    if not isinstance(seq, str) or len(seq) != 3:
        raise ValueError(f"`seq` must be a 3-character string such as 'ZXZ', got {seq!r}.")
    if seq.isupper() and set(seq) <= set("XYZ"):
        extrinsic = False
    elif seq.islower() and set(seq) <= set("xyz"):
        extrinsic = True
    else:
        raise ValueError(
            f"`seq` must be three of 'XYZ' (intrinsic) or three of 'xyz' (extrinsic), "
            f"not mixed, got {seq!r}."
        )
    if seq[0] == seq[1] or seq[1] == seq[2]:
        raise ValueError(f"`seq` must not repeat an axis consecutively, got {seq!r}.")
    return [AXIS_INDEX[c] for c in seq.lower()], extrinsic
