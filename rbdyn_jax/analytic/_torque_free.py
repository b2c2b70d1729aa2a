"""Torque-free motion: the axisymmetric body in closed form (angular velocity and
attitude), the triaxial body by Jacobi elliptic functions on both sides of the separatrix
and on it, and the period of its polhode."""

import math

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._checks import as_float_array, check_trailing
from .._custom_types import QuaternionLike, Scalar, ScalarLike, VectorLike
from .._program.xla import jit
from ..rotation import quat_from_rotvec, quat_multiply, quat_normalize, quat_rotate
from ._elliptic import ellipj_m1, ellipk_m1, ellipkinc_m1
from ._helpers import broadcast_batch, check_times, safe_div, safe_sqrt, sign

# |L² − 2TB| below this many ulps of its two terms counts as exactly on the separatrix.
_SEPARATRIX_ULPS = 16.0

_BatchTimesLike = Float[ArrayLike, "*batch n"]


# ---------------------------------------------------------------------------------------
# torque-free axisymmetric body (docs/physics.md#torque-free-motion)
# ---------------------------------------------------------------------------------------


def _symmetric_core(A, C, omega0, ts, quat0):
    p0, q0, r0 = omega0[0], omega0[1], omega0[2]
    lam = (C - A) * r0 / A
    c, s = jnp.cos(lam * ts), jnp.sin(lam * ts)
    omega = jnp.stack([p0 * c - q0 * s, p0 * s + q0 * c, jnp.broadcast_to(r0, ts.shape)], -1)
    L_body0 = jnp.stack([A * p0, A * q0, C * r0])
    L_inertial = quat_rotate(quat0, L_body0)
    # Rot(L̂_inertial, |L| t / A) = exp([L_inertial t / A]×): no division by |L|.
    q_space = quat_from_rotvec(L_inertial[None, :] * (ts / A)[:, None])
    half = -0.5 * lam * ts
    zero = jnp.zeros_like(ts)
    q_body = jnp.stack([jnp.cos(half), zero, zero, jnp.sin(half)], -1)  # Rot(e_z, −λ t)
    quat = quat_multiply(quat_multiply(q_space, quat0[None, :]), q_body)
    return omega, quat


_symmetric_vec = jit(jnp.vectorize(_symmetric_core, signature="(),(),(3),(n),(4)->(n,3),(n,4)"))


def torque_free_symmetric(
    A: ScalarLike,
    C: ScalarLike,
    omega0: VectorLike,
    ts: _BatchTimesLike,
    quat0: QuaternionLike | None = None,
) -> tuple[Float[Array, "*batch n 3"], Float[Array, "*batch n 4"]]:
    """Torque-free motion of an axisymmetric body `A = B ≠ C` in closed form.

    See docs/physics.md#torque-free-motion (Euler–Poinsot). In the body, `r` is constant
    and `(p, q)` rotates at `λ = (C − A) r / A` (`p' = −λ q`, `q' = λ p`). The attitude is

        R(t) = Rot(L̂_inertial, |L| t / A) · R0 · Rot(e_z, −λ t),   L_inertial = R0 J ω0,

    (the symmetry axis precesses about the fixed `L` at `|L| / A`); one checks
    `Rᵀ Ṙ = [(1/A) Rot(e_z, λt) J ω0 − λ e_z]× = [ω(t)]×`. With `A = C` the body is
    spherical and ω is constant, with the same formula.

    **Arguments:**

    - `A`: the equatorial moment (about body x and y), `(*batch)`.
    - `C`: the axial moment (about body z), `(*batch)`.
    - `omega0`: body angular velocity `(p0, q0, r0)` at `t = 0`, `(*batch, 3)`.
    - `ts`: times `(*batch, n)` (commonly `(n,)`), measured from the instant where
        `ω = omega0`, `R = R0`; any sign and order.
    - `quat0`: attitude `R0` at `t = 0` as a `[w, x, y, z]` quaternion (body → inertial),
        `(*batch, 4)`; normalised here. Default: identity.

    **Returns:**

    `(omega, quat)`: body angular velocity `(*batch, n, 3)` and unit attitude quaternion
    `(*batch, n, 4)` at `ts`.
    """
    A = as_float_array(A, "A")
    C = as_float_array(C, "C")
    omega0 = check_trailing(omega0, (3,), "omega0")
    ts = check_times(ts, batched=True)
    if quat0 is None:
        quat0 = jnp.array([1.0, 0.0, 0.0, 0.0], dtype=omega0.dtype)
    quat0 = quat_normalize(check_trailing(quat0, (4,), "quat0"))
    A = eqx.error_if(A, ~(A > 0), "`A` must be positive.")
    C = eqx.error_if(C, ~(C > 0), "`C` must be positive.")
    args = broadcast_batch((A, 0), (C, 0), (omega0, 1), (ts, 1), (quat0, 1))
    return _symmetric_vec(*args)


# ---------------------------------------------------------------------------------------
# torque-free triaxial body: Jacobi elliptic functions (L&L §37;
# docs/physics.md#torque-free-motion)
# ---------------------------------------------------------------------------------------


def _sorted_frame(moments, omega0):
    """Moments in increasing order, ω0 in that order, the inverse order and the parity.

    Relabelling the axes by an odd permutation makes the frame left-handed, which reverses
    the sign of Euler's cross products: the relabelled ω then runs backwards in time.
    """
    order = jnp.argsort(moments)
    inverse = jnp.argsort(order)
    inversions = (
        (order[0] > order[1]).astype(jnp.int32)
        + (order[0] > order[2]).astype(jnp.int32)
        + (order[1] > order[2]).astype(jnp.int32)
    )
    time_sign = jnp.where(inversions % 2 == 1, -1.0, 1.0).astype(moments.dtype)
    return moments[order], omega0[order], inverse, time_sign


def _elliptic_parameters(I, w):
    """Branch masks and the constants of every branch, in the sorted frame I1 ≤ I2 ≤ I3."""
    I1, I2, I3 = I[0], I[1], I[2]
    w1, w2, w3 = w[0], w[1], w[2]
    # d_k = L² − 2 T I_k, written without cancellation (the k-th term vanishes).
    d1 = I2 * (I2 - I1) * w2**2 + I3 * (I3 - I1) * w3**2  # ≥ 0
    d3n = I1 * (I3 - I1) * w1**2 + I2 * (I3 - I2) * w2**2  # = −d3 = 2TI3 − L² ≥ 0
    d2_pos = I3 * (I3 - I2) * w3**2
    d2_neg = I1 * (I2 - I1) * w1**2
    # Within rounding of zero (XLA may contract d2 with an FMA in one fused kernel and not
    # in another), d2 is set to exactly 0: the separatrix. Outside, the sign is reliable.
    d2 = d2_pos - d2_neg  # sign picks the side
    d2 = jnp.where(
        jnp.abs(d2) <= _SEPARATRIX_ULPS * jnp.finfo(d2.dtype).eps * (d2_pos + d2_neg), 0.0, d2
    )
    spherical = I1 == I3
    sym12 = (I1 == I2) & ~spherical  # unique axis 3
    sym23 = (I2 == I3) & ~spherical  # unique axis 1
    nonzero = (w1 != 0).astype(jnp.int32) + (w2 != 0).astype(jnp.int32)
    nonzero = nonzero + (w3 != 0).astype(jnp.int32)
    constant = spherical | (nonzero <= 1)
    separatrix = d2 == 0
    case1 = d2 > 0  # L² > 2TB: ω circulates about the axis of largest moment
    I123 = I1 * I2 * I3
    # case 1 (L&L §37, eq. 37.10): ω1 = s a cn, ω2 = b sn, ω3 = s c dn (also the separatrix)
    a1 = safe_sqrt(safe_div(d3n, I1 * (I3 - I1)))
    b1 = safe_sqrt(safe_div(d3n, I2 * (I3 - I2)))
    c1 = safe_sqrt(safe_div(d1, I3 * (I3 - I1)))
    wp1 = safe_sqrt(safe_div((I3 - I2) * d1, I123))
    # m = (I2 − I1)(−d3) / ((I3 − I2) d1); its complement 1 − m from d2, without cancellation
    m1_1 = safe_div((I3 - I1) * d2, (I3 - I2) * d1)
    # case 2 (indices 1 ↔ 3): ω1 = s a dn, ω2 = b sn, ω3 = s c cn
    a2 = a1
    b2 = safe_sqrt(safe_div(d1, I2 * (I2 - I1)))
    c2 = c1
    wp2 = safe_sqrt(safe_div((I2 - I1) * d3n, I123))
    # m = (I3 − I2) d1 / ((I2 − I1)(−d3))
    m1_2 = safe_div(-(I3 - I1) * d2, (I2 - I1) * d3n)
    m1 = jnp.clip(jnp.where(case1, m1_1, m1_2), 0.0, 1.0)
    wp = jnp.where(case1, wp1, wp2)
    return dict(
        spherical=spherical,
        sym12=sym12,
        sym23=sym23,
        constant=constant,
        separatrix=separatrix,
        case1=case1,
        a1=a1,
        b1=b1,
        c1=c1,
        b2=b2,
        a2=a2,
        c2=c2,
        m1=m1,
        wp=wp,
        wp1=wp1,
        lam12=safe_div((I3 - I1) * w3, I1),
        lam23=safe_div((I1 - I2) * w1, I2),
    )


def _elliptic_core(moments, omega0, ts):
    I, w, inverse, time_sign = _sorted_frame(moments, omega0)
    t = time_sign * ts
    P = _elliptic_parameters(I, w)
    w1, w2, w3 = w[0], w[1], w[2]
    full = lambda x: jnp.broadcast_to(x, t.shape)  # noqa: E731

    # elliptic, both sides of the separatrix
    s1 = sign(w3)
    s2 = sign(w1)
    # phase: cn u0 = ω_cn / coefficient, sn u0 = ω2 / b (atan2 of both, scaled by ab > 0)
    phi1 = jnp.arctan2(w2 * P["a1"], s1 * w1 * P["b1"])
    phi2 = jnp.arctan2(w2 * P["c2"], s2 * w3 * P["b2"])
    phi0 = jnp.where(P["case1"], phi1, phi2)
    u0 = ellipkinc_m1(phi0, P["m1"])
    sn, cn, dn = ellipj_m1(P["wp"] * t + u0, full(P["m1"]))
    ell1 = jnp.stack([s1 * P["a1"] * cn, P["b1"] * sn, s1 * P["c1"] * dn], -1)
    ell2 = jnp.stack([s2 * P["a2"] * dn, P["b2"] * sn, s2 * P["c2"] * cn], -1)
    ell = jnp.where(P["case1"], ell1, ell2)

    # separatrix L² = 2TB: ω1 = s1' a sech u, ω2 = b tanh u, ω3 = s3' c sech u
    sa, sc = sign(w1), sign(w3)
    sinh_u0 = safe_div(w2 * P["a1"], P["b1"] * jnp.abs(w1))
    u_sep = sa * sc * P["wp1"] * t + jnp.arcsinh(sinh_u0)
    sech = 1.0 / jnp.cosh(u_sep)
    sep = jnp.stack([sa * P["a1"] * sech, P["b1"] * jnp.tanh(u_sep), sc * P["c1"] * sech], -1)

    # axisymmetric: (ω1, ω2) rotate about axis 3, or (ω2, ω3) about axis 1, at rate λ
    c12, s12 = jnp.cos(P["lam12"] * t), jnp.sin(P["lam12"] * t)
    sym12 = jnp.stack([w1 * c12 - w2 * s12, w1 * s12 + w2 * c12, full(w3)], -1)
    c23, s23 = jnp.cos(P["lam23"] * t), jnp.sin(P["lam23"] * t)
    sym23 = jnp.stack([full(w1), w2 * c23 - w3 * s23, w2 * s23 + w3 * c23], -1)

    const = jnp.broadcast_to(w, t.shape + (3,))
    out = jnp.where(P["separatrix"], sep, ell)
    out = jnp.where(P["sym23"], sym23, out)
    out = jnp.where(P["sym12"], sym12, out)
    out = jnp.where(P["constant"], const, out)
    return out[:, inverse]


def _elliptic_period_core(moments, omega0):
    I, w, _, _ = _sorted_frame(moments, omega0)
    P = _elliptic_parameters(I, w)
    inf = jnp.array(jnp.inf, dtype=moments.dtype)
    ell = jnp.where(P["wp"] > 0, safe_div(4.0 * ellipk_m1(P["m1"]), P["wp"]), inf)
    two_pi = 2.0 * math.pi
    sym12 = jnp.where(P["lam12"] != 0, safe_div(two_pi, jnp.abs(P["lam12"])), inf)
    sym23 = jnp.where(P["lam23"] != 0, safe_div(two_pi, jnp.abs(P["lam23"])), inf)
    zero = jnp.all(w == 0)
    out = jnp.where(P["separatrix"], inf, ell)
    out = jnp.where(P["sym23"], sym23, out)
    out = jnp.where(P["sym12"], sym12, out)
    return jnp.where(P["spherical"] | zero, inf, out)


_elliptic_vec = jit(jnp.vectorize(_elliptic_core, signature="(3),(3),(n)->(n,3)"))
_elliptic_period_vec = jit(jnp.vectorize(_elliptic_period_core, signature="(3),(3)->()"))


def _check_moments(moments: ArrayLike) -> Array:
    moments = check_trailing(moments, (3,), "moments")
    return eqx.error_if(moments, ~jnp.all(moments > 0), "`moments` must be positive.")


def torque_free_elliptic(
    moments: VectorLike, omega0: VectorLike, ts: _BatchTimesLike
) -> Float[Array, "*batch n 3"]:
    """Torque-free body angular velocity of a triaxial body (Jacobi elliptic functions).

    Landau & Lifshitz, *Mechanics* §37; docs/physics.md#torque-free-motion. With the
    moments sorted as `I1 < I2 < I3`, `2T = Σ I_k ω_k²`, `L² = Σ I_k² ω_k²` and
    `d_k = L² − 2T I_k`:

    - `L² > 2T I2` (`d2 > 0`, circulation about the axis of largest moment):
      `ω1 = s a cn u`, `ω2 = b sn u`, `ω3 = s c dn u`, with
      `a² = −d3 / (I1 (I3 − I1))`, `b² = −d3 / (I2 (I3 − I2))`, `c² = d1 / (I3 (I3 − I1))`,
      `u = ωp t + u0`, `ωp² = (I3 − I2) d1 / (I1 I2 I3)`,
      `m = (I2 − I1)(−d3) / ((I3 − I2) d1)`, `s = sign ω3(0)`.
    - `L² < 2T I2` (`d2 < 0`): indices 1 ↔ 3 exchanged, `ω1 = s a dn u`, `ω2 = b sn u`,
      `ω3 = s c cn u`, `s = sign ω1(0)`, with `a` as above, `b² = d1 / (I2 (I2 − I1))`,
      `c² = d1 / (I3 (I3 − I1))`, `ωp² = (I2 − I1)(−d3) / (I1 I2 I3)`,
      `m = (I3 − I2) d1 / ((I2 − I1)(−d3))`.
    - `L² = 2T I2` exactly (the separatrix, `m = 1`): the hyperbolic limit
      `ω1 = s1 a sech u`, `ω2 = b tanh u`, `ω3 = s3 c sech u`, `u = s1 s3 ωp t + u0`
      (heteroclinic: ω tends to the intermediate axis as `t → ±∞`).
    - Two equal moments: the closed form of `torque_free_symmetric`; three equal moments,
      or ω along a principal axis (including the unstable intermediate one) or zero:
      constant ω.

    The phase `u0` reproduces ω0 at `t = 0` for any signs of its components: `cn u0` and
    `sn u0` are read off ω0, their amplitude `φ0 = atan2(sn, cn)` and `u0 = F(φ0|m)` (the
    incomplete integral extended to every real φ0). The parameter `1 − m` is computed from
    `d2` directly, so the solution stays accurate close to the separatrix. Axes are sorted
    internally; an odd permutation of the axes reverses time in the sorted frame.
    Branches are selected by exact comparisons of the inputs (`I1 == I2`, `ω_k == 0`), and
    `d2` counts as zero within 16 ulps of its two terms `I3 (I3 − I2) ω3²`, `I1 (I2 − I1) ω1²`
    (rounding can give it either sign there; the problem itself is that ill-conditioned);
    nearby values go through the elliptic formulas, which are continuous there.

    **Arguments:**

    - `moments`: the principal moments about the body x, y, z axes, `(*batch, 3)`, positive,
        any order (e.g. `(2, 1, 3)`).
    - `omega0`: body angular velocity at `t = 0` in those axes, `(*batch, 3)`.
    - `ts`: times `(*batch, n)` (commonly `(n,)`), measured from the instant where
        `ω = omega0`; any sign and order.

    **Returns:**

    Body angular velocity `(*batch, n, 3)` in the axes of `moments`.
    """
    moments = _check_moments(moments)
    omega0 = check_trailing(omega0, (3,), "omega0")
    ts = check_times(ts, batched=True)
    return _elliptic_vec(*broadcast_batch((moments, 1), (omega0, 1), (ts, 1)))


def torque_free_elliptic_period(moments: VectorLike, omega0: VectorLike) -> Scalar:
    """Period of the torque-free body angular velocity ω(t) (of the polhode).

    `4 K(m) / ωp` for a triaxial body (both sides of the separatrix, notation of
    `torque_free_elliptic`: sn and cn have period 4K, dn 2K), `2π / |λ|` for an
    axisymmetric one (`λ = (C − A) r / A`). At a spin about the largest or smallest axis
    the value is the limit of the nearby polhodes' periods (the small-oscillation period)
    although ω is then constant. `inf` on the separatrix (including a spin about the
    intermediate axis), for a spherical body, for ω = 0, and for an axisymmetric body with
    `r = 0`: ω is then constant or not periodic.

    **Arguments:** `moments`: principal moments `(*batch, 3)`, any order; `omega0`: body
    angular velocity `(*batch, 3)` in those axes.

    **Returns:** the period, `(*batch)`.
    """
    moments = _check_moments(moments)
    omega0 = check_trailing(omega0, (3,), "omega0")
    return _elliptic_period_vec(*broadcast_batch((moments, 1), (omega0, 1)))
