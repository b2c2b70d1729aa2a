"""State of a rigid body and the record a torque is evaluated on.

The bottom layer of the package: it imports no other module of it, so that torques and models
can both use it. Conventions (docs/physics.md#conventions): vectors in body components;
quaternions `[w, x, y, z]`, with `R(q)` mapping body components to the parent frame's
components.
"""

import equinox as eqx
from jaxtyping import Array, Float


class State(eqx.Module):
    """State of the quaternion forms of the equations (docs/physics.md#quaternion-kinematics).

    **Fields:**

    - `omega`: `(*batch, 3)` body angular velocity in body components — absolute for
      `RigidBody`, relative to the transport frame O1 (ω_r) for `RelativeRigidBody`.
    - `quat`: `(*batch, 4)` attitude of the body relative to its parent frame (O0 for
      `RigidBody`, O1 for `RelativeRigidBody`), scalar first.
    """

    omega: Float[Array, "*batch 3"]
    quat: Float[Array, "*batch 4"]


class EulerState(eqx.Module):
    """State of the Euler-angle form (docs/physics.md#equations-of-motion): `omega` =
    (p, q, r) in body components and `angles` = ZXZ (ψ, θ, φ) of the body relative to the
    parent frame."""

    omega: Float[Array, "*batch 3"]
    angles: Float[Array, "*batch 3"]


class PoissonState(eqx.Module):
    """State of the Poisson form (docs/physics.md#poisson-equations): `omega` in body
    components and `gamma`, the body components of the parent frame's z-axis
    (γ, γ', γ'')."""

    omega: Float[Array, "*batch 3"]
    gamma: Float[Array, "*batch 3"]


class Kinematics(eqx.Module):
    """Everything a torque may depend on, at one instant (all vectors in body components).

    **Fields:**

    - `t`: time.
    - `omega`: absolute angular velocity ω = ω_r + ω_e.
    - `omega_r`: angular velocity relative to the parent frame (= `omega` in absolute models).
    - `omega_e`, `eps_e`: the parent frame's absolute angular velocity and acceleration
      (zero in absolute models; docs/physics.md#transport-frame).
    - `gamma`: the parent frame's z-axis (O0's z0 for absolute models, O1's z1 — the nadir
      for a circular orbit — for relative ones; docs/physics.md#poisson-equations,
      docs/physics.md#circular-orbit).
    - `gamma_inertial`: the inertial z0-axis (equal to `gamma` in absolute models).
    - `quat`: attitude relative to the parent frame, or `None` where the state form does
      not carry it (the Poisson form).
    - `quat_inertial`: attitude relative to O0, or `None` likewise.
    """

    t: Float[Array, ""]
    omega: Float[Array, "3"]
    omega_r: Float[Array, "3"]
    omega_e: Float[Array, "3"]
    eps_e: Float[Array, "3"]
    gamma: Float[Array, "3"]
    gamma_inertial: Float[Array, "3"]
    quat: Float[Array, "4"] | None
    quat_inertial: Float[Array, "4"] | None


__all__ = ["EulerState", "Kinematics", "PoissonState", "State"]
