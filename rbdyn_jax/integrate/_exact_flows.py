"""The exact flows of the split kinetic energy, in the inertia's principal frame: the frame
(`PrincipalFrame`), the state in it with the rounding errors of its compensated sums
(`Principal`), the flow of a principal axis' term (`_axis_flow`) and the rotation of the
Casimir's (`_casimir_rotation`) as increments of L and of the attitude, the Hamilton product
on components, and the compensated sum that adds an increment (`_two_sum`).
"""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .. import rotation
from ..inertia import principal_axes


class PrincipalFrame(eqx.Module):
    """The inertia's principal frame: `moments` (ascending), `axes` (columns: the
    principal axes in body components, right-handed) and `quat`, the attitude of the
    principal frame in the body (`R(quat) = axes`). A body attitude q becomes the principal
    frame's `q ⊗ quat`, and ω the components `axesᵀ ω`."""

    moments: Float[Array, "3"]
    axes: Float[Array, "3 3"]
    quat: Float[Array, "4"]

    @classmethod
    def of(cls, inertia) -> "PrincipalFrame":
        moments, axes = principal_axes(inertia)
        return cls(moments, axes, rotation.dcm_to_quat(axes))


def _q_times(q, p):
    """Hamilton product `q ⊗ p` on components (lists of four arrays)."""
    w, x, y, z = q
    a, b, c, d = p
    return [
        w * a - x * b - y * c - z * d,
        w * b + x * a + y * d - z * c,
        w * c - x * d + y * a + z * b,
        w * d + x * c - y * b + z * a,
    ]


def _two_sum(hi, lo, d):
    """`hi + lo + d` as a new pair `(hi, lo)`: the rounding error of the sum kept in `lo`
    (compensated summation by Knuth's TwoSum, whose last step recovers the rounding of
    `hi + b` exactly; `b = d + lo` is itself rounded, at the size of the increment's ulp).
    XLA keeps floating-point additions in the order written (no reassociation)."""
    b = d + lo
    s = hi + b
    bb = s - hi
    return s, (hi - (s - bb)) + (b - bb)


def _cos_minus_one(s, c):
    """`cos x − 1` from `s = sin x`, `c = cos x`, to the rounding of its size for every x:
    `−s² / (1 + c)` where `c ≥ 0` (no cancellation against 1 for small x), `c − 1` where
    `c < 0` (there `1 + c` would cancel near x = π). The unselected branch's denominator is
    kept away from 0, so that derivatives through `jnp.where` stay finite."""
    right = c >= 0
    return jnp.where(right, -s * s / jnp.where(right, 1.0 + c, 1.0), c - 1.0)


def _axis_flow(i: int, L, q, rate):
    """The exact flow of `½ d_i L_i²` for a time h, with `rate = d_i h`: L and the
    attitude turn about the principal axis i by `θ = rate L_i` (L_i kept), `L ← Rot(e_i,
    −θ) L` in body components, `q ← q ⊗ (cos θ/2, sin θ/2 e_i)`. Returns the increments of
    L (`{j: ΔL_j}`) and of q, from `cos θ − 1 = −2 sin²(θ/2)` and `cos(θ/2) − 1`
    (`_cos_minus_one`): small numbers for a small angle, whose rounding is small against L
    and q, and accurate for any angle."""
    j, k = (i + 1) % 3, (i + 2) % 3
    half = 0.5 * rate * L[i]
    sh, ch = jnp.sin(half), jnp.cos(half)
    s, cm = 2.0 * sh * ch, -2.0 * sh * sh  # sin θ, cos θ − 1
    dL = {j: cm * L[j] + s * L[k], k: cm * L[k] - s * L[j]}
    chm = _cos_minus_one(sh, ch)  # cos(θ/2) − 1
    w, v = q[0], q[1:]
    dv = [None] * 3
    dw = chm * w - sh * v[i]
    dv[i], dv[j], dv[k] = chm * v[i] + sh * w, chm * v[j] + sh * v[k], chm * v[k] - sh * v[j]
    return dL, [dw, *dv]


def _casimir_rotation(L, rate, increment):
    """The rotation of the exact flow of `|L|²/(2 I_a)` for a time h, with `rate = h /
    I_a`: L kept in the body, the attitude turned about it by `φ = rate |L|`, `q ← q ⊗
    (cos φ/2, sin φ/2 L/|L|)` (the identity at L = 0, with finite derivatives there).
    Returns that quaternion, or with `increment` its difference from the identity, `(cos
    φ/2 − 1, …)`, as `_axis_flow`."""
    n2 = L[0] * L[0] + L[1] * L[1] + L[2] * L[2]
    nonzero = n2 > 0
    n = jnp.sqrt(jnp.where(nonzero, n2, 1.0))
    half = 0.5 * rate * n
    sn, c = jnp.sin(half), jnp.cos(half)
    scale = jnp.where(nonzero, sn / n, 0.5 * rate)  # sin(φ/2)/|L|
    if increment:
        w = jnp.where(nonzero, _cos_minus_one(sn, c), 0.0)  # cos(φ/2) − 1
    else:
        w = jnp.where(nonzero, c, 1.0)
    return [w, scale * L[0], scale * L[1], scale * L[2]]


class Principal(eqx.Module):
    """The state in the principal frame: the body angular momentum `L` (principal
    components) and the attitude `quat` of the principal frame, each with the rounding
    error of its compensated sums (`L_lo`, `quat_lo`: the state is `L + L_lo`, …).

    Every flow adds a small increment to the state; summed plainly, each addition's
    rounding (half an ulp of the component) would make |L| and |q| random-walk, to about
    2e-12 after 5·10⁷ steps. Compensated, what remains is the rounding of the increments,
    smaller by their size (docs/performance.md#long-horizons)."""

    L: Float[Array, "3"]
    quat: Float[Array, "4"]
    L_lo: Float[Array, "3"]
    quat_lo: Float[Array, "4"]
