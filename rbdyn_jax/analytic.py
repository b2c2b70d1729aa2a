"""Closed-form and quadrature reference solutions, used to check the simulator.

Nothing here integrates an ODE: every function is a closed form, a special function, or a
fixed quadrature, so it is independent of the diffrax machinery it is meant to check.

- Torque-free axisymmetric body, angular velocity and attitude in closed form
  (docs/physics.md#torque-free-motion): `torque_free_symmetric`.
- Torque-free triaxial body, Jacobi elliptic functions (docs/physics.md#torque-free-motion;
  Landau & Lifshitz, *Mechanics* §37) on both sides of the separatrix and on it:
  `torque_free_elliptic`, `torque_free_elliptic_period`, with the special functions
  `ellipj`, `ellipk`, `ellipkinc` implemented in JAX (descending Landen transformation and
  Carlson's `R_F`).
- Lagrange top under a non-stationary restoring moment `k = ε K(τ) sin ψ`
  (Zinkevich & Kozachenko (2008); docs/physics.md#restoring-moment): first approximation
  `lagrange_top_first_approximation` and a second approximation
  `lagrange_top_second_approximation`.
- Integrable gravity-gradient case `A = B = m C` (Shinibaev et al. (2013);
  docs/physics.md#the-integrable-case): the nutation half period by quadrature,
  `gg_nutation_half_period`, its quartic `gg_nutation_quartic`, and the first integrals
  `gg_integrable_case_integrals`.

The JAX functions are pure, jit-able and accept leading `*batch` axes; the nutation
quadrature is NumPy/SciPy (a reference evaluated once per initial condition).
"""

import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._checks import as_float_array, check_trailing
from ._custom_types import QuaternionLike, Scalar, ScalarLike, VectorLike
from ._program.xla import filter_jit, jit
from .rotation import quat_from_rotvec, quat_multiply, quat_normalize, quat_rotate

__all__ = [
    "ellipj",
    "ellipk",
    "ellipkinc",
    "gg_integrable_case_integrals",
    "gg_nutation_half_period",
    "gg_nutation_quartic",
    "lagrange_top_first_approximation",
    "lagrange_top_second_approximation",
    "torque_free_elliptic",
    "torque_free_elliptic_period",
    "torque_free_symmetric",
]

# Descending Landen steps in `ellipj`. The AGM of (1, √(1 − m)) converges to machine
# precision within 6 steps for m ≤ 1 − 1e-16 (b₀ ≥ 1e-8); once converged a further step is
# an exact halving, so a fixed count costs nothing in accuracy.
_LANDEN_STEPS = 10
# Duplication steps of Carlson's R_F. Each step shrinks the spread of the arguments by ~4
# (after a few steps that equalise extreme ratios such as R_F(0, 1e-16, 1)); 16 steps leave
# a spread < 1e-4, where the 5th-order series is exact to ~1e-24.
_CARLSON_STEPS = 16
# |L² − 2TB| below this many ulps of its two terms counts as exactly on the separatrix.
_SEPARATRIX_ULPS = 16.0
# Default Gauss–Legendre order of the restoring-moment quadratures: exact for polynomial K
# of degree ≤ 2·32 − 1 = 63 and converged to rounding for K analytic near [0, τ] with τ = O(1).
_GL_ORDER = 32

_Times = Float[Array, " n"]
_TimesLike = Float[ArrayLike, " n"]
_BatchTimesLike = Float[ArrayLike, "*batch n"]


# ---------------------------------------------------------------------------------------
# small helpers
# ---------------------------------------------------------------------------------------


def _safe_div(x: Array, y: Array) -> Array:
    """`x / y`, with 0 where `y == 0` (value and gradient finite in discarded branches)."""
    ok = y != 0
    return jnp.where(ok, x / jnp.where(ok, y, 1.0), 0.0)


def _safe_sqrt(x: Array) -> Array:
    """`√max(x, 0)` with a finite gradient at 0 (for discarded `where` branches)."""
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)


def _sign(x: Array) -> Array:
    """+1 for x ≥ 0, −1 otherwise (never 0: a sign to multiply a magnitude by)."""
    return jnp.where(x >= 0, 1.0, -1.0).astype(x.dtype)


def _common(*xs: ArrayLike, names: tuple[str, ...]) -> list[Array]:
    """Float arrays of one dtype broadcast to one shape (elementwise special functions)."""
    arrs = [as_float_array(x, n) for x, n in zip(xs, names)]
    dtype = arrs[0].dtype
    for a in arrs[1:]:
        dtype = jnp.promote_types(dtype, a.dtype)
    shape = jnp.broadcast_shapes(*(a.shape for a in arrs))
    return [jnp.broadcast_to(a.astype(dtype), shape) for a in arrs]


def _broadcast_batch(*pairs: tuple[Array, int]) -> list[Array]:
    """Broadcast the leading (batch) axes of arrays with the given numbers of core axes.

    Done explicitly so that `jnp.vectorize` sees equal batch ranks (no rank promotion).
    """
    batch = jnp.broadcast_shapes(*(x.shape[: x.ndim - k] for x, k in pairs))
    return [jnp.broadcast_to(x, batch + x.shape[x.ndim - k :]) for x, k in pairs]


def _check_times(ts: ArrayLike, name: str = "ts", batched: bool = False) -> Array:
    ts = as_float_array(ts, name)
    if batched and ts.ndim < 1:
        raise ValueError(f"`{name}` must have shape (*batch, n), got shape {tuple(ts.shape)}.")
    if not batched and ts.ndim != 1:
        raise ValueError(f"`{name}` must be a 1-D array of times, got shape {tuple(ts.shape)}.")
    return ts


# ---------------------------------------------------------------------------------------
# special functions (A&S 16.4, Carlson 1995)
# ---------------------------------------------------------------------------------------


def _carlson_rf(x: Array, y: Array, z: Array) -> Array:
    """Carlson's symmetric elliptic integral `R_F(x, y, z)` (duplication theorem)."""

    def step(_, xyz):
        x, y, z = xyz
        sx, sy, sz = jnp.sqrt(x), jnp.sqrt(y), jnp.sqrt(z)
        lam = sx * sy + sy * sz + sz * sx
        return 0.25 * (x + lam), 0.25 * (y + lam), 0.25 * (z + lam)

    x, y, z = jax.lax.fori_loop(0, _CARLSON_STEPS, step, (x, y, z))
    mu = (x + y + z) / 3.0
    dx, dy = 1.0 - x / mu, 1.0 - y / mu
    dz = -(dx + dy)
    e2 = dx * dy - dz * dz
    e3 = dx * dy * dz
    series = 1.0 - e2 / 10.0 + e3 / 14.0 + e2 * e2 / 24.0 - 3.0 * e2 * e3 / 44.0
    return series / jnp.sqrt(mu)


def _ellipk_m1(m1: Array) -> Array:
    """K from the complementary parameter `m1 = 1 − m` (accurate as m → 1; inf at m = 1)."""
    zero = m1 == 0
    k = _carlson_rf(jnp.zeros_like(m1), jnp.where(zero, 1.0, m1), jnp.ones_like(m1))
    return jnp.where(zero, jnp.inf, k)


def _ellipkinc_m1(phi: Array, m1: Array) -> Array:
    """F(φ|m) for any real φ, from `m1 = 1 − m` (no cancellation near m = 1)."""
    j = jnp.round(phi / jnp.pi)
    phr = phi - j * jnp.pi  # in [−π/2, π/2]
    s, c = jnp.sin(phr), jnp.cos(phr)
    c2 = c * c
    f = s * _carlson_rf(c2, c2 + m1 * s * s, jnp.ones_like(s))
    k = _ellipk_m1(m1)
    return f + jnp.where(j == 0, 0.0, 2.0 * j * jnp.where(j == 0, 0.0, k))


def _ellipj_m1(u: Array, m1: Array) -> tuple[Array, Array, Array]:
    """sn, cn, dn from `m1 = 1 − m` (accurate as m → 1); hyperbolic limit where `m1 == 0`."""
    one = m1 == 0
    m1_ = jnp.where(one, 0.5, m1)

    # Descending Landen transformation / AGM (A&S 16.4.2–16.4.4, as Cephes `ellpj`).
    def agm(ab, _):
        a, b = ab
        a_next = 0.5 * (a + b)
        return (a_next, jnp.sqrt(a * b)), 0.5 * (a - b) / a_next  # c_{i+1} / a_{i+1}

    (a, _), c_over_a = jax.lax.scan(agm, (jnp.ones_like(m1_), jnp.sqrt(m1_)), length=_LANDEN_STEPS)

    def back(phi, ratio):  # 2φ_{i−1} − φ_i = asin((c_i / a_i) sin φ_i)
        return 0.5 * (jnp.arcsin(ratio * jnp.sin(phi)) + phi), None

    phi, _ = jax.lax.scan(back, (2.0**_LANDEN_STEPS) * a * u, c_over_a, reverse=True)
    sn, cn = jnp.sin(phi), jnp.cos(phi)
    # dn = √(1 − m sn²) = √(cn² + m1 sn²): no cancellation, unlike Cephes' cn / cos(φ1 − φ0)
    # which loses digits where cn ≈ 0.
    dn = jnp.sqrt(cn * cn + m1_ * sn * sn)
    # m = 1: sn = tanh, cn = dn = sech (A&S 16.6); 1/cosh overflows gracefully to 0.
    sech = 1.0 / jnp.cosh(u)
    return (
        jnp.where(one, jnp.tanh(u), sn),
        jnp.where(one, sech, cn),
        jnp.where(one, sech, dn),
    )


_ellipj_jit = jit(lambda u, m: _ellipj_m1(u, 1.0 - m))
_ellipk_jit = jit(lambda m: _ellipk_m1(1.0 - m))
_ellipkinc_jit = jit(lambda phi, m: _ellipkinc_m1(phi, 1.0 - m))


def ellipj(u: ScalarLike, m: ScalarLike) -> tuple[Scalar, Scalar, Scalar]:
    """Jacobi elliptic functions `sn(u|m), cn(u|m), dn(u|m)`, as `scipy.special.ellipj`.

    Descending Landen transformation (A&S 16.4) with a fixed number of steps, so it is
    jit-able and vmappable; `m = 1` gives the hyperbolic limit (tanh, sech, sech).

    **Arguments:**

    - `u`: argument, any shape.
    - `m`: parameter `m = k²`, broadcastable with `u`; valid for `0 ≤ m ≤ 1` (NaN for
        `m > 1`; `m < 0` is not checked and gives values scipy would not).

    **Returns:**

    `(sn, cn, dn)`, each of the broadcast shape.
    """
    u, m = _common(u, m, names=("u", "m"))
    return _ellipj_jit(u, m)


def ellipk(m: ScalarLike) -> Scalar:
    """Complete elliptic integral of the first kind `K(m) = R_F(0, 1 − m, 1)`.

    As `scipy.special.ellipk` (parameter `m = k²`, `m < 1`; `K(1) = inf`).
    """
    m = as_float_array(m, "m")
    return _ellipk_jit(m)


def ellipkinc(phi: ScalarLike, m: ScalarLike) -> Scalar:
    """Incomplete elliptic integral of the first kind `F(φ|m)`, as `scipy.special.ellipkinc`.

    `F(φ|m) = sin φ · R_F(cos²φ, 1 − m sin²φ, 1)` on `|φ| ≤ π/2`, extended to every real φ
    by `F(φ + jπ) = F(φ) + 2jK(m)`.

    **Arguments:** `phi`: amplitude (radians); `m`: parameter, `0 ≤ m ≤ 1` (at `m = 1`
    only `|φ| < π/2` is finite), broadcastable with `phi`.

    **Returns:** `F(φ|m)` of the broadcast shape.
    """
    phi, m = _common(phi, m, names=("phi", "m"))
    return _ellipkinc_jit(phi, m)


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
    ts = _check_times(ts, batched=True)
    if quat0 is None:
        quat0 = jnp.array([1.0, 0.0, 0.0, 0.0], dtype=omega0.dtype)
    quat0 = quat_normalize(check_trailing(quat0, (4,), "quat0"))
    A = eqx.error_if(A, ~(A > 0), "`A` must be positive.")
    C = eqx.error_if(C, ~(C > 0), "`C` must be positive.")
    args = _broadcast_batch((A, 0), (C, 0), (omega0, 1), (ts, 1), (quat0, 1))
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
    a1 = _safe_sqrt(_safe_div(d3n, I1 * (I3 - I1)))
    b1 = _safe_sqrt(_safe_div(d3n, I2 * (I3 - I2)))
    c1 = _safe_sqrt(_safe_div(d1, I3 * (I3 - I1)))
    wp1 = _safe_sqrt(_safe_div((I3 - I2) * d1, I123))
    # m = (I2 − I1)(−d3) / ((I3 − I2) d1); its complement 1 − m from d2, without cancellation
    m1_1 = _safe_div((I3 - I1) * d2, (I3 - I2) * d1)
    # case 2 (indices 1 ↔ 3): ω1 = s a dn, ω2 = b sn, ω3 = s c cn
    a2 = a1
    b2 = _safe_sqrt(_safe_div(d1, I2 * (I2 - I1)))
    c2 = c1
    wp2 = _safe_sqrt(_safe_div((I2 - I1) * d3n, I123))
    # m = (I3 − I2) d1 / ((I2 − I1)(−d3))
    m1_2 = _safe_div(-(I3 - I1) * d2, (I2 - I1) * d3n)
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
        lam12=_safe_div((I3 - I1) * w3, I1),
        lam23=_safe_div((I1 - I2) * w1, I2),
    )


def _elliptic_core(moments, omega0, ts):
    I, w, inverse, time_sign = _sorted_frame(moments, omega0)
    t = time_sign * ts
    P = _elliptic_parameters(I, w)
    w1, w2, w3 = w[0], w[1], w[2]
    full = lambda x: jnp.broadcast_to(x, t.shape)  # noqa: E731

    # elliptic, both sides of the separatrix
    s1 = _sign(w3)
    s2 = _sign(w1)
    # phase: cn u0 = ω_cn / coefficient, sn u0 = ω2 / b (atan2 of both, scaled by ab > 0)
    phi1 = jnp.arctan2(w2 * P["a1"], s1 * w1 * P["b1"])
    phi2 = jnp.arctan2(w2 * P["c2"], s2 * w3 * P["b2"])
    phi0 = jnp.where(P["case1"], phi1, phi2)
    u0 = _ellipkinc_m1(phi0, P["m1"])
    sn, cn, dn = _ellipj_m1(P["wp"] * t + u0, full(P["m1"]))
    ell1 = jnp.stack([s1 * P["a1"] * cn, P["b1"] * sn, s1 * P["c1"] * dn], -1)
    ell2 = jnp.stack([s2 * P["a2"] * dn, P["b2"] * sn, s2 * P["c2"] * cn], -1)
    ell = jnp.where(P["case1"], ell1, ell2)

    # separatrix L² = 2TB: ω1 = s1' a sech u, ω2 = b tanh u, ω3 = s3' c sech u
    sa, sc = _sign(w1), _sign(w3)
    sinh_u0 = _safe_div(w2 * P["a1"], P["b1"] * jnp.abs(w1))
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
    ell = jnp.where(P["wp"] > 0, _safe_div(4.0 * _ellipk_m1(P["m1"]), P["wp"]), inf)
    two_pi = 2.0 * math.pi
    sym12 = jnp.where(P["lam12"] != 0, _safe_div(two_pi, jnp.abs(P["lam12"])), inf)
    sym23 = jnp.where(P["lam23"] != 0, _safe_div(two_pi, jnp.abs(P["lam23"])), inf)
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
    ts = _check_times(ts, batched=True)
    return _elliptic_vec(*_broadcast_batch((moments, 1), (omega0, 1), (ts, 1)))


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
    return _elliptic_period_vec(*_broadcast_batch((moments, 1), (omega0, 1)))


# ---------------------------------------------------------------------------------------
# Lagrange top under a non-stationary restoring moment (Zinkevich & Kozachenko (2008);
# docs/physics.md#restoring-moment)
# ---------------------------------------------------------------------------------------


def _check_quad_order(order: int) -> None:
    if not isinstance(order, int) or isinstance(order, bool) or order < 1:
        raise ValueError(f"`quad_order` must be a positive int, got {order!r}.")


def _gl_rule(order: int, dtype) -> tuple[Array, Array]:
    x, w = np.polynomial.legendre.leggauss(order)
    return jnp.asarray(x, dtype=dtype), jnp.asarray(w, dtype=dtype)


def _integral_0_to(f: Callable[[Array], Array], upper: Array, x: Array, w: Array) -> Array:
    """`∫₀^upper f(s) ds` for every element of `upper` (Gauss–Legendre, nodes on a new axis)."""
    expand = (1,) * upper.ndim
    s = 0.5 * upper[..., None] * (x.reshape(expand + x.shape) + 1.0)
    return jnp.sum(w.reshape(expand + w.shape) * f(s), axis=-1) * upper * 0.5


def _call_K(K: Callable, s: Array) -> Array:
    out = jnp.asarray(K(s))
    if out.shape != s.shape:
        out = jnp.broadcast_to(out, s.shape)
    return out.astype(s.dtype)


def _psi_first(psi0: Array, F1: Array) -> Array:
    """ψ with `tan(ψ/2) = tan(ψ0/2) exp(F1)`, on the 2π branch of ψ0.

    docs/physics.md#first-approximation."""
    j = jnp.round(psi0 / (2.0 * jnp.pi))
    psr = psi0 - 2.0 * jnp.pi * j  # in [−π, π]
    half = 0.5 * psr
    return 2.0 * jnp.arctan2(jnp.sin(half) * jnp.exp(F1), jnp.cos(half)) + 2.0 * jnp.pi * j


def _scalars(**kw) -> dict[str, Array]:
    out = {}
    for name, v in kw.items():
        a = as_float_array(v, name)
        if a.ndim != 0:
            raise ValueError(f"`{name}` must be a scalar, got shape {tuple(a.shape)}.")
        out[name] = a
    return out


def lagrange_top_first_approximation(
    ts: _TimesLike,
    *,
    A: float,
    C: float,
    r0: float,
    psi0: float,
    theta0: float,
    eps: float,
    K: Callable[[Array], Array],
    M3: float = 0.0,
    quad_order: int = _GL_ORDER,
) -> tuple[_Times, _Times, _Times]:
    """First approximation of a Lagrange top under `k(τ, ψ) = ε K(τ) sin ψ`.

    Zinkevich & Kozachenko (2008), the averaged system in the first approximation
    (docs/physics.md#first-approximation): with the full equations (their eq. (1))
    `A p' + (C − A) q r = k sinθ cosφ`, `A q' + (A − C) p r = −k sinθ sinφ`,
    `C r' = M3` (perturbing `M1 = M2 = 0`; constant body-fixed ones average out at this
    order) and slow time `τ = ε t`,

        θ = θ0,   r = r0 + M3 t / C,
        tan(ψ/2) = tan(ψ0/2) · exp(F1(τ)),   F1(τ) = (C r0)⁻¹ ∫₀^τ K(s) ds,

    i.e. the averaged gyroscopic precession `ψ' = k / (C r0)` (for the heavy top, `k = mgl`,
    the slow precession `mgl / (C r)`). ψ stays on the 2π branch of `psi0`. Valid for
    `√(p² + q²) ≪ r`, `C r² ≫ k`, `|M3| ≪ k`, over `t = O(1/ε)`, with errors `O(ε)` (the
    nutation, of amplitude `~ A k / (C r0)²`, is averaged out).

    `F1` is computed by Gauss–Legendre quadrature of order `quad_order` on `[0, τ]`,
    exact for polynomial `K` of degree ≤ `2 quad_order − 1` and accurate to rounding for
    `K` analytic in a neighbourhood of `[0, τ]` with `τ = O(1)`.

    **Arguments:**

    - `ts`: times `(n,)`, `t = 0` at the initial condition.
    - `A`, `C`: equatorial and axial moments of inertia about the fixed point (`A` is
        unused at this order; it is taken for symmetry with the second approximation).
    - `r0`: initial axial spin `r(0)` (non-zero).
    - `psi0`, `theta0`: initial precession and nutation angles (ZXZ,
        docs/physics.md#euler-angles).
    - `eps`: the small parameter ε of `τ = ε t` and `k = ε K(τ) sin ψ`.
    - `K`: `K(τ)`, a JAX-traceable function called with an array of slow times and acting
        elementwise. It is a static argument of an internal `jit`: pass the same function
        object to reuse the compilation.
    - `M3`: constant axial perturbing moment (physical units, `M3 = ε² M3*` of Zinkevich &
        Kozachenko (2008), eq. (3)).
    - `quad_order`: Gauss–Legendre order of the quadrature.

    **Returns:**

    `(psi, theta, r)`, each of shape `(n,)`.
    """
    ts = _check_times(ts)
    s = _scalars(A=A, C=C, r0=r0, psi0=psi0, theta0=theta0, eps=eps, M3=M3)
    _check_quad_order(quad_order)
    return _first_impl(
        ts, s["C"], s["r0"], s["psi0"], s["theta0"], s["eps"], s["M3"], K, quad_order
    )


@filter_jit
def _first_impl(ts, C, r0, psi0, theta0, eps, M3, K, quad_order):
    x, w = _gl_rule(quad_order, ts.dtype)
    tau = eps * ts
    F1 = _integral_0_to(lambda u: _call_K(K, u), tau, x, w) / (C * r0)
    psi = _psi_first(psi0, F1)
    theta = jnp.full_like(ts, theta0)
    r = r0 + M3 * ts / C
    return psi, theta, r


def lagrange_top_second_approximation(
    ts: _TimesLike,
    *,
    A: float,
    C: float,
    r0: float,
    psi0: float,
    theta0: float,
    eps: float,
    K: Callable[[Array], Array],
    M3: float = 0.0,
    phi0: float = 0.0,
    p0: float | None = None,
    q0: float | None = None,
    quad_order: int = _GL_ORDER,
) -> tuple[_Times, _Times, _Times]:
    """Second approximation of the Lagrange top of `lagrange_top_first_approximation`.

    docs/physics.md#second-approximation: the formulas of Zinkevich & Kozachenko (2008)
    that follow their eq. (5), re-derived and corrected (the printed forms fail the initial
    conditions at O(ε) and have sign and factor slips; see below). Errors `O(ε²)` over
    `t = O(1/ε)`.

    Mean motion (guiding centre: `L = A e × ė + C r e`, `dL/dt = N`, solved for ė to
    second order; it reproduces the paper's `g(τ)`):

        dψ̄/dτ = K sinψ̄ / (C r0) + ε A cosθ0 K² sin²ψ̄ / (C r0)³ − K sinψ̄ M3 τ / (ε C² r0²),
        θ̄ = θ̄0 + A sinθ̄0 (k(τ) − k(0)) / (C r0)²,   k = ε K(τ) sin ψ̄,

    the first line solved as `ψ̄ = ψ1 + sinψ1(τ) ∫₀^τ g(s) / sinψ1(s) ds` (`ψ1`: the first
    approximation from `ψ̄0`, `g` the two correction terms; the paper's `exp(∓F)` factors
    are `sinψ1(0) / sinψ1(τ)` in closed form). The paper's two θ integrals
    `∫ ∂K/∂τ sinψ1` and `∫ K² sin2ψ1` combine, with the correct factor `ε/2` on the second
    (printed `1/4`), into the closed form above.

    Fast nutation (the paper's S1, S2, with S1's sign corrected):

        ψ = ψ̄ − (A / (C r0 sinθ0)) e^{F/2} [â0 cos χ + b̂0 sin χ],
        θ = θ̄ + (A / (C r0)) e^{F/2} [â0 sin χ − b̂0 cos χ],
        χ = α − G = φ0 + C r0 t / A + M3 t² / (2A) − 2 cosθ0 (ψ1 − ψ̄0),
        e^{F} = sinψ̄0 / sinψ1(τ),
        â0 = p0 − (k0 / (C r0)) sinθ0 sinφ0,   b̂0 = −q0 + (k0 / (C r0)) sinθ0 cosφ0,

    (`ε a`, `ε b` of the paper at `t = 0`, `k0 = ε K(0) sin ψ0`), and the mean initial values
    `ψ̄0 = ψ0 − S1(0)`, `θ̄0 = θ0 − S2(0)`, so that `ψ(0) = ψ0`, `θ(0) = θ0` exactly.
    Perturbing moments `M1 = M2 = 0`.

    **Arguments:** as `lagrange_top_first_approximation`, plus the initial proper-rotation
    angle `phi0` and body rates `p0`, `q0` (default: the steady-precession values
    `p0 = ψ'0 sinθ0 sinφ0`, `q0 = ψ'0 sinθ0 cosφ0`, `ψ'0 = k0 / (C r0)`, for which the
    nutation vanishes to this order). `A` is used here.

    **Returns:**

    `(psi, theta, r)`, each of shape `(n,)`; `r = r0 + M3 t / C` (exact).
    """
    ts = _check_times(ts)
    s = _scalars(A=A, C=C, r0=r0, psi0=psi0, theta0=theta0, eps=eps, M3=M3, phi0=phi0)
    p0 = None if p0 is None else _scalars(p0=p0)["p0"]
    q0 = None if q0 is None else _scalars(q0=q0)["q0"]
    _check_quad_order(quad_order)
    return _second_impl(
        ts,
        s["A"],
        s["C"],
        s["r0"],
        s["psi0"],
        s["theta0"],
        s["eps"],
        s["M3"],
        s["phi0"],
        p0,
        q0,
        K,
        quad_order,
    )


@filter_jit
def _second_impl(ts, A_, C_, r0_, ps0, th0, eps_, M3_, ph0, p0, q0, K, quad_order):
    x, w = _gl_rule(quad_order, ts.dtype)
    Kf = lambda u: _call_K(K, u)  # noqa: E731
    Cr = C_ * r0_
    zero = jnp.zeros((), dtype=ts.dtype)

    k0 = eps_ * Kf(zero) * jnp.sin(ps0)
    rate0 = k0 / Cr
    p0_ = rate0 * jnp.sin(th0) * jnp.sin(ph0) if p0 is None else p0
    q0_ = rate0 * jnp.sin(th0) * jnp.cos(ph0) if q0 is None else q0
    a0 = p0_ - rate0 * jnp.sin(th0) * jnp.sin(ph0)
    b0 = -q0_ + rate0 * jnp.sin(th0) * jnp.cos(ph0)
    amp = A_ / Cr
    S1_0 = -amp / jnp.sin(th0) * (a0 * jnp.cos(ph0) + b0 * jnp.sin(ph0))
    S2_0 = amp * (a0 * jnp.sin(ph0) - b0 * jnp.cos(ph0))
    psib0 = ps0 - S1_0
    thb0 = th0 - S2_0

    def psi1(tau):
        return _psi_first(psib0, _integral_0_to(Kf, tau, x, w) / Cr)

    def g_over_sin(tau):  # g(τ) / sinψ1(τ), the integrand of the mean-ψ correction
        Kt = Kf(tau)
        return eps_ * A_ * jnp.cos(th0) * Kt**2 * jnp.sin(psi1(tau)) / Cr**3 - Kt * M3_ * tau / (
            eps_ * C_ * Cr * r0_
        )

    tau = eps_ * ts
    ps1 = psi1(tau)
    sin1 = jnp.sin(ps1)
    psibar = ps1 + sin1 * _integral_0_to(g_over_sin, tau, x, w)
    kbar = eps_ * Kf(tau) * jnp.sin(ps1)
    thbar = thb0 + A_ * jnp.sin(thb0) * (kbar - eps_ * Kf(zero) * jnp.sin(psib0)) / Cr**2

    sinb0 = jnp.sin(psib0)
    ratio = _safe_div(sinb0, sin1)
    half_F = jnp.where(sinb0 == 0, 1.0, jnp.sqrt(jnp.abs(ratio)))  # e^{F/2}
    chi = ph0 + Cr * ts / A_ + M3_ * ts**2 / (2.0 * A_) - 2.0 * jnp.cos(th0) * (ps1 - psib0)
    S1 = -amp / jnp.sin(th0) * half_F * (a0 * jnp.cos(chi) + b0 * jnp.sin(chi))
    S2 = amp * half_F * (a0 * jnp.sin(chi) - b0 * jnp.cos(chi))
    r = r0_ + M3_ * ts / C_
    return psibar + S1, thbar + S2, r


# ---------------------------------------------------------------------------------------
# gravity gradient, integrable case A = B = m C (Shinibaev et al. (2013);
# docs/physics.md#the-integrable-case)
# ---------------------------------------------------------------------------------------


def gg_integrable_case_integrals(
    A: ScalarLike, C: ScalarLike, eps: ScalarLike, omega: VectorLike, gamma: VectorLike
) -> tuple[Scalar, Scalar, Scalar, Scalar]:
    """First integrals of the integrable gravity-gradient case `A = B = m C`.

    Shinibaev et al. (2013), eqs. (7), (8), (10), (13), collected as (14)
    (docs/physics.md#the-integrable-case), `n = (1 − m)/m = (C − A)/A`:
    `C1 = p² + q² + ε n γ''²`, `C2 = γ p + γ' q + r (n + 1) γ''`, `r`, `|γ|²`.

    **Arguments:** `A` (= B), `C`, `eps` (ε = 3μ/R³), `(*batch)`; body angular velocity
    `omega = (p, q, r)` and body components `gamma = (γ, γ', γ'')` of the direction to the
    attracting centre, `(*batch, 3)`.

    **Returns:** `(C1, C2, r, |γ|²)`, each `(*batch)`.
    """
    A = as_float_array(A, "A")
    C = as_float_array(C, "C")
    eps = as_float_array(eps, "eps")
    omega = check_trailing(omega, (3,), "omega")
    gamma = check_trailing(gamma, (3,), "gamma")
    p, q, r = jnp.moveaxis(omega, -1, 0)
    g1, g2, g3 = jnp.moveaxis(gamma, -1, 0)
    n = (C - A) / A
    C1 = p * p + q * q + eps * n * g3 * g3
    C2 = g1 * p + g2 * q + r * (n + 1.0) * g3
    return C1, C2, r, g1 * g1 + g2 * g2 + g3 * g3


def gg_nutation_quartic(
    A: float, C: float, eps: float, omega0: ArrayLike, gamma0: ArrayLike
) -> np.ndarray:
    """Coefficients of the quartic `Q(u) = (du/dt)²`, `u = γ''`, of the nutation quadrature.

    Shinibaev et al. (2013), eq. (19); docs/physics.md#nutation-quadrature.
    From `r = r0`, `p² + q² = C1 − ε n u²`, `γ p + γ' q = C2 − r0 (n + 1) u`,
    `γ² + γ'² = 1 − u²`, Poisson `u' = q γ − p γ'` and the identity
    `(pγ + qγ')² + (qγ − pγ')² = (p² + q²)(γ² + γ'²)`:

        Q(u) = (C1 − ε n u²)(1 − u²) − (C2 − r0 (n + 1) u)²
             = a0 u⁴ + a2 u² + a3 u + a4,
        a0 = ε n,  a2 = −(ε n + C1 + r0² (n + 1)²),  a3 = 2 C2 r0 (n + 1),  a4 = C1 − C2²,

    exactly the coefficients of Shinibaev et al. (2013), eq. (19).

    **Arguments:** moments `A` (= B) and `C`, `eps` = ε, initial `omega0 = (p0, q0, r0)` and
    unit `gamma0 = (γ0, γ'0, γ''0)` (shape `(3,)` each).

    **Returns:** `[a0, 0, a2, a3, a4]` (highest power first, as `np.polyval`/`np.roots`).
    """
    A, C, eps, omega0, gamma0 = _gg_inputs(A, C, eps, omega0, gamma0)
    p0, q0, r0 = omega0
    g1, g2, g3 = gamma0
    n = (C - A) / A
    C1 = p0 * p0 + q0 * q0 + eps * n * g3 * g3
    C2 = g1 * p0 + g2 * q0 + r0 * (n + 1.0) * g3
    return np.array(
        [
            eps * n,
            0.0,
            -(eps * n + C1 + r0 * r0 * (n + 1.0) ** 2),
            2.0 * C2 * r0 * (n + 1.0),
            C1 - C2 * C2,
        ]
    )


def _gg_inputs(A, C, eps, omega0, gamma0):
    A, C, eps = float(A), float(C), float(eps)
    if not A > 0:
        raise ValueError(f"`A` must be positive, got {A}.")
    if not C > 0:
        raise ValueError(f"`C` must be positive, got {C}.")
    omega0 = np.asarray(omega0, dtype=float)
    gamma0 = np.asarray(gamma0, dtype=float)
    if omega0.shape != (3,):
        raise ValueError(f"`omega0` must have shape (3,), got {omega0.shape}.")
    if gamma0.shape != (3,):
        raise ValueError(f"`gamma0` must have shape (3,), got {gamma0.shape}.")
    if not np.all(np.isfinite(omega0)) or not np.all(np.isfinite(gamma0)):
        raise ValueError("`omega0` and `gamma0` must be finite.")
    if abs(np.dot(gamma0, gamma0) - 1.0) > 1e-9:
        raise ValueError(f"`gamma0` must be a unit vector, got |gamma0|² = {gamma0 @ gamma0}.")
    return A, C, eps, omega0, gamma0


def gg_nutation_half_period(
    A: float, C: float, eps: float, omega0: ArrayLike, gamma0: ArrayLike
) -> float:
    """Half period of the nutation γ''(t) in the integrable gravity-gradient case.

    Shinibaev et al. (2013), eq. (19) (docs/physics.md#nutation-quadrature): the time
    between successive turning points of `u = γ''` is `∫ du / √Q(u)` between the two
    adjacent real roots `u1 < u2` of the quartic `gg_nutation_quartic` that bracket `γ''0`
    (Q > 0 between them, inside [−1, 1]).
    Writing `Q = (u − u1)(u2 − u) g(u)` (g: Q divided by the two roots' factors, positive
    on [u1, u2]) and `u = mid + half · sin φ` removes both inverse-square-root endpoint
    singularities:

        T/2 = ∫_{−π/2}^{π/2} dφ / √g(mid + half sin φ),

    a smooth integrand, done by `scipy.integrate.quad` (relative tolerance 1e-13). The
    roots come from `np.roots`, polished by Newton steps. If `γ''0` is a double root
    (`u` constant: steady motion) the value is the limit of nearby motions: the
    small-oscillation value `π / √g(u*)` (`g = −Q''/2`) if the steady motion is stable,
    `inf` if it is unstable (nearby motions are asymptotic to it).

    **Arguments:** moments `A` (= B) and `C` (> 0), `eps` = ε = 3μ/R³, initial body rates
    `omega0 = (p0, q0, r0)` and unit `gamma0 = (γ0, γ'0, γ''0)`, shape `(3,)` each.

    **Returns:** the half period (a float).

    **Raises:** `ValueError` for bad arguments, or when no pair of real roots of the
    quartic brackets `γ''0` (which the equations of motion exclude).
    """
    coeffs = gg_nutation_quartic(A, C, eps, omega0, gamma0)
    u0 = float(np.asarray(gamma0, dtype=float)[2])
    scale = float(np.max(np.abs(coeffs)))
    if scale == 0:
        raise ValueError("the nutation quartic vanishes identically (`omega0` = 0, `eps` n = 0).")
    # Trim vanishing leading coefficients (ε n = 0: a quadratic, the torque-free body).
    poly = np.trim_zeros(np.where(np.abs(coeffs) <= 1e-300, 0.0, coeffs), "f")
    dpoly = np.polyder(poly)
    d2poly = np.polyder(dpoly)
    if abs(np.polyval(poly, u0)) <= 1e-12 * scale and abs(np.polyval(dpoly, u0)) <= 1e-8 * scale:
        # u0 is a double root: du/dt = d²u/dt² = 0, u stays constant (steady motion). The
        # limit of nearby motions: π/√g with g = −Q''/2 if stable, inf if unstable.
        curv = float(np.polyval(d2poly, u0))
        return float(np.pi / np.sqrt(-0.5 * curv)) if curv < 0 else math.inf
    roots = np.roots(poly)
    real = []
    for z in roots:
        if abs(z.imag) <= 1e-7 * max(1.0, abs(z)):
            x = z.real
            for _ in range(4):  # Newton polish, kept only while it helps
                d = np.polyval(dpoly, x)
                if d == 0:
                    break
                x_new = x - np.polyval(poly, x) / d
                if abs(np.polyval(poly, x_new)) >= abs(np.polyval(poly, x)):
                    break
                x = x_new
            real.append(x)
    real = sorted(real)
    tol = 1e-9 * max(1.0, abs(u0))
    interval = None
    for lo, hi in zip(real[:-1], real[1:]):
        positive = np.polyval(poly, 0.5 * (lo + hi)) > 0
        if lo - tol <= u0 <= hi + tol and hi > lo and positive:
            interval = (lo, hi)
            break
    if interval is None:
        raise ValueError(
            "no pair of real roots of the nutation quartic brackets `gamma0[2]`: "
            f"roots {np.sort_complex(roots)}, gamma0[2] = {u0}."
        )
    lo, hi = interval
    quotient, _ = np.polydiv(poly, np.poly([lo, hi]))
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)

    def integrand(phi):
        return 1.0 / np.sqrt(-np.polyval(quotient, mid + half * np.sin(phi)))

    import scipy.integrate  # here, not at the top: it would slow `import rbdyn_jax`

    value, _ = scipy.integrate.quad(
        integrand, -0.5 * np.pi, 0.5 * np.pi, epsabs=0.0, epsrel=1e-13, limit=200
    )
    return float(value)
