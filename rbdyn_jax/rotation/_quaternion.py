"""Quaternion algebra: the Hamilton product, conjugate, normalisation, the rotation of a
vector, and the conversions between a quaternion and its rotation matrix (direction-cosine
matrix, body → parent).
"""

import equinox as eqx
import jax.numpy as jnp

from .._checks import check_trailing
from .._custom_types import (
    Matrix,
    MatrixLike,
    Quaternion,
    QuaternionLike,
    Vector,
    VectorLike,
)
from .._vector import cross, split
from ._common import _broadcast, _dot


def quat_multiply(q1: QuaternionLike, q2: QuaternionLike) -> Quaternion:
    """Hamilton product `q1 ⊗ q2` (docs/physics.md#quaternions): `R(q1 ⊗ q2) = R(q1) R(q2)`.

    **Arguments:** `q1`, `q2`: quaternions `[w, x, y, z]` with broadcastable batch axes.

    **Returns:** their product, shape `(*batch, 4)`.
    """
    q1 = check_trailing(q1, (4,), "q1")
    q2 = check_trailing(q2, (4,), "q2")
    q1, q2 = _broadcast(q1, q2, trailing=(1, 1))
    w1, x1, y1, z1 = split(q1)
    w2, x2, y2, z2 = split(q2)
    return jnp.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        axis=-1,
    )


def quat_conjugate(q: QuaternionLike) -> Quaternion:
    """Conjugate `[w, −x, −y, −z]`: the inverse rotation of a unit quaternion."""
    q = check_trailing(q, (4,), "q")
    return jnp.concatenate([q[..., :1], -q[..., 1:]], axis=-1)


def quat_normalize(q: QuaternionLike) -> Quaternion:
    """`q / |q|`. A zero quaternion is a runtime error (it represents no rotation).

    **Arguments:** `q`: quaternion(s) `(*batch, 4)`, any non-zero norm.

    **Returns:** unit quaternion(s) of the same shape.
    """
    q = check_trailing(q, (4,), "q")
    n2 = _dot(q, q)
    n2 = eqx.error_if(n2, n2 == 0, "`q` is a zero quaternion: it represents no rotation.")
    return q / jnp.sqrt(n2)[..., None]


def quat_rotate(q: QuaternionLike, v: VectorLike) -> Vector:
    """`R(q) v`: body components `v` to parent components (docs/physics.md#quaternions); `q` unit.

    Computed as `v + 2w (u × v) + 2 u × (u × v)` with `q = [w, u]`.
    """
    q = check_trailing(q, (4,), "q")
    v = check_trailing(v, (3,), "v")
    q, v = _broadcast(q, v, trailing=(1, 1))
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * cross(u, v)
    return v + w * t + cross(u, t)


def quat_to_dcm(q: QuaternionLike) -> Matrix:
    """Direction-cosine matrix `R(q)` (body → parent, docs/physics.md#quaternions).

    Uses the homogeneous form divided by `|q|²`, so a non-unit `q` gives the rotation of
    `q / |q|`.

    **Returns:** `(*batch, 3, 3)` rotation matrix.
    """
    q = check_trailing(q, (4,), "q")
    w, x, y, z = split(q)
    s = 2.0 / (w * w + x * x + y * y + z * z)
    xx, yy, zz = s * x * x, s * y * y, s * z * z
    xy, xz, yz = s * x * y, s * x * z, s * y * z
    wx, wy, wz = s * w * x, s * w * y, s * w * z
    rows = [
        [1.0 - yy - zz, xy - wz, xz + wy],
        [xy + wz, 1.0 - xx - zz, yz - wx],
        [xz - wy, yz + wx, 1.0 - xx - yy],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def dcm_to_quat(R: MatrixLike) -> Quaternion:
    """Unit quaternion of a rotation matrix, stable for every rotation.

    Shepperd's method (as scipy): of the four algebraically equal formulas, use the one
    built on the largest of `(tr R, R_xx, R_yy, R_zz)`, so the normalised vector is never
    small. The sign is the one that formula gives (q and −q are the same rotation).

    **Arguments:** `R`: `(*batch, 3, 3)` rotation matrix (body → parent).

    **Returns:** `(*batch, 4)` unit quaternion.
    """
    R = check_trailing(R, (3, 3), "R")
    r00, r11, r22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    r01, r02, r10 = R[..., 0, 1], R[..., 0, 2], R[..., 1, 0]
    r12, r20, r21 = R[..., 1, 2], R[..., 2, 0], R[..., 2, 1]
    tr = r00 + r11 + r22
    candidates = jnp.stack(
        [
            jnp.stack([1.0 + tr, r21 - r12, r02 - r20, r10 - r01], axis=-1),
            jnp.stack([r21 - r12, 1.0 + 2 * r00 - tr, r01 + r10, r02 + r20], axis=-1),
            jnp.stack([r02 - r20, r01 + r10, 1.0 + 2 * r11 - tr, r12 + r21], axis=-1),
            jnp.stack([r10 - r01, r02 + r20, r12 + r21, 1.0 + 2 * r22 - tr], axis=-1),
        ],
        axis=-2,
    )
    choice = jnp.argmax(jnp.stack([tr, r00, r11, r22], axis=-1), axis=-1)
    q = jnp.take_along_axis(candidates, choice[..., None, None], axis=-2)[..., 0, :]
    return q / jnp.sqrt(_dot(q, q))[..., None]
