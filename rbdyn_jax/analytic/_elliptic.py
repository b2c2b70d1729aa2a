"""Jacobi elliptic functions and elliptic integrals of the first kind in JAX (A&S 16.4,
Carlson 1995): the public `ellipj`, `ellipk`, `ellipkinc`, and their forms in the
complementary parameter `1 − m` (`ellipj_m1`, `ellipk_m1`, `ellipkinc_m1`) that the
torque-free solution evaluates near the separatrix."""

import jax
import jax.numpy as jnp
from jaxtyping import Array

from .._checks import as_float_array
from .._custom_types import Scalar, ScalarLike
from .._program.xla import jit
from ._helpers import common

# Descending Landen steps in `ellipj`. The AGM of (1, √(1 − m)) converges to machine
# precision within 6 steps for m ≤ 1 − 1e-16 (b₀ ≥ 1e-8); once converged a further step is
# an exact halving, so a fixed count costs nothing in accuracy.
_LANDEN_STEPS = 10
# Duplication steps of Carlson's R_F. Each step shrinks the spread of the arguments by ~4
# (after a few steps that equalise extreme ratios such as R_F(0, 1e-16, 1)); 16 steps leave
# a spread < 1e-4, where the 5th-order series is exact to ~1e-24.
_CARLSON_STEPS = 16


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


def ellipk_m1(m1: Array) -> Array:
    """K from the complementary parameter `m1 = 1 − m` (accurate as m → 1; inf at m = 1)."""
    zero = m1 == 0
    k = _carlson_rf(jnp.zeros_like(m1), jnp.where(zero, 1.0, m1), jnp.ones_like(m1))
    return jnp.where(zero, jnp.inf, k)


def ellipkinc_m1(phi: Array, m1: Array) -> Array:
    """F(φ|m) for any real φ, from `m1 = 1 − m` (no cancellation near m = 1)."""
    j = jnp.round(phi / jnp.pi)
    phr = phi - j * jnp.pi  # in [−π/2, π/2]
    s, c = jnp.sin(phr), jnp.cos(phr)
    c2 = c * c
    f = s * _carlson_rf(c2, c2 + m1 * s * s, jnp.ones_like(s))
    k = ellipk_m1(m1)
    return f + jnp.where(j == 0, 0.0, 2.0 * j * jnp.where(j == 0, 0.0, k))


def ellipj_m1(u: Array, m1: Array) -> tuple[Array, Array, Array]:
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


_ellipj_jit = jit(lambda u, m: ellipj_m1(u, 1.0 - m))
_ellipk_jit = jit(lambda m: ellipk_m1(1.0 - m))
_ellipkinc_jit = jit(lambda phi, m: ellipkinc_m1(phi, 1.0 - m))


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
    u, m = common(u, m, names=("u", "m"))
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
    phi, m = common(phi, m, names=("phi", "m"))
    return _ellipkinc_jit(phi, m)
