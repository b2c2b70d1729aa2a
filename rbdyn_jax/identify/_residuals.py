"""The whitened residual vector of a model against `Observations`, and its loss ½ Σ r²."""

import diffrax
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .. import rotation
from ..integrate import RESULTS, make_controller, simulate
from ..models import RigidBody
from ..state import State
from ._observations import Observations

DEFAULT_TOL = 1e-10  # identify's default rtol and atol: solve errors far below the noise


def _simulate_all(
    model, y0s: State, data: Observations, solver, stepsize_controller, max_steps, adjoint
):
    def one(y0, ts):
        return simulate(
            model,
            y0,
            ts,
            solver=solver,
            stepsize_controller=stepsize_controller,
            max_steps=max_steps,
            adjoint=adjoint,
            throw=False,
        )

    return jax.vmap(one)(y0s, data.ts)


def residuals(
    model: RigidBody,
    y0s: State,
    data: Observations,
    *,
    solver: diffrax.AbstractSolver = diffrax.Tsit5(),
    stepsize_controller: diffrax.AbstractStepSizeController | None = None,
    rtol: float | None = None,
    atol: float | None = None,
    max_steps: int = 4096,
    adjoint: diffrax.AbstractAdjoint = diffrax.RecursiveCheckpointAdjoint(),
) -> Float[Array, " m"]:
    """Whitened residual vector of `model` started at `y0s` (`State` with a leading K axis)
    against `data`: `[(ω_sim − ω_obs)/σ_ω ; rotvec(q_obs* ⊗ q_sim)/σ_q]` flattened, zero at
    masked samples (docs/physics.md#quaternion-kinematics,
    docs/physics.md#eulers-equations). `|rotvec|` is the geodesic angle between observed
    and simulated attitude, invariant to the sign of either quaternion. A failed solve gives
    NaN residuals for its trajectory.

    `solver`, `stepsize_controller`, `max_steps`, `adjoint` are passed to `simulate`;
    `rtol`, `atol` are shorthand for `stepsize_controller=diffrax.PIDController(rtol, atol)`,
    each defaulting to 1e-10 (giving both a controller and a tolerance is a `ValueError`)."""
    controller = make_controller(stepsize_controller, rtol, atol, default_tol=DEFAULT_TOL)
    traj = _simulate_all(model, y0s, data, solver, controller, max_steps, adjoint)
    ok = (traj.result == RESULTS.successful)[:, None]
    parts = []
    if data.omega is not None:
        r = (traj.ys.omega - data.omega) / data.sigma_omega
        r = jnp.where(data.mask_omega[..., None], r, 0.0)
        parts.append(jnp.where(ok[..., None], r, jnp.nan).reshape(-1))
    if data.quat is not None:
        dq = rotation.quat_multiply(rotation.quat_conjugate(data.quat), traj.ys.quat)
        r = rotation.quat_to_rotvec(dq) / data.sigma_quat[..., None]
        r = jnp.where(data.mask_quat[..., None], r, 0.0)
        parts.append(jnp.where(ok[..., None], r, jnp.nan).reshape(-1))
    return jnp.concatenate(parts)


def loss(model: RigidBody, y0s: State, data: Observations, **kwargs) -> Float[Array, ""]:
    """½ Σ r² of `residuals` (the negative log-likelihood under Gaussian noise, up to a
    constant). Keyword arguments as `residuals`."""
    r = residuals(model, y0s, data, **kwargs)
    return 0.5 * jnp.sum(r * r)
