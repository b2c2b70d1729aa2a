"""Kinematic equations: the rates of a quaternion, of a rotation matrix and of a vector fixed
in the parent frame (Poisson's equation) given the body angular velocity, the angular
velocity from a rotation matrix and its rate, and the cross-product matrix `skew` and its
inverse `vee`.
"""

import jax.numpy as jnp

from .._checks import check_trailing
from .._custom_types import (
    Matrix,
    MatrixLike,
    Quaternion,
    QuaternionLike,
    Vector,
    VectorLike,
)
from .._vector import HIGHEST, cross, split
from ._common import _broadcast
from ._quaternion import quat_multiply


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
