"""Attitude kinematics: quaternions, direction-cosine matrices, Euler/Cardan angles.

Conventions (docs/physics.md#quaternions, docs/physics.md#euler-angles): Hamilton quaternions,
scalar first `[w, x, y, z]`; `R(q)` maps body components to parent components,
`v_parent = R(q) v_body`; Euler sequences exactly as `scipy.spatial.transform.Rotation`: upper
case ("ZXZ") intrinsic, rotations about the moving axes, `R = R_a(α) R_b(β) R_c(γ)`; lower case
("zxz") extrinsic, about the fixed axes, so that "abc" with angles (α, β, γ) is intrinsic "CBA"
with angles (γ, β, α).

Every function is pure, accepts leading `*batch` axes and is safe under `jit`, `vmap` and
`grad`: singular branches use a double `where` (a safe argument in the branch not taken) and
Taylor series near zero, so that values and gradients stay finite there.
"""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array

from ._checks import check_trailing
from ._custom_types import (
    Angles,
    AnglesLike,
    BoolArray,
    Matrix,
    MatrixLike,
    Quaternion,
    QuaternionLike,
    Scalar,
    ScalarLike,
    Vector,
    VectorLike,
)
from ._vector import HIGHEST, cross, parse_seq, split

# Second angles closer than this to the singular set are treated as gimbal lock by
# `quat_to_euler`; the same value as scipy's `Rotation.as_euler`.
GIMBAL_LOCK_EPS = 1e-7


# ---------------------------------------------------------------------------------------
# small helpers
# ---------------------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------------------
# quaternion algebra
# ---------------------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------------------
# rotation vectors and interpolation
# ---------------------------------------------------------------------------------------

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


# ---------------------------------------------------------------------------------------
# Euler / Cardan angles
# ---------------------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------------------
# kinematic equations
# ---------------------------------------------------------------------------------------


def skew(v: VectorLike) -> Matrix:
    """`[v]×`, the matrix with `[v]× u = v × u`."""
    v = check_trailing(v, (3,), "v")
    x, y, z = split(v)
    o = jnp.zeros_like(x)
    rows = [[o, -z, y], [z, o, -x], [-y, x, o]]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def vee(Omega: MatrixLike) -> Vector:
    """Inverse of `skew`, from the skew-symmetric part of `Omega`."""
    W = check_trailing(Omega, (3, 3), "Omega")
    return 0.5 * jnp.stack(
        [W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]],
        axis=-1,
    )


def quat_derivative(q: QuaternionLike, omega: VectorLike) -> Quaternion:
    """Quaternion kinematics `q' = ½ q ⊗ (0, ω)`, ω in body components.

    docs/physics.md#quaternion-kinematics."""
    q = check_trailing(q, (4,), "q")
    omega = check_trailing(omega, (3,), "omega")
    zero = jnp.zeros_like(omega[..., :1])
    return 0.5 * quat_multiply(q, jnp.concatenate([zero, omega], axis=-1))


def dcm_derivative(R: MatrixLike, omega: VectorLike) -> Matrix:
    """`R' = R [ω]×` for `R` body → parent and ω in body components.

    docs/physics.md#direction-cosines.

    Equivalently `l' + Ω l = 0` with `l = Rᵀ` and `Ω = [ω]×`, Pars (1971), eq. (7.15.4).
    """
    R = check_trailing(R, (3, 3), "R")
    R, W = _broadcast(R, skew(omega), trailing=(2, 2))
    return jnp.matmul(R, W, precision=HIGHEST)


def omega_from_dcm(R: MatrixLike, R_dot: MatrixLike) -> Vector:
    """Body angular velocity from a rotation matrix and its rate: `Ω = −l' lᵀ`, `l = Rᵀ`.

    Pars (1971), eq. (7.15.7); docs/physics.md#direction-cosines. Ω is skew-symmetric for an
    exact rotation path, and its skew part is taken so rounding in `R_dot` does not leak in.
    """
    R = check_trailing(R, (3, 3), "R")
    R_dot = check_trailing(R_dot, (3, 3), "R_dot")
    R, R_dot = _broadcast(R, R_dot, trailing=(2, 2))
    l = jnp.swapaxes(R, -1, -2)
    l_dot = jnp.swapaxes(R_dot, -1, -2)
    return vee(-jnp.matmul(l_dot, jnp.swapaxes(l, -1, -2), precision=HIGHEST))


def poisson(gamma: VectorLike, omega: VectorLike) -> Vector:
    """Poisson equation `γ' = γ × ω` for a vector fixed in the parent frame.

    Shinibaev et al. (2013), eq. (3); docs/physics.md#poisson-equations.

    `gamma` holds its body components, `omega` the body angular velocity; written out,
    `dγ/dt = r γ' − q γ''`, `dγ'/dt = p γ'' − r γ`, `dγ''/dt = q γ − p γ'`.
    """
    gamma = check_trailing(gamma, (3,), "gamma")
    omega = check_trailing(omega, (3,), "omega")
    gamma, omega = _broadcast(gamma, omega, trailing=(1, 1))
    return cross(gamma, omega)


__all__ = [
    "GIMBAL_LOCK_EPS",
    "dcm_derivative",
    "dcm_to_euler",
    "dcm_to_quat",
    "euler_rates_to_omega",
    "euler_to_dcm",
    "euler_to_quat",
    "gimbal_lock_distance",
    "omega_from_dcm",
    "omega_to_euler_rates",
    "poisson",
    "quat_conjugate",
    "quat_derivative",
    "quat_from_rotvec",
    "quat_multiply",
    "quat_normalize",
    "quat_rotate",
    "quat_to_dcm",
    "quat_to_euler",
    "quat_to_rotvec",
    "skew",
    "slerp",
    "vee",
]
