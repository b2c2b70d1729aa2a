"""First integrals and other conserved quantities along a trajectory.

See the physics guide: docs/physics.md#torque-free-motion,
docs/physics.md#balancing-transport-moment, docs/physics.md#torque-and-integrals and
docs/physics.md#the-integrable-case.

Pure functions of `(model, trajectory)`, evaluated at every saved time (the leading axis of
`trajectory.ys`); each returns an array with that time axis. They use the model's own
`kinematics`, so they work for every state form that carries what they need. A trajectory
from `simulate_batch` (leading batch axes before time) gives results with those axes too,
for a model shared by the batch (with a batched model, `jax.vmap` over both yourself).
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from . import rotation
from ._checks import sqrt_eps
from ._vector import HIGHEST
from .frames import Inertial
from .integrate import Trajectory
from .models import AbstractRigidBody, RelativeRigidBody
from .torques import AbstractConservativeTorque, GravityGradient, SumTorque


def _over_batch(f):
    """Map `f(model, traj)` over the leading batch axes of a batched trajectory."""

    @functools.wraps(f)
    def wrapper(model, traj):
        if traj.ts.ndim > 1:
            return jax.vmap(lambda tr: wrapper(model, tr))(traj)
        return f(model, traj)

    return wrapper


def _kinematics(model: AbstractRigidBody, traj: Trajectory):
    return jax.vmap(model.kinematics)(traj.ts, traj.ys)


def _quad(J, v):
    return jnp.einsum("...i,ij,...j->...", v, J, v, precision=HIGHEST)


@_over_batch
def kinetic_energy(model: AbstractRigidBody, traj: Trajectory) -> Float[Array, " n"]:
    """Absolute kinetic energy `T = ½ ωᵀ J ω`, ω = ω_r + ω_e
    (docs/physics.md#inertia-tensor)."""
    kin = _kinematics(model, traj)
    return 0.5 * _quad(model.inertia, kin.omega)


@_over_batch
def energy(model: AbstractRigidBody, traj: Trajectory) -> Float[Array, " n"]:
    """Total energy `T + V` of an absolute model with conservative torques: the heavy top
    (`V = mg r_c·γ₀`), the constant-k restoring moment (`V = k cosθ`), the gravity gradient
    (`V = ½ ε γᵀ J γ`, docs/physics.md#torque-and-integrals). Raises a `ValueError` naming
    a torque with no potential (one that is not an `AbstractConservativeTorque`, a sum with
    such a term, or a restoring moment with a callable k). For a relative model in a moving
    frame this sum is not an integral (use the frame's own integral, e.g. the Jacobi
    integral of a circular orbit): a `ValueError`."""
    if isinstance(model, RelativeRigidBody) and not isinstance(model.frame, Inertial):
        raise ValueError(
            "`energy` is the absolute-motion energy; a RelativeRigidBody in a "
            "moving frame does not conserve it."
        )
    kin = _kinematics(model, traj)
    if not isinstance(model.torque, AbstractConservativeTorque | SumTorque):
        raise ValueError(
            f"{type(model.torque).__name__} has no potential energy (it is not "
            "an `AbstractConservativeTorque`)."
        )
    V = jax.vmap(lambda k: model.torque.potential(k, model.inertia))(kin)
    return 0.5 * _quad(model.inertia, kin.omega) + V


@_over_batch
def angular_momentum_inertial(model: AbstractRigidBody, traj: Trajectory) -> Float[Array, "n 3"]:
    """Angular momentum `L = R(q) J ω` in inertial (O0) components; constant for a
    torque-free body (docs/physics.md#torque-free-motion). Needs the attitude (not the
    Poisson form)."""
    kin = _kinematics(model, traj)
    if kin.quat_inertial is None:
        raise ValueError(
            "`angular_momentum_inertial` needs the attitude; the Poisson form only carries γ."
        )
    L_body = jnp.einsum("ij,nj->ni", model.inertia, kin.omega, precision=HIGHEST)
    return rotation.quat_rotate(kin.quat_inertial, L_body)


@_over_batch
def area_integral(model: AbstractRigidBody, traj: Trajectory) -> Float[Array, " n"]:
    """Area integral `(J ω)·γ`: the angular momentum about the parent z-axis, conserved
    under torques symmetric about it (heavy top, gravity gradient;
    docs/physics.md#torque-and-integrals) where that axis is fixed in space: an absolute
    model, or a relative one whose frame turns about its z-axis. In a frame whose z-axis
    turns (a circular orbit's) it changes with the frame, and is no integral."""
    kin = _kinematics(model, traj)
    return jnp.einsum("ij,nj,ni->n", model.inertia, kin.omega, kin.gamma, precision=HIGHEST)


@_over_batch
def gamma_norm(model: AbstractRigidBody, traj: Trajectory) -> Float[Array, " n"]:
    """|γ|, which is 1 for the Poisson vector (docs/physics.md#poisson-equations)."""
    return jnp.linalg.norm(_kinematics(model, traj).gamma, axis=-1)


@_over_batch
def relative_kinetic_energy(model: AbstractRigidBody, traj: Trajectory) -> Float[Array, " n"]:
    """`T_r = ½ ω_rᵀ J ω_r`, conserved under `BalancingTransport`
    (docs/physics.md#balancing-transport-moment)."""
    return 0.5 * _quad(model.inertia, _kinematics(model, traj).omega_r)


def _gravity_gradient_eps(model: AbstractRigidBody) -> Array:
    torques = model.torque.torques if isinstance(model.torque, SumTorque) else (model.torque,)
    gg = [t for t in torques if isinstance(t, GravityGradient)]
    if len(gg) != 1:
        raise ValueError("`gg_integrable_integrals` needs a model with one GravityGradient.")
    return gg[0].eps


@_over_batch
def gg_integrable_integrals(model: AbstractRigidBody, traj: Trajectory):
    """The four integrals of the integrable case A = B = m C (Shinibaev et al. (2013),
    eq. (14); docs/physics.md#the-integrable-case):

        r,   γ² + γ'² + γ''²,   C1 = p² + q² + ε n γ''²,   C2 = γ p + γ' q + r (n + 1) γ'',

    with n = (1 − m)/m and the inertia taken from the model's (diagonal) J.

    **Returns:** a tuple `(C1, C2, r, gamma_sq)` of `(n,)` arrays (the order of
    `analytic.gg_integrable_case_integrals`). `simulate` renormalises γ on output, so the
    drift of |γ|² it removed is in `trajectory.stats["norm_drift"]`, not in `gamma_sq`.
    """
    J = model.inertia
    off = jnp.abs(J - jnp.diag(jnp.diagonal(J)))
    not_axisymmetric = (jnp.max(off) + jnp.abs(J[0, 0] - J[1, 1])) > sqrt_eps(J.dtype) * jnp.max(
        jnp.abs(J)
    )
    J = eqx.error_if(
        J, not_axisymmetric, "`gg_integrable_integrals` needs a principal J = diag(A, A, C)."
    )
    kin = _kinematics(model, traj)
    A, C = J[0, 0], J[2, 2]
    n = (C - A) / A  # (1 − m)/m with m = A / C
    eps = _gravity_gradient_eps(model)
    p, q, r = kin.omega[:, 0], kin.omega[:, 1], kin.omega[:, 2]
    g, g1, g2 = kin.gamma[:, 0], kin.gamma[:, 1], kin.gamma[:, 2]
    C1 = p**2 + q**2 + eps * n * g2**2
    C2 = g * p + g1 * q + r * (n + 1) * g2
    return C1, C2, r, g**2 + g1**2 + g2**2


__all__ = [
    "angular_momentum_inertial",
    "area_integral",
    "energy",
    "gamma_norm",
    "gg_integrable_integrals",
    "kinetic_energy",
    "relative_kinetic_energy",
]
