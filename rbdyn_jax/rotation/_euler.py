"""The twelve Euler/Cardan sequences: conversions between angles and quaternions or rotation
matrices (Bernardes & Viollet's method, scipy's ranges and gimbal-lock rule), the distance
from the singular set, and the maps between Euler-angle rates and the body angular velocity.
"""

import jax.numpy as jnp
from jaxtyping import Array

from .._checks import check_trailing
from .._custom_types import (
    Angles,
    AnglesLike,
    BoolArray,
    Matrix,
    MatrixLike,
    Quaternion,
    QuaternionLike,
    Scalar,
    Vector,
    VectorLike,
)
from .._vector import cross, parse_seq, split
from ._common import _broadcast, _dot, _safe_atan2, _safe_hypot
from ._quaternion import dcm_to_quat, quat_multiply, quat_normalize, quat_rotate, quat_to_dcm

# Second angles closer than this to the singular set are treated as gimbal lock by
# `quat_to_euler`; the same value as scipy's `Rotation.as_euler`.
GIMBAL_LOCK_EPS = 1e-7


def _as_intrinsic(angles: Array, seq: str) -> tuple[Array, list[int]]:
    """Angles and axes of the intrinsic sequence equal to `seq` ("abc" ≡ "CBA" reversed)."""
    axes, extrinsic = parse_seq(seq)
    if extrinsic:
        return angles[..., ::-1], axes[::-1]
    return angles, axes


def _axis_quat(axis: int, angle: Array) -> Array:
    half = 0.5 * angle
    parts = [jnp.cos(half)] + [jnp.zeros_like(half)] * 3
    parts[1 + axis] = jnp.sin(half)
    return jnp.stack(parts, axis=-1)


def euler_to_quat(angles: AnglesLike, seq: str) -> Quaternion:
    """Unit quaternion of Euler/Cardan angles, as `Rotation.from_euler(seq, angles)`.

    **Arguments:** `angles`: `(*batch, 3)` radians; `seq`: one of the 12 sequences, upper
    case intrinsic ("ZXZ": `R = Rz(ψ) Rx(θ) Rz(φ)`, docs/physics.md#euler-angles), lower
    case extrinsic.

    **Returns:** `(*batch, 4)` quaternion `[w, x, y, z]`.
    """
    angles = check_trailing(angles, (3,), "angles")
    angles, axes = _as_intrinsic(angles, seq)
    q = _axis_quat(axes[0], angles[..., 0])
    for i in (1, 2):
        q = quat_multiply(q, _axis_quat(axes[i], angles[..., i]))
    return q


def euler_to_dcm(angles: AnglesLike, seq: str) -> Matrix:
    """Rotation matrix of Euler/Cardan angles (see `euler_to_quat`)."""
    return quat_to_dcm(euler_to_quat(angles, seq))


def quat_to_euler(
    q: QuaternionLike, seq: str, *, return_gimbal_lock: bool = False
) -> Angles | tuple[Angles, BoolArray]:
    """Euler/Cardan angles of a quaternion, as `Rotation.as_euler(seq)`.

    The quaternion method of Bernardes & Viollet (2022), the one scipy uses, with the same
    ranges: first and third angles in [−π, π]; the second in [0, π] for proper sequences
    (first axis = third axis) and in [−π/2, π/2] for Tait–Bryan ones.

    **Gimbal lock.** When the second angle is within `GIMBAL_LOCK_EPS` (1e-7 rad) of its
    singular values (0 or π for proper, ±π/2 for Tait–Bryan) only the sum or difference of
    the first and third angles is defined. Then, as scipy does, the **third angle is set to
    0** and the first carries the whole rotation. scipy warns; here pass
    `return_gimbal_lock=True` to also receive a boolean mask of where it happened (or call
    `gimbal_lock_distance` on the angles). The result is still an exact representation of
    the rotation.

    **Arguments:** `q`: `(*batch, 4)` quaternion (normalised here; zero is an error);
    `seq`: one of the 12 sequences; `return_gimbal_lock`: also return the mask.

    **Returns:** `(*batch, 3)` angles in radians, and the `(*batch,)` mask if asked.
    """
    axes, extrinsic = parse_seq(seq)
    q = quat_normalize(q)
    # Bernardes & Viollet work on the extrinsic form: intrinsic "ABC" is extrinsic "cba".
    i, j, k = axes if extrinsic else axes[::-1]
    proper = i == k
    if proper:
        k = 3 - i - j
    sign = (i - j) * (j - k) * (k - i) // 2  # +1 for an even permutation of (0, 1, 2)
    w = q[..., 0]
    qi, qj, qk = q[..., 1 + i], q[..., 1 + j], q[..., 1 + k]
    if proper:
        a, b, c, d = w, qi, qj, sign * qk
    else:
        a, b, c, d = w - qj, qi + sign * qk, qj + w, sign * qk - qi

    second = 2.0 * jnp.arctan2(_safe_hypot(c, d), _safe_hypot(a, b))
    half_sum = _safe_atan2(b, a)
    half_diff = _safe_atan2(d, c)
    near_zero = jnp.abs(second) <= GIMBAL_LOCK_EPS
    near_pi = jnp.abs(second - jnp.pi) <= GIMBAL_LOCK_EPS
    locked = near_zero | near_pi

    # Regular case; in extrinsic order the first angle is half_sum - half_diff.
    first = half_sum - half_diff
    third = half_sum + half_diff
    # Gimbal lock: third angle (of the caller's sequence) 0, the first takes the rest.
    locked_angle = jnp.where(near_zero, 2.0 * half_sum, 2.0 * half_diff * (-1 if extrinsic else 1))
    if not proper:
        third = sign * third
        locked_angle = locked_angle if extrinsic else sign * locked_angle
        second = second - 0.5 * jnp.pi
    if extrinsic:
        out = [jnp.where(locked, locked_angle, first), second, jnp.where(locked, 0.0, third)]
    else:
        out = [jnp.where(locked, locked_angle, third), second, jnp.where(locked, 0.0, first)]
    angles = jnp.stack(out, axis=-1)
    # Into [−π, π] as scipy does: only values outside move, so an exact ±π keeps its sign.
    two_pi = 2.0 * jnp.pi
    angles = jnp.where(
        angles > jnp.pi, angles - two_pi, jnp.where(angles < -jnp.pi, angles + two_pi, angles)
    )
    if return_gimbal_lock:
        return angles, locked
    return angles


def dcm_to_euler(
    R: MatrixLike, seq: str, *, return_gimbal_lock: bool = False
) -> Angles | tuple[Angles, BoolArray]:
    """Euler/Cardan angles of a rotation matrix (see `quat_to_euler`)."""
    return quat_to_euler(dcm_to_quat(R), seq, return_gimbal_lock=return_gimbal_lock)


def gimbal_lock_distance(angles: AnglesLike, seq: str) -> Scalar:
    """Angular distance (radians) of the second angle from the singular set of `seq`.

    The Euler-rate map of a sequence is singular where its first and third rotation axes align
    (docs/physics.md#gimbal-lock, the "paradox" of Pars (1971), §7.16): second angle ≡ 0 (mod π)
    for proper sequences (first axis = third axis, e.g. ZXZ), ≡ π/2 (mod π) for Tait–Bryan ones
    (e.g. XYZ). Returns `min_k |β − β_k|` over that set, in [0, π/2].
    """
    angles = check_trailing(angles, (3,), "angles")
    axes, _ = parse_seq(seq)
    beta = angles[..., 1]
    if axes[0] != axes[2]:
        beta = beta - 0.5 * jnp.pi
    return jnp.abs(beta - jnp.pi * jnp.round(beta / jnp.pi))


def _rate_columns(angles: Array, seq: str) -> tuple[Array, Array, Array]:
    """Body components of the three rotation axes of `seq` at `angles`.

    For intrinsic "ABC", `R = R_a(α) R_b(β) R_c(γ)` and `Rᵀ Ṙ = [ω]×` give
    `ω = α' R_c(γ)ᵀ R_b(β)ᵀ e_a + β' R_c(γ)ᵀ e_b + γ' e_c`; an extrinsic sequence is first
    rewritten as the intrinsic one with reversed axes and angles.
    """
    angles, axes = _as_intrinsic(angles, seq)
    eye = jnp.eye(3, dtype=angles.dtype)
    e = [jnp.broadcast_to(eye[a], angles.shape) for a in axes]
    qb_inv = _axis_quat(axes[1], -angles[..., 1])
    qc_inv = _axis_quat(axes[2], -angles[..., 2])
    col_a = quat_rotate(qc_inv, quat_rotate(qb_inv, e[0]))
    col_b = quat_rotate(qc_inv, e[1])
    return col_a, col_b, e[2]


def _reorder(x: Array, seq: str) -> Array:
    """Map between the caller's angle order and the intrinsic order of `_rate_columns`."""
    _, extrinsic = parse_seq(seq)
    return x[..., ::-1] if extrinsic else x


def euler_rates_to_omega(angles: AnglesLike, rates: AnglesLike, seq: str) -> Vector:
    """Body angular velocity from Euler-angle rates (docs/physics.md#euler-angle-rates).

    For "ZXZ" = (ψ, θ, φ) this is literally `p = ψ' sinθ sinφ + θ' cosφ`,
    `q = ψ' sinθ cosφ − θ' sinφ`, `r = ψ' cosθ + φ'`; for "ZYZ" Pars (1971), eq. (7.16.1). Valid
    for all 12 sequences, intrinsic or extrinsic; the result is in body components (the frame
    rotated by `euler_to_dcm(angles, seq)`).

    **Arguments:** `angles`, `rates`: `(*batch, 3)` in the order of `seq`.

    **Returns:** `(*batch, 3)` body angular velocity.
    """
    angles = check_trailing(angles, (3,), "angles")
    rates = check_trailing(rates, (3,), "rates")
    angles, rates = _broadcast(angles, rates, trailing=(1, 1))
    cols = _rate_columns(angles, seq)
    r = split(_reorder(rates, seq))
    return r[0][..., None] * cols[0] + r[1][..., None] * cols[1] + r[2][..., None] * cols[2]


def omega_to_euler_rates(angles: AnglesLike, omega: VectorLike, seq: str) -> Angles:
    """Euler-angle rates from the body angular velocity (inverse of `euler_rates_to_omega`).

    For "ZXZ" it reproduces docs/physics.md#euler-angle-rates: `ψ' = (p sinφ + q cosφ)/sinθ`,
    `θ' = p cosφ − q sinφ`, `φ' = r − (p sinφ + q cosφ) cotθ`. Solved in closed form with the
    adjugate of the map `[c_a c_b c_c]`, whose determinant is ±sin β (proper) or ±cos β
    (Tait–Bryan): the result is non-finite only where that determinant is exactly zero, the
    singular set measured by `gimbal_lock_distance`, and finite, with a finite gradient,
    everywhere else (large near the singular set: check that distance).

    **Arguments:** `angles`, `omega`: `(*batch, 3)`.

    **Returns:** `(*batch, 3)` rates in the order of `seq`.
    """
    angles = check_trailing(angles, (3,), "angles")
    omega = check_trailing(omega, (3,), "omega")
    angles, omega = _broadcast(angles, omega, trailing=(1, 1))
    ca, cb, cc = _rate_columns(angles, seq)
    # Rows of the inverse of the matrix with columns (ca, cb, cc) are (cb×cc, cc×ca, ca×cb)/det.
    rows = (cross(cb, cc), cross(cc, ca), cross(ca, cb))
    det = _dot(ca, rows[0])
    rates = jnp.stack([_dot(r, omega) for r in rows], axis=-1) / det[..., None]
    return _reorder(rates, seq)
