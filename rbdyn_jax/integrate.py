"""Integration of a model with diffrax (the only module that calls diffrax; DESIGN.md).

`simulate(model, y0, ts, ...)` solves one trajectory; `simulate_batch(model, y0s, ts, ...)`
vmaps it over initial conditions and, with `model_axes`, over model parameters. Both are
compiled once per model *structure* (`eqx.filter_jit`): changing parameter values, initial
conditions, times or tolerances reuses the compiled solve.
"""

import numbers

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, PyTree

from ._checks import as_float_array
from .models import AbstractRigidBody


class RESULTS(diffrax.RESULTS):  # pyright: ignore[reportGeneralTypeIssues]
    """Outcome of a solve: diffrax's codes (`successful`, `max_steps_reached`, …) and one
    of ours. The text of each item is its error message."""

    nonfinite_state = (
        "The state or its derivative is not finite (NaN or inf, or a zero quaternion): "
        "check the initial condition and the model's parameters."
    )


class Trajectory(eqx.Module):
    """A solved trajectory.

    **Fields:**
    - `ts`: `(n,)` output times.
    - `ys`: the state at `ts`, with a leading time axis on every leaf (a `State` for the
      quaternion models). Quaternions (and γ in the Poisson form) are renormalised.
    - `stats`: dict of diffrax's step counts (`num_steps`, `num_accepted_steps`,
      `num_rejected_steps`) and `norm_drift`, the largest deviation of |q| (|γ| in the
      Poisson form) from 1 that the renormalisation removed.
    - `result`: a `RESULTS` item; `RESULTS.successful` when the solve succeeded.

    From `simulate_batch` every leaf has a further leading batch axis.
    """

    ts: Float[Array, "*batch n"]
    ys: PyTree
    stats: dict
    result: RESULTS


def _all_finite(tree) -> Array:
    leaves = [jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(tree)]
    return jnp.all(jnp.stack(leaves))


def _where_tree(pred, tree, fill):
    return jax.tree_util.tree_map(lambda x: jnp.where(pred, x, jnp.full_like(x, fill)), tree)


class _Guarded(eqx.Module):
    """The model's vector field, or dy/dt = 0 for a lane flagged bad (`args` = ok flag), so
    a bad lane takes a few steps instead of stalling its batch. A module, not a closure, so
    adjoints (BacksolveAdjoint) see the model's parameters as inputs."""

    model: AbstractRigidBody

    def __call__(self, t, y, ok):
        return _where_tree(ok, self.model.vector_field(t, y, None), 0.0)


def _solve(model, y0, ts, solver, controller, adjoint, max_steps, dt0) -> Trajectory:
    # A non-finite initial state would make the step controller reject step after step
    # until `max_steps` (and hold a whole vmapped batch in its loop): integrate a harmless
    # stand-in instead and report the trajectory as non-finite.
    # The initial attitude is normalised (the torques assume a unit quaternion; a zero one
    # becomes NaN and is reported as non-finite). A state whose derivative is already
    # non-finite (NaN parameters, a singular inertia) is caught here too.
    ts = eqx.error_if(ts, jnp.any(jnp.diff(ts) <= 0), "`ts` must be strictly increasing.")
    y0, _ = model.normalise(y0)
    ok0 = _all_finite(y0)
    ok0 = ok0 & _all_finite(model.vector_field(ts[0], _where_tree(ok0, y0, 1.0), None))
    y0_run = _where_tree(ok0, y0, 1.0)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(_Guarded(model)),
        solver,
        t0=ts[0],
        t1=ts[-1],
        dt0=dt0,
        y0=y0_run,
        args=ok0,
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=controller,
        adjoint=adjoint,
        max_steps=max_steps,
        throw=False,
    )
    ys, drift = model.normalise(sol.ys)
    ys = _where_tree(ok0, ys, jnp.nan)
    result = RESULTS.promote(sol.result)
    bad_state = ~ok0 | ((result == RESULTS.successful) & ~_all_finite(ys))
    result = RESULTS.where(bad_state, RESULTS.nonfinite_state, result)
    stats = {
        "num_steps": sol.stats["num_steps"],
        "num_accepted_steps": sol.stats["num_accepted_steps"],
        "num_rejected_steps": sol.stats["num_rejected_steps"],
        "norm_drift": drift,
    }
    return Trajectory(ts=ts, ys=ys, stats=stats, result=result)


_solve_jit = eqx.filter_jit(_solve)


@eqx.filter_jit
def _solve_batch(model, y0s, ts, solver, controller, adjoint, max_steps, dt0, model_axes):
    def one(m, y0):
        return _solve(m, y0, ts, solver, controller, adjoint, max_steps, dt0)

    return eqx.filter_vmap(one, in_axes=(model_axes, 0))(model, y0s)


def _prepare(model, ts, rtol, atol, max_steps):
    if not isinstance(model, AbstractRigidBody):
        raise ValueError(f"`model` must be a rigid-body model, got {type(model).__name__}.")
    ts = as_float_array(ts, "ts")
    if ts.ndim != 1 or ts.shape[0] < 2:
        raise ValueError(f"`ts` must be a 1-D array of at least 2 times, got shape {ts.shape}.")
    if not isinstance(max_steps, numbers.Integral) or isinstance(max_steps, bool) or max_steps < 1:
        raise ValueError(f"`max_steps` must be a positive int, got {max_steps!r}.")
    tols = []
    for name, tol in (("rtol", rtol), ("atol", atol)):
        if jnp.ndim(tol) != 0:
            raise ValueError(f"`{name}` must be a scalar, got shape {jnp.shape(tol)}.")
        if isinstance(tol, jax.core.Tracer):  # value known only at run time
            tol = eqx.error_if(tol, ~(tol > 0), f"`{name}` must be positive.")
        elif not float(tol) > 0:
            raise ValueError(f"`{name}` must be a positive number, got {tol!r}.")
        tols.append(jnp.asarray(tol, dtype=ts.dtype))
    controller = diffrax.PIDController(rtol=tols[0], atol=tols[1])
    return ts, controller, int(max_steps)


def simulate(
    model: AbstractRigidBody,
    y0: PyTree,
    ts: Float[ArrayLike, " n"],
    *,
    solver: diffrax.AbstractSolver = diffrax.Tsit5(),
    rtol: float = 1e-8,
    atol: float = 1e-8,
    max_steps: int = 16_384,
    adjoint: diffrax.AbstractAdjoint = diffrax.RecursiveCheckpointAdjoint(),
    dt0: float | None = None,
    throw: bool = True,
) -> Trajectory:
    """Integrate `model` from `y0` at `ts[0]`, saving the state at every time of `ts`.

    **Arguments:**
    - `model`: a rigid-body model (`RigidBody`, `RelativeRigidBody`, …).
    - `y0`: its initial state (`State(omega, quat)` for the quaternion models); its
      quaternion (γ in the Poisson form) is normalised first.
    - `ts`: strictly increasing output times; the solve runs from `ts[0]` to `ts[-1]`.
    - `solver`, `adjoint`: diffrax objects, passed through unchanged (adaptive step
      control by `diffrax.PIDController(rtol, atol)`).
    - `rtol`, `atol`: tolerances of the step-size controller, positive scalars (passed to the
      compiled solve as arrays: changing them does not recompile; they may be traced).
    - `max_steps`: the most steps the solver may take.
    - `dt0`: initial step; `None` lets diffrax choose.
    - `throw`: raise a runtime error when the result is not `RESULTS.successful`;
      otherwise the code is returned in `Trajectory.result`.

    **Returns:** a `Trajectory`.
    """
    ts, controller, max_steps = _prepare(model, ts, rtol, atol, max_steps)
    traj = _solve_jit(model, y0, ts, solver, controller, adjoint, max_steps, dt0)
    if throw:
        traj = traj.result.error_if(traj, traj.result != RESULTS.successful)
    return traj


def simulate_batch(
    model: AbstractRigidBody,
    y0s: PyTree,
    ts: Float[ArrayLike, " n"],
    *,
    model_axes: PyTree | None = None,
    solver: diffrax.AbstractSolver = diffrax.Tsit5(),
    rtol: float = 1e-8,
    atol: float = 1e-8,
    max_steps: int = 16_384,
    adjoint: diffrax.AbstractAdjoint = diffrax.RecursiveCheckpointAdjoint(),
    dt0: float | None = None,
    throw: bool = False,
) -> Trajectory:
    """`simulate` vmapped over a batch of initial conditions and, optionally, of models.

    **Arguments:** as `simulate`, and
    - `y0s`: initial states with a leading batch axis on every leaf.
    - `model_axes`: `None` (default) shares `model` across the batch; `0` maps every array
      leaf of `model` along its leading axis (build such a model with
      `eqx.filter_vmap(lambda J: RigidBody(J, torque))(Js)`); or any `in_axes` prefix of
      the model for `eqx.filter_vmap` (e.g. batch only the inertia).
    - `throw`: default `False`: a failing trajectory (`max_steps_reached`,
      `nonfinite_state`, …) gets its own code in `result` and the others are unaffected.

    **Returns:** a `Trajectory` with a leading batch axis on every leaf (including `ts`,
    `stats` and `result`).
    """
    ts, controller, max_steps = _prepare(model, ts, rtol, atol, max_steps)
    traj = _solve_batch(model, y0s, ts, solver, controller, adjoint, max_steps, dt0, model_axes)
    if throw:
        traj = traj.result.error_if(traj, jnp.any(traj.result != RESULTS.successful))
    return traj


__all__ = ["RESULTS", "Trajectory", "simulate", "simulate_batch"]
