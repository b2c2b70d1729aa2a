"""Rigid-body models: pytrees whose leaves are their parameters, with `vector_field(t, y, args)`.

- `RigidBody(inertia, torque)`: absolute motion, Euler's equations
  (docs/physics.md#eulers-equations) with quaternion kinematics
  (docs/physics.md#quaternion-kinematics); state `State(omega, quat)`.
- `RelativeRigidBody(inertia, frame, torque)`: motion relative to a transport frame O1 by
  the compact form, Mukhametzyanov (2009), eq. (11) (docs/physics.md#compact-form); state
  `State(omega_r, quat_r)`.
- `EulerAngleRigidBody(inertia, torque)`: the same equations with ZXZ angles as the
  attitude (the top of docs/physics.md#equations-of-motion as Zinkevich & Kozachenko (2008)
  write it); state `EulerState(omega, angles)`.
- `PoissonRigidBody(inertia, torque)`: the same equations with the Poisson vector γ
  (docs/physics.md#torque-and-integrals); state `PoissonState(omega, gamma)`.

All share `dynamics.euler_rhs` / `relative_rhs` and the torques of `torques.py`. The
inertia is checked (symmetric, physical) when the model is built, by its field's converter
(`eqx.field(converter=...)`, run by the constructor only: `eqx.tree_at` and pytree
unflattening keep a leaf as it is); a `torque` or `frame` of `None` (the default) becomes
`NoTorque()` / `Inertial()` the same way. Equinox runs the converters after any `__init__`,
a subclass's own too: a subclass whose inertia leaf is not one 3×3 tensor re-declares the
field without one (`inertia: Array`).
`with_log_cholesky(model, theta)` swaps in an inertia that is physical by construction,
unchecked: the way to fit an inertia.
"""

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PyTree

from . import rotation
from ._checks import check_trailing, holds_now, sqrt_eps
from .dynamics import euler_rhs, relative_rhs
from .frames import AbstractFrame, Inertial
from .inertia import check_inertia, from_log_cholesky
from .state import EulerState, Kinematics, PoissonState, State
from .torques import AbstractTorque, NoTorque


def _inertia(J: Float[ArrayLike, "3 3"]) -> Float[Array, "3 3"]:
    """The model's inertia: one 3×3, symmetric, physical and positive definite (Euler's
    equations solve J ω' = …; a rod's singular J is physical but has no dynamics)."""
    J = check_trailing(J, (3, 3), "inertia")
    if J.ndim != 2:
        raise ValueError(
            f"`inertia` must be one 3×3 tensor, got shape {J.shape}; build a batch of models "
            "with `eqx.filter_vmap(lambda J: RigidBody(J, torque))(Js)` and pass it to "
            "`simulate_batch(..., model_axes=0)`."
        )
    J = check_inertia(J, "inertia")
    if holds_now(_definite, J):
        return J  # concrete and valid: checked now, in NumPy
    return eqx.error_if(
        J,
        ~_definite(jax.lax.stop_gradient(J)),
        "`inertia` must be positive "
        "definite (a principal moment is zero: a rod or a point has no "
        "rotational dynamics).",
    )


def _torque(torque: AbstractTorque | None) -> AbstractTorque:
    """The model's torque: `NoTorque()` for `None` (the default)."""
    return NoTorque() if torque is None else torque


def _frame(frame: AbstractFrame | None) -> AbstractFrame:
    """A relative model's transport frame: `Inertial()` for `None` (the default)."""
    return Inertial() if frame is None else frame


def _definite(J, xp=jnp):
    """Whether the smallest principal moment exceeds √eps·max|J| (`xp`: jax.numpy or NumPy,
    as for the inertia checks)."""
    smallest = xp.linalg.eigvalsh(0.5 * (J + J.T))[0]
    return smallest > sqrt_eps(J.dtype) * xp.max(xp.abs(J))


def _absolute_kinematics(t, omega, quat, gamma):
    zero = jnp.zeros_like(omega)
    return Kinematics(
        t=jnp.asarray(t),
        omega=omega,
        omega_r=omega,
        omega_e=zero,
        eps_e=zero,
        gamma=gamma,
        gamma_inertial=gamma,
        quat=quat,
        quat_inertial=quat,
    )


def _z_in_body(quat):
    """Body components of the parent z-axis: R(q)ᵀ e_z."""
    return rotation.quat_rotate(
        rotation.quat_conjugate(quat), jnp.array([0.0, 0.0, 1.0], dtype=quat.dtype)
    )


def _normalize_quat(y: State):
    n = jnp.linalg.norm(y.quat, axis=-1)
    return State(y.omega, y.quat / n[..., None]), jnp.max(jnp.abs(n - 1.0))


class AbstractRigidBody(eqx.Module):
    """A model: `vector_field(t, y, args)` for diffrax, plus how to tidy its output."""

    inertia: eqx.AbstractVar[Float[Array, "3 3"]]
    torque: eqx.AbstractVar[AbstractTorque]

    @abc.abstractmethod
    def vector_field(self, t, y, args) -> PyTree:
        """dy/dt at time t."""

    @abc.abstractmethod
    def kinematics(self, t, y) -> Kinematics:
        """The `Kinematics` record of state `y` at time `t` (what torques see)."""

    @abc.abstractmethod
    def normalize(self, y) -> tuple[PyTree, Float[Array, ""]]:
        """Project `y` back on its constraint (unit quaternion, |γ| = 1) and return the
        largest violation that was removed (0 where there is none)."""


class RigidBody(AbstractRigidBody):
    """Absolute rotation about a fixed point or the centre of mass
    (docs/physics.md#eulers-equations):

        J ω' = J ω × ω + M,    q' = ½ q ⊗ (0, ω),

    with `State(omega, quat)`: ω in body components, q the attitude body → O0.

    **Fields:** `inertia` (3×3 J, checked symmetric and physical), `torque` (default
    `NoTorque()`).
    """

    inertia: Float[Array, "3 3"] = eqx.field(converter=_inertia)
    torque: AbstractTorque = eqx.field(default=None, converter=_torque)

    def kinematics(self, t, y: State) -> Kinematics:
        return _absolute_kinematics(t, y.omega, y.quat, _z_in_body(y.quat))

    def vector_field(self, t, y: State, args) -> State:
        M = self.torque(self.kinematics(t, y), self.inertia)
        return State(
            omega=euler_rhs(self.inertia, y.omega, M),
            quat=rotation.quat_derivative(y.quat, y.omega),
        )

    def normalize(self, y: State):
        return _normalize_quat(y)


class RelativeRigidBody(AbstractRigidBody):
    """Rotation relative to a moving transport frame O1 (Mukhametzyanov (2009), eq. (11);
    docs/physics.md#compact-form):

        J ε_r = J ω_r × ω_r − J ε_e + J ω_e × ω_e + 2 ω_r × J' ω_e + M,
        q_r' = ½ q_r ⊗ (0, ω_r),

    with `State(omega=ω_r, quat=q_r)`: ω_r the angular velocity relative to O1 in body
    components and q_r the attitude body → O1. ω_e = R_rᵀ ω_e¹ and ε_e = R_rᵀ dω_e¹/dt
    come from the `frame`; the absolute attitude is q_e ⊗ q_r.

    **Fields:** `inertia`, `frame` (an `AbstractFrame`, default `Inertial()`), `torque`.
    """

    inertia: Float[Array, "3 3"] = eqx.field(converter=_inertia)
    frame: AbstractFrame = eqx.field(default=None, converter=_frame)
    torque: AbstractTorque = eqx.field(default=None, converter=_torque)

    def kinematics(self, t, y: State) -> Kinematics:
        q_e, w_e1, e_e1 = self.frame(t)
        to_body = rotation.quat_conjugate(y.quat)
        omega_e = rotation.quat_rotate(to_body, w_e1)
        eps_e = rotation.quat_rotate(to_body, e_e1)
        q_abs = rotation.quat_multiply(q_e, y.quat)
        return Kinematics(
            t=jnp.asarray(t),
            omega=y.omega + omega_e,
            omega_r=y.omega,
            omega_e=omega_e,
            eps_e=eps_e,
            gamma=_z_in_body(y.quat),
            gamma_inertial=_z_in_body(q_abs),
            quat=y.quat,
            quat_inertial=q_abs,
        )

    def vector_field(self, t, y: State, args) -> State:
        kin = self.kinematics(t, y)
        M = self.torque(kin, self.inertia)
        return State(
            omega=relative_rhs(self.inertia, y.omega, kin.omega_e, kin.eps_e, M),
            quat=rotation.quat_derivative(y.quat, y.omega),
        )

    def normalize(self, y: State):
        return _normalize_quat(y)


class EulerAngleRigidBody(AbstractRigidBody):
    """Absolute motion with ZXZ Euler angles (ψ, θ, φ) as the attitude, as the top of
    Zinkevich & Kozachenko (2008), eq. (1), is written (docs/physics.md#equations-of-motion):
    Euler's equations and the inverse kinematic map of docs/physics.md#euler-angle-rates,
    `ψ' = (p sinφ + q cosφ)/sinθ`, `θ' = p cosφ − q sinφ`, `φ' = r − (p sinφ + q cosφ) cotθ`.
    Singular at sinθ = 0: keep θ away from 0 and π (`rotation.gimbal_lock_distance`).

    **Fields:** `inertia`, `torque`.
    """

    inertia: Float[Array, "3 3"] = eqx.field(converter=_inertia)
    torque: AbstractTorque = eqx.field(default=None, converter=_torque)

    def kinematics(self, t, y: EulerState) -> Kinematics:
        theta, phi = y.angles[1], y.angles[2]
        # Shinibaev et al. (2013), eq. (4); docs/physics.md#poisson-equations
        gamma = jnp.stack(
            [jnp.sin(theta) * jnp.sin(phi), jnp.sin(theta) * jnp.cos(phi), jnp.cos(theta)]
        )
        return _absolute_kinematics(t, y.omega, rotation.euler_to_quat(y.angles, "ZXZ"), gamma)

    def vector_field(self, t, y: EulerState, args) -> EulerState:
        M = self.torque(self.kinematics(t, y), self.inertia)
        return EulerState(
            omega=euler_rhs(self.inertia, y.omega, M),
            angles=rotation.omega_to_euler_rates(y.angles, y.omega, "ZXZ"),
        )

    def normalize(self, y: EulerState):
        return y, jnp.zeros((), dtype=y.omega.dtype)


class PoissonRigidBody(AbstractRigidBody):
    """Absolute motion in the Poisson form (Shinibaev et al. (2013), eqs. (2)–(3);
    docs/physics.md#torque-and-integrals):

        J ω' = J ω × ω + M,    γ' = γ × ω,

    with γ the body components of the parent z-axis. Only torques that depend on γ and ω
    can be used (gravity gradient, uniform gravity, constant-k restoring moment, body
    torques); one that needs the full attitude raises a `ValueError` at trace time.

    **Fields:** `inertia`, `torque`.
    """

    inertia: Float[Array, "3 3"] = eqx.field(converter=_inertia)
    torque: AbstractTorque = eqx.field(default=None, converter=_torque)

    def kinematics(self, t, y: PoissonState) -> Kinematics:
        return _absolute_kinematics(t, y.omega, None, y.gamma)

    def vector_field(self, t, y: PoissonState, args) -> PoissonState:
        M = self.torque(self.kinematics(t, y), self.inertia)
        return PoissonState(
            omega=euler_rhs(self.inertia, y.omega, M), gamma=rotation.poisson(y.gamma, y.omega)
        )

    def normalize(self, y: PoissonState):
        n = jnp.linalg.norm(y.gamma, axis=-1)
        return PoissonState(y.omega, y.gamma / n[..., None]), jnp.max(jnp.abs(n - 1.0))


def with_log_cholesky(
    model: AbstractRigidBody, theta: Float[ArrayLike, "*batch 6"]
) -> AbstractRigidBody:
    """`model` with its inertia replaced by `inertia.from_log_cholesky(theta)`, unchecked:
    the way to fit an inertia (what `identify.fit` does).

    Every real `theta` gives a physical inertia (docs/physics.md#log-cholesky-parametrisation:
    `J' = L Lᵀ` with a positive diagonal of `L`, so `J' ≻ 0`, the triangle inequalities
    hold and J ≻ 0), so the checks of a model's constructor hold by construction and are
    skipped. Building the
    model from a traced `theta` with the constructor instead, `RigidBody(from_log_cholesky(
    theta))`, checks the inertia at run time with `eqx.error_if`, a host callback in your
    program, and JAX's persistent compilation cache never stores a program that holds one:
    a later process compiles it again, where with this function it loads it from the
    cache (docs/performance.md).

    **Arguments:**

    - `model`: any rigid-body model; every field but the inertia is kept.
    - `theta`: the 6 log-Cholesky parameters, `(log L00, log L11, log L22, L10, L20, L21)`;
      a concrete one must give a finite inertia. A leading batch gives a batched inertia (for
      `simulate_batch(..., model_axes=...)` mapping it). A traced non-finite `theta` is
      not refused here: its solves report `RESULTS.nonfinite_state`. Nor is a nearly
      singular inertia (log-diagonal entries far below the others), which the
      constructor's definiteness check would refuse.

    **Returns:** a model of the same class.
    """
    if not isinstance(model, AbstractRigidBody):
        raise ValueError(f"`model` must be a rigid-body model, got {type(model).__name__}.")
    J = from_log_cholesky(theta)  # its shape and dtype checked there
    if not isinstance(J, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(J))):
        raise ValueError("`theta` must be finite (and give a finite inertia).")
    return eqx.tree_at(lambda m: m.inertia, model, J)


__all__ = [
    "AbstractRigidBody",
    "EulerAngleRigidBody",
    "PoissonRigidBody",
    "RelativeRigidBody",
    "RigidBody",
    "with_log_cholesky",
]
