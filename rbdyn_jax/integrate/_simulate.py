"""The public solves: `simulate` (one trajectory) and `simulate_batch` (a batch)."""

import dataclasses
import math
import numbers

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float, PyTree

from .._checks import as_float_array
from .._program.program import Program
from .._program.xla import top_level
from ..models import AbstractRigidBody
from ._batching import AbstractBatching, Kernel, Lanes, Vmap, default_batching
from ._diffeqsolve import solve
from ._field import checked_before_tracing, solve_dtype
from ._lie_poisson import LiePoissonSplitting
from ._solution import Trajectory, thrown
from ._splittable import fixed_step_controller

DEFAULT_TOL = 1e-8  # rtol and atol of the default PIDController
# The smallest relative tolerance a solve takes, in units of its dtype's machine epsilon:
# below a few units the step-size controller compares an error estimate made of rounding
# with a tolerance it cannot resolve, and steps shrink until `max_steps` (float32: 9.5e-7).
RTOL_EPS = 8
# The most steps a solve may take: its step counters are int32 where JAX's 64-bit types
# are off (a float32 solve).
MAX_STEPS = 2**31 - 1


def min_rtol(dtype) -> float:
    """The smallest `rtol` a solve in `dtype` takes: `RTOL_EPS` machine epsilons (9.5e-7
    in float32, 1.8e-15 in float64)."""
    return RTOL_EPS * float(np.finfo(np.dtype(dtype)).eps)


def default_tolerance(dtype, default_tol: float = DEFAULT_TOL) -> float:
    """The tolerance a solve in `dtype` takes where none is given: `default_tol`, or, where
    `dtype` cannot resolve it, the power of ten just above `min_rtol(dtype)` (1e-6 in
    float32)."""
    floor = min_rtol(dtype)
    return default_tol if default_tol >= floor else 10.0 ** math.ceil(math.log10(floor))


def _tolerance(tol, name, dtype):
    """A checked tolerance as an array of `dtype`: a traced one is checked at run time."""
    if jnp.ndim(tol) != 0:
        raise ValueError(f"`{name}` must be a scalar, got shape {jnp.shape(tol)}.")
    if isinstance(tol, jax.core.Tracer):  # value known only at run time
        tol = eqx.error_if(tol, ~(tol > 0), f"`{name}` must be positive.")
        return jnp.asarray(tol, dtype)
    if not float(tol) > 0:
        raise ValueError(f"`{name}` must be a positive scalar, got {tol!r}.")
    with jax.ensure_compile_time_eval():  # concrete, also inside a caller's trace
        return jax.device_put(np.asarray(tol, dtype))  # NumPy's cast: no program compiled


def make_controller(
    stepsize_controller: diffrax.AbstractStepSizeController | None = None,
    rtol: float | None = None,
    atol: float | None = None,
    *,
    default_tol: float = DEFAULT_TOL,
    dtype=None,
) -> diffrax.AbstractStepSizeController:
    """The step-size controller a solve runs with: `stepsize_controller`, or
    `diffrax.PIDController(rtol, atol)` (a tolerance not given is `default_tol`, raised to
    what `dtype` resolves: `default_tolerance`); giving both is a `ValueError`. A PID
    controller's tolerances are checked (positive scalars; a concrete `rtol` at least
    `min_rtol(dtype)`, which refuses rtol < 9.5e-7 in float32) and made arrays of `dtype`
    (JAX's default float for `None`), and so are its `dtmin` and `dtmax` where given, so
    that a compiled program taking the controller reuses itself for new values, which may
    also be traced.

    `simulate` and `simulate_batch` call it on their arguments; call it yourself to hold a
    controller in your own compiled function (as `identify.fit` does)."""
    if stepsize_controller is None:
        tol = default_tolerance(jnp.result_type(float) if dtype is None else dtype, default_tol)
        stepsize_controller = diffrax.PIDController(
            rtol=tol if rtol is None else rtol, atol=tol if atol is None else atol
        )
    elif rtol is not None or atol is not None:
        raise ValueError(
            "Give the tolerances either as `rtol`/`atol` or inside `stepsize_controller`, not both."
        )
    if not isinstance(stepsize_controller, diffrax.AbstractStepSizeController):
        raise ValueError(
            "`stepsize_controller` must be a diffrax step-size controller, got "
            f"{type(stepsize_controller).__name__}."
        )
    if isinstance(stepsize_controller, diffrax.PIDController):
        dtype = jnp.result_type(float) if dtype is None else dtype
        tols = (
            _tolerance(stepsize_controller.rtol, "rtol", dtype),
            _tolerance(stepsize_controller.atol, "atol", dtype),
        )
        rtol = stepsize_controller.rtol
        if not isinstance(rtol, jax.core.Tracer) and float(rtol) < min_rtol(dtype):
            raise ValueError(
                f"`rtol` = {float(rtol):g} is finer than {np.dtype(dtype).name} resolves "
                f"(rtol ≥ {min_rtol(dtype):.2g}, {RTOL_EPS} machine epsilons): the step-size "
                "controller's error estimate would be rounding. Use a larger rtol, or solve "
                "in float64 (`jax.config.update('jax_enable_x64', True)`, float64 inputs)."
            )
        stepsize_controller = eqx.tree_at(lambda c: (c.rtol, c.atol), stepsize_controller, tols)
        # Its step bounds too, where given: another bound reuses the compiled solve.
        bounds = {
            name: _tolerance(getattr(stepsize_controller, name), name, dtype)
            for name in ("dtmin", "dtmax")
            if getattr(stepsize_controller, name) is not None
        }
        stepsize_controller = dataclasses.replace(stepsize_controller, **bounds)
    return stepsize_controller


def _prepare(model, y0, ts, stepsize_controller, rtol, atol, max_steps, solver=None, dt0=None):
    if not isinstance(model, AbstractRigidBody):
        raise ValueError(f"`model` must be a rigid-body model, got {type(model).__name__}.")
    ts = as_float_array(ts, "ts")
    if ts.ndim != 1 or ts.shape[0] < 2:
        raise ValueError(f"`ts` must be a 1-D array of at least 2 times, got shape {ts.shape}.")
    if not isinstance(ts, jax.core.Tracer):  # checked here, so not in the compiled solve
        t = np.asarray(ts)  # NumPy: concrete even while a caller's function is traced
        if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
            raise ValueError("`ts` must be finite and strictly increasing.")
    if (
        not isinstance(max_steps, numbers.Integral)
        or isinstance(max_steps, bool)
        or not 1 <= max_steps <= MAX_STEPS
    ):
        raise ValueError(f"`max_steps` must be an int in 1..{MAX_STEPS}, got {max_steps!r}.")
    if isinstance(solver, LiePoissonSplitting):  # fixed steps, its models only
        stepsize_controller = fixed_step_controller(
            model, ts, stepsize_controller, rtol, atol, dt0, max_steps
        )
        rtol = atol = None
    dtype = solve_dtype(model, y0, ts)
    ts = ts.astype(dtype)  # exact: the solve's dtype is at least the times'
    controller = make_controller(stepsize_controller, rtol, atol, dtype=dtype)
    if dt0 is not None:  # an array: another first step reuses the compiled solve
        dt0 = _tolerance(dt0, "dt0", dtype)
    return ts, controller, int(max_steps), dt0


_solved = Program(solve, validated=checked_before_tracing)


def array_fields(y0, name):
    """Refuse a state whose fields are lists or tuples, which a solve would take apart into
    scalars (the leaves of a pytree)."""
    if isinstance(y0, eqx.Module):
        for field, value in vars(y0).items():
            if isinstance(value, list | tuple):
                raise ValueError(
                    f"`{name}.{field}` is a {type(value).__name__}: give the state's fields "
                    f"as arrays, e.g. `jnp.asarray({field})`."
                )


def one_state(y0):
    """Refuse a `y0` that is not one trajectory's state: its fields must be arrays and every
    leaf a vector. A batch of states in `simulate` would be integrated as one coupled
    system, with one step size and one error norm over the whole batch, which dilutes each
    trajectory's error by the batch's size: a `ValueError` points to `simulate_batch`."""
    array_fields(y0, "y0")
    shapes = [np.shape(x) for x in jax.tree_util.tree_leaves(y0)]
    if any(len(s) != 1 for s in shapes):
        raise ValueError(
            "`y0` must be one trajectory's state, every leaf a vector "
            f"(`State(omega=(3,), quat=(4,))`); got shapes {shapes}. Solve a batch of "
            "initial states with `simulate_batch`."
        )


def batch_size(model, y0s, model_axes) -> int:
    """The number of trajectories in a batch: the leading axis every leaf of `y0s` carries,
    which the arrays `model_axes` maps must carry along their axis too. A `ValueError`
    names the shapes that disagree."""
    shapes = [np.shape(x) for x in jax.tree_util.tree_leaves(y0s)]
    sizes = {s[0] if s else None for s in shapes}
    if not shapes or None in sizes or len(sizes) != 1:
        raise ValueError(
            "`y0s` must carry the batch along a leading axis of every leaf, of one size; "
            f"got shapes {shapes}."
        )
    (n,) = sizes

    def check(axis, sub):  # the arrays of `sub` mapped along `axis`
        axis = axis.axis if isinstance(axis, eqx.if_array) else axis
        if not isinstance(axis, int):  # None, or a callable choosing per leaf
            return
        for x in jax.tree_util.tree_leaves(sub):
            if eqx.is_array(x) and (x.ndim <= axis or x.shape[axis] != n):
                raise ValueError(
                    f"`model_axes` maps a model array of shape {x.shape} along axis {axis}, "
                    f"which must be the batch's {n} trajectories (`y0s`)."
                )

    if model_axes is not None:
        jax.tree_util.tree_map(check, model_axes, model, is_leaf=lambda x: x is None)
    return n


def simulate(
    model: AbstractRigidBody,
    y0: PyTree,
    ts: Float[ArrayLike, " n"],
    *,
    solver: diffrax.AbstractSolver = diffrax.Tsit5(),
    stepsize_controller: diffrax.AbstractStepSizeController | None = None,
    rtol: float | None = None,
    atol: float | None = None,
    max_steps: int = 16_384,
    adjoint: diffrax.AbstractAdjoint | None = None,
    dt0: float | None = None,
    throw: bool = False,
) -> Trajectory:
    """Integrate `model` from `y0` at `ts[0]`, saving the state at every time of `ts`.

    Compiled once per model *structure*: new parameter values, initial conditions, times,
    tolerances, first steps or step bounds reuse the compiled solve.

    **Arguments:**

    - `model`: a rigid-body model (`RigidBody`, `RelativeRigidBody`, …).
    - `y0`: its initial state, one trajectory's (`State(omega, quat)` of arrays of shapes
      (3,) and (4,) for the quaternion models; a batch is `simulate_batch`'s); its
      quaternion (γ in the Poisson form) is normalised first.
    - `ts`: strictly increasing output times; the solve runs from `ts[0]` to `ts[-1]`.
    - `solver`, `adjoint`: diffrax objects, passed through unchanged (`adjoint=None`, the
      default, takes `diffrax.RecursiveCheckpointAdjoint()`). The structure-preserving
      `LiePoissonSplitting` takes fixed steps: give `dt0`, and no tolerances; its model and
      torque are checked before the solve is traced.
    - `stepsize_controller`: a diffrax step-size controller, passed through (its
      tolerances as arrays); default `diffrax.PIDController(rtol=1e-8, atol=1e-8)`
      (1e-6 in float32: `default_tolerance`), or `diffrax.ConstantStepSize()` for
      `LiePoissonSplitting`.
    - `rtol`, `atol`: shorthand for `stepsize_controller=diffrax.PIDController(rtol,
      atol)` (the other defaulting as above); positive scalars, which may be traced. The
      solve runs in the dtype of `ts`, the model's arrays and `y0` together; a concrete
      `rtol` finer than it resolves is refused (`min_rtol`: below 9.5e-7 in float32).
    - `max_steps`: the most steps the solver may take.
    - `dt0`: initial step (a positive scalar; another value reuses the compiled solve);
      `None` takes 0.01 (in the unit of `ts`), what `diffeqsolve` takes. For
      `LiePoissonSplitting`, the fixed step (required).
    - `throw`: default `False`: the outcome is returned in `Trajectory.result`
      (`RESULTS.successful`, `max_steps_reached`, `nonfinite_state`, …), as
      `simulate_batch` returns it per trajectory. `True` raises a runtime error when the
      result is not `RESULTS.successful`.

    **Returns:** a `Trajectory`.
    """
    one_state(y0)
    ts, controller, max_steps, dt0 = _prepare(
        model, y0, ts, stepsize_controller, rtol, atol, max_steps, solver, dt0
    )
    adjoint = diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint
    traj = _solved(model, y0, ts, solver, controller, adjoint, max_steps, dt0)
    return thrown(traj) if throw else traj


def simulate_batch(
    model: AbstractRigidBody,
    y0s: PyTree,
    ts: Float[ArrayLike, " n"],
    *,
    model_axes: PyTree | None = None,
    batching: AbstractBatching | None = None,
    solver: diffrax.AbstractSolver = diffrax.Tsit5(),
    stepsize_controller: diffrax.AbstractStepSizeController | None = None,
    rtol: float | None = None,
    atol: float | None = None,
    max_steps: int = 16_384,
    adjoint: diffrax.AbstractAdjoint | None = None,
    dt0: float | None = None,
    throw: bool = False,
) -> Trajectory:
    """Solve a batch of trajectories: `simulate` over a batch of initial conditions and,
    optionally, of models.

    **Arguments:** as `simulate`, and

    - `y0s`: initial states with a leading batch axis on every leaf, of one size (none:
      the `Trajectory` of no trajectories).
    - `model_axes`: `None` (default) shares `model` across the batch; `0` maps every array
      leaf of `model` along its leading axis (build such a model with
      `eqx.filter_vmap(lambda J: RigidBody(J, torque))(Js)`); or any `in_axes` prefix of
      the model for `eqx.filter_vmap` (e.g. batch only the inertia).
    - `batching`: how the batch is run: `Lanes(...)` (the lane solver), `Kernel(...)` (a
      Pallas kernel, a block of trajectories per program) or `Vmap()` (`diffeqsolve`
      vmapped). `None` (default) takes, on a GPU backend, `Kernel()` where it can run the
      solve (an explicit Runge–Kutta solver, a `PIDController`, no `adjoint`, a field
      written on vector components); else `Lanes()` where it can run the solve (the same
      solvers and controller); else `Vmap()` (for `LiePoissonSplitting`, whose fixed steps
      run in lockstep). All give the same trajectories to round-off.
    - `adjoint`: for `Vmap` only (default there `diffrax.RecursiveCheckpointAdjoint()`);
      giving one selects `Vmap` by default.
    - `throw`: default `False`: a failing trajectory (`max_steps_reached`,
      `nonfinite_state`, …) gets its own code in `result` and the others are unaffected.
      With `throw=True` inside a caller's transformation (`jax.jit`, …), the lane solver
      and the kernel run on one device: XLA aborts the process when a check raises on one
      device of a program while the others wait for it.

    **Returns:** a `Trajectory` with a leading batch axis on every leaf (including `ts`,
    `stats` and `result`).
    """
    array_fields(y0s, "y0s")
    ts, controller, max_steps, dt0 = _prepare(
        model, y0s, ts, stepsize_controller, rtol, atol, max_steps, solver, dt0
    )
    if batching is not None and not isinstance(batching, AbstractBatching):
        raise ValueError(
            "`batching` must be `rbdyn_jax.Lanes(...)`, `rbdyn_jax.Kernel(...)`, "
            f"`rbdyn_jax.Vmap()` or None, got {type(batching).__name__}."
        )
    if batch_size(model, y0s, model_axes) == 0:  # no lanes to fill: the vmapped solve
        batching = Vmap()  # gives the empty `Trajectory`
    elif batching is None:
        batching = default_batching(solver, controller, adjoint, model, y0s, model_axes)
    if throw and isinstance(batching, Lanes | Kernel) and not top_level():
        batching = dataclasses.replace(batching, devices=1)
    traj = batching.solve(
        model,
        y0s,
        ts,
        solver=solver,
        controller=controller,
        adjoint=adjoint,
        max_steps=max_steps,
        dt0=dt0,
        model_axes=model_axes,
    )
    return thrown(traj) if throw else traj
