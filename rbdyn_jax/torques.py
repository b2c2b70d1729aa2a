"""Torque models: `eqx.Module`s whose parameters are pytree leaves.

See the physics guide: docs/physics.md#absolute-motion, docs/physics.md#relative-motion,
docs/physics.md#restoring-moment and docs/physics.md#gravity-gradient.

A torque is called as `torque(kin, inertia)` with the `Kinematics` record of `state.py`
(time, body rates, attitudes, the parent frame's rates) and the 3×3 inertia tensor, and
returns the moment about the fixed point / centre of mass in **body components**. The same
torque works in absolute and relative models. Torques compose with `+` into a `SumTorque`.

Conservative torques are `AbstractConservativeTorque`s: they also give their potential
energy (`potential(kin, inertia)`), used by `invariants.energy`. A sum has one when each of
its terms has.
"""

import abc
from collections.abc import Callable

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from . import rotation
from ._checks import as_float_array, check_scalar, check_trailing
from ._vector import cross, matvec  # written out: fast on CPU (`_vector` says why)
from .dynamics import transport_moment
from .state import Kinematics

_E_Z = (0.0, 0.0, 1.0)


def _e_z(like: Array) -> Array:
    return jnp.asarray(_E_Z, dtype=like.dtype)


def _need(kin: Kinematics, field: str, torque: str):
    value = getattr(kin, field)
    if value is None:
        raise ValueError(
            f"`{torque}` needs the attitude `{field}`, which this state form does not carry "
            "(the Poisson form knows only γ); use a quaternion or Euler-angle model."
        )
    return value


class AbstractTorque(eqx.Module):
    """A moment acting on the body, in body components (see the module docstring)."""

    @abc.abstractmethod
    def __call__(self, kin: Kinematics, inertia: Float[Array, "3 3"]) -> Float[Array, "3"]:
        """The moment in body components at the instant described by `kin`."""

    def __add__(self, other: "AbstractTorque") -> "SumTorque":
        if not isinstance(other, AbstractTorque):
            return NotImplemented
        return SumTorque(self, other)


class AbstractConservativeTorque(AbstractTorque):
    """A torque that derives from a potential energy `V`: the moment is `−∂V/∂θ` for a
    rotation θ of the body, so `T + V` is conserved in an absolute model
    (`invariants.energy`)."""

    @abc.abstractmethod
    def potential(self, kin: Kinematics, inertia: Float[Array, "3 3"]) -> Float[Array, ""]:
        """Potential energy whose negative gradient is this torque."""


class SumTorque(AbstractTorque):
    """The sum of several torques (a container, like diffrax's `MultiTerm`). Its
    `potential` is the sum of its terms' when each is an `AbstractConservativeTorque`; a
    `ValueError` naming the first term that is not, otherwise."""

    torques: tuple[AbstractTorque, ...]

    def __init__(self, *torques: AbstractTorque):
        flat = []
        for t in torques:
            if not isinstance(t, AbstractTorque):
                raise ValueError(f"`SumTorque` takes torques, got {type(t).__name__}.")
            flat.extend(t.torques if isinstance(t, SumTorque) else (t,))
        self.torques = tuple(flat)

    def __call__(self, kin, inertia):
        total = jnp.zeros_like(kin.omega)
        for t in self.torques:
            total = total + t(kin, inertia)
        return total

    def potential(self, kin, inertia):
        for t in self.torques:
            if not isinstance(t, AbstractConservativeTorque):
                raise ValueError(
                    f"{type(t).__name__} has no potential energy (it is not an "
                    "`AbstractConservativeTorque`), so neither has the "
                    f"`SumTorque` of {[type(u).__name__ for u in self.torques]}."
                )
        total = jnp.zeros_like(kin.t)
        for t in self.torques:
            total = total + t.potential(kin, inertia)
        return total


class NoTorque(AbstractConservativeTorque):
    """Zero moment (Euler–Poinsot motion, docs/physics.md#torque-free-motion)."""

    def __call__(self, kin, inertia):
        return jnp.zeros_like(kin.omega)

    def potential(self, kin, inertia):
        return jnp.zeros_like(kin.t)


class BodyTorque(AbstractTorque):
    """A constant moment fixed in the body axes (e.g. the perturbing M1, M2, M3 of
    docs/physics.md#equations-of-motion)."""

    moment: Float[Array, "3"]

    def __init__(self, moment: Float[ArrayLike, "3"]):
        self.moment = check_trailing(moment, (3,), "moment")

    def __call__(self, kin, inertia):
        return jnp.broadcast_to(self.moment, kin.omega.shape).astype(kin.omega.dtype)


class InertialTorque(AbstractTorque):
    """A constant moment fixed in the inertial frame O0, given by its O0 components."""

    moment: Float[Array, "3"]

    def __init__(self, moment: Float[ArrayLike, "3"]):
        self.moment = check_trailing(moment, (3,), "moment")

    def __call__(self, kin, inertia):
        q = _need(kin, "quat_inertial", "InertialTorque")
        return rotation.quat_rotate(rotation.quat_conjugate(q), self.moment)


class UniformGravity(AbstractConservativeTorque):
    """Weight in a uniform field along −z0 acting at the centre of mass (heavy top).

    `M = r_c × (−mg γ₀) = mg γ₀ × r_c` with γ₀ the body components of the inertial z0-axis
    and `r_c` the centre-of-mass offset from the fixed point, body components. For
    `r_c = (0, 0, l)` this is the Lagrange top of docs/physics.md#equations-of-motion with
    `k = m g l`:
    `M = k sinθ (cos φ, −sin φ, 0)`. Potential `V = mg r_c · γ₀` (height of the centre of
    mass times the weight).

    **Fields:** `weight` (m g, a scalar) and `com` (r_c, 3 body components).
    """

    weight: Float[Array, ""]
    com: Float[Array, "3"]

    def __init__(self, weight: Float[ArrayLike, ""], com: Float[ArrayLike, "3"]):
        self.weight = check_scalar(weight, "weight")
        self.com = check_trailing(com, (3,), "com")

    def __call__(self, kin, inertia):
        return self.weight * jnp.cross(kin.gamma_inertial, self.com)

    def potential(self, kin, inertia):
        return self.weight * jnp.dot(self.com, kin.gamma_inertial)


def _precession_angle(q):
    """ZXZ precession angle ψ from a unit quaternion without the full Euler conversion
    (this runs in every right-hand-side evaluation): the body z-axis in the parent frame is
    R[:, 2] = (sinψ sinθ, −cosψ sinθ, cosθ), so ψ = atan2(R02, −R12). At θ = 0 (where the
    restoring moment's lever sinθ vanishes) it returns 0, with a finite gradient."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    s, c = x * z + w * y, w * x - y * z  # R02 / 2, −R12 / 2
    origin = (s == 0) & (c == 0)
    return jnp.where(origin, 0.0, jnp.arctan2(s, jnp.where(origin, 1.0, c)))


class PolynomialSinPsi(eqx.Module):
    """The restoring-moment coefficient `k(τ, ψ) = ε K(τ) sin ψ` with K a polynomial,
    `K(τ) = Σ_i coeffs[i] τ^i` (docs/physics.md#first-approximation). Its `coeffs` and `eps`
    are leaves."""

    coeffs: Float[Array, " n"]
    eps: Float[Array, ""]

    def __init__(self, coeffs: Float[ArrayLike, " n"], eps: Float[ArrayLike, ""]):
        self.coeffs = as_float_array(coeffs, "coeffs")
        if not self.coeffs.ndim:
            raise ValueError("`coeffs` must have shape (*batch, n): a polynomial's coefficients.")
        self.eps = check_scalar(eps, "eps")

    def K(self, tau):
        return jnp.polyval(self.coeffs[::-1], tau)

    def __call__(self, tau, psi):
        return self.eps * self.K(tau) * jnp.sin(psi)


class RestoringMoment(AbstractConservativeTorque):
    """Non-stationary restoring moment (Zinkevich & Kozachenko (2008), eq. (1);
    docs/physics.md#equations-of-motion):

        M = k(τ, ψ) sinθ (cos φ, −sin φ, 0) = k(τ, ψ) γ × e_z,   τ = ε t,

    with (ψ, θ, φ) the ZXZ angles of the body relative to its parent frame and γ the
    parent z-axis in body components. `k` is a number (a leaf, the heavy top's `m g l`), or
    any differentiable callable `k(tau, psi)` — an `eqx.Module` such as `PolynomialSinPsi`
    keeps its coefficients as leaves. The constant perturbing moments M1, M2, M3 are added
    as `+ BodyTorque(M)`.

    `eps` (the slow-time scale ε of τ = ε t) defaults to `k.eps` when `k` has one (as
    `PolynomialSinPsi` does), else to 1.

    A number `k` derives from the potential `V = k cosθ`; a callable `k(τ, ψ)` from none
    (docs/physics.md#potential-torques-as-kicks), and `potential` then raises a
    `ValueError`.
    """

    k: Float[Array, ""] | Callable
    eps: Float[Array, ""]

    def __init__(self, k, eps: Float[ArrayLike, ""] | None = None):
        self.k = k if callable(k) else check_scalar(k, "k")
        if eps is None:
            eps = getattr(k, "eps", 1.0)
        self.eps = check_scalar(eps, "eps")

    def __call__(self, kin, inertia):
        lever = jnp.cross(kin.gamma, _e_z(kin.gamma))  # sinθ (cos φ, −sin φ, 0)
        if callable(self.k):
            q = _need(kin, "quat", "RestoringMoment with k(τ, ψ)")
            psi = _precession_angle(q)
            k = self.k(self.eps * kin.t, psi)
        else:
            k = self.k
        return k * lever

    def potential(self, kin, inertia):
        if callable(self.k):
            raise ValueError(
                "RestoringMoment with a callable k(τ, ψ) has no potential energy "
                "(only a number k has one, k cosθ)."
            )
        return self.k * kin.gamma[..., 2]  # k cosθ: the heavy top's mgl cosθ


class GravityGradient(AbstractConservativeTorque):
    """Gravity-gradient torque `M = ε γ × J γ`, ε = 3μ/R³.

    Shinibaev et al. (2013), eq. (2); docs/physics.md#torque-and-integrals.

    γ is the body components of the parent frame's z-axis: the direction of the attracting
    centre — O0's z0 for `RigidBody`, the nadir z1 under a `CircularOrbit` frame. Potential
    `V = ½ ε γᵀ J γ`.
    """

    eps: Float[Array, ""]

    def __init__(self, eps: Float[ArrayLike, ""]):
        self.eps = check_scalar(eps, "eps")

    @classmethod
    def from_orbit_rate(cls, n: Float[ArrayLike, ""]) -> "GravityGradient":
        """ε = 3 n² for a circular orbit of rate n (docs/physics.md#circular-orbit)."""
        n = as_float_array(n, "n")
        return cls(eps=3.0 * n * n)

    def __call__(self, kin, inertia):
        g = kin.gamma
        return self.eps * cross(g, matvec(inertia, g))

    def potential(self, kin, inertia):
        g = kin.gamma
        return 0.5 * self.eps * jnp.dot(g, matvec(inertia, g))


class BalancingTransport(AbstractTorque):
    """The special moment that balances the transport inertia moment,
    `M = J ε_e − J ω_e × ω_e`; under it the relative kinetic energy is conserved
    (Mukhametzyanov (2009), eq. (16); docs/physics.md#balancing-transport-moment)."""

    def __call__(self, kin, inertia):
        return -transport_moment(inertia, kin.omega_e, kin.eps_e)


__all__ = [
    "AbstractConservativeTorque",
    "AbstractTorque",
    "BalancingTransport",
    "BodyTorque",
    "GravityGradient",
    "InertialTorque",
    "NoTorque",
    "PolynomialSinPsi",
    "RestoringMoment",
    "SumTorque",
    "UniformGravity",
]
