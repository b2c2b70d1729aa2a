"""Rotation vectors and interpolation: the exponential and logarithm maps between a rotation
vector (axis × angle) and a unit quaternion, with Taylor series at small angles, and
spherical linear interpolation (`slerp`).
"""

import jax.numpy as jnp

from .._checks import check_trailing
from .._custom_types import (
    Quaternion,
    QuaternionLike,
    ScalarLike,
    Vector,
    VectorLike,
)
from ._common import _broadcast, _dot, _safe_norm
from ._quaternion import quat_conjugate, quat_multiply, quat_normalize

# Below this rotation angle (radians) the Taylor branches are used; their truncation error
# is O(angle⁴) ≈ 1e-24 relative, far below float64 rounding.
_SMALL_ANGLE = 1e-6


def quat_from_rotvec(rotvec: VectorLike) -> Quaternion:
    """Unit quaternion of the rotation by `|v|` about `v / |v|` (the exponential map).

    `q = [cos(θ/2), sin(θ/2) v/θ]`, θ = |v|, with a Taylor series for θ → 0 so that value
    and gradient are exact there.
    """
    v = check_trailing(rotvec, (3,), "rotvec")
    theta, small = _safe_norm(v, _SMALL_ANGLE)
    t2 = _dot(v, v)
    half = 0.5 * theta
    w = jnp.where(small, 1.0 - t2 / 8.0 + t2 * t2 / 384.0, jnp.cos(half))
    safe_theta = jnp.where(small, 1.0, theta)
    scale = jnp.where(small, 0.5 - t2 / 48.0 + t2 * t2 / 3840.0, jnp.sin(half) / safe_theta)
    return jnp.concatenate([w[..., None], scale[..., None] * v], axis=-1)


def quat_to_rotvec(q: QuaternionLike) -> Vector:
    """Rotation vector (axis × angle, angle in [0, π]) of a quaternion (the logarithm map).

    The quaternion is normalised and taken with `w ≥ 0` (the shorter of the two rotations
    it could name); a Taylor series handles the angle → 0 limit.
    """
    q = quat_normalize(q)
    q = jnp.where(q[..., :1] < 0, -q, q)
    w = q[..., 0]
    u = q[..., 1:]
    s, small = _safe_norm(u, 0.5 * _SMALL_ANGLE)  # s = sin(angle/2)
    angle = 2.0 * jnp.arctan2(s, w)
    # small angle: angle/sin(angle/2) = 2 + angle²/12 + 7 angle⁴/2880, angle ≈ 2 s / w
    a2 = 4.0 * _dot(u, u) / jnp.where(small, w * w, 1.0)
    scale = jnp.where(
        small, 2.0 + a2 / 12.0 + 7.0 * a2 * a2 / 2880.0, angle / jnp.where(small, 1.0, s)
    )
    return scale[..., None] * u


def slerp(q0: QuaternionLike, q1: QuaternionLike, t: ScalarLike) -> Quaternion:
    """Spherical linear interpolation on the shorter arc: `q0 ⊗ exp(t log(q0* ⊗ q1))`.

    **Arguments:** `q0`, `q1`: unit quaternions `(*batch, 4)`; `t`: `(*batch)` fractions
    (0 gives `q0`, 1 gives `q1` up to sign; values outside [0, 1] extrapolate).

    **Returns:** `(*batch, 4)` unit quaternion(s).
    """
    q0 = check_trailing(q0, (4,), "q0")
    q1 = check_trailing(q1, (4,), "q1")
    t = check_trailing(t, (), "t")
    q0, q1, t = _broadcast(q0, q1, t, trailing=(1, 1, 0))
    rv = quat_to_rotvec(quat_multiply(quat_conjugate(q0), q1))
    return quat_multiply(q0, quat_from_rotvec(t[..., None] * rv))
