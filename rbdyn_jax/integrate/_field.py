"""The vector-field plumbing every solve shares: the unit time the solves run in, the
guarded field (a bad trajectory stands still instead of stalling its batch), the checked
start and the finished `Trajectory`."""

import dataclasses

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from .._program.xla import nested_filter_jit
from ..models import AbstractRigidBody
from ._solution import RESULTS, Trajectory, as_result, result_code


def all_finite(tree) -> Array:
    leaves = [jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(tree)]
    return jnp.all(jnp.stack(leaves))


def array_axes(model_axes):
    """`simulate_batch`'s `model_axes` as `eqx.filter_vmap` takes it: each integer axis of
    the prefix maps only the array leaves beneath it (`eqx.if_array`), so that a model's
    other leaves (a Python function such as a restoring moment's `k`) are shared by the
    batch, as "`0` maps every array leaf" says."""
    return jax.tree_util.tree_map(
        lambda a: eqx.if_array(a) if isinstance(a, int) else a, model_axes
    )


def where_tree(pred, tree, fill):
    return jax.tree_util.tree_map(lambda x: jnp.where(pred, x, jnp.full_like(x, fill)), tree)


# diffeqsolve's first step when given `dt0=None`: its controller picks a step by Hairer's
# heuristic only for a bare `ODETerm`, and diffeqsolve hands it the term wrapped, so it
# takes 0.01. Kept in the unit of `ts` when the solves run in the unit time (`unit_time`),
# so that they take the steps they took in t (tested against a plain `diffeqsolve` in t).
FIRST_STEP = 0.01


def checked_before_tracing(model, y0, ts, solver, controller, *rest):
    """What a solve's own checks have validated before it is traced where it is concrete
    (`simulate`'s checks of the times and tolerances, in NumPy): the solve's `Program` then
    traces it with its runtime checks as NaN. Every solve program takes these five first."""
    return ts, controller


def checked_times(ts):
    """`ts`, checked strictly increasing at run time (times validated before tracing never
    fail it: `simulate`'s own checks)."""
    return eqx.error_if(ts, jnp.any(jnp.diff(ts) <= 0), "`ts` must be strictly increasing.")


def unit_time(ts, dt0):
    """The solves run in the time s = (t − t0)/span ∈ [0, 1], `t0, span = ts[0], ts[-1] −
    ts[0]`: returns `t0`, `span`, the output times in s and the first step in s (`dt0`, or
    `FIRST_STEP`, in the unit of `ts`).

    diffeqsolve's `t0` and `t1` are then the constants 0 and 1, whatever `ts` is: its
    end-of-interval clip (t1 less 100 floats, 100 chained `prevbefore` calls) folds to a
    constant instead of being most of the program's instructions, and one compiled solve
    serves every `ts`. With dy/ds = span·f and the first step given in t, the steps are
    those of the solve in t, to round-off (the controller's error estimates and step
    factors do not depend on the time unit)."""
    t0, span = ts[0], ts[-1] - ts[0]
    return t0, span, (ts - t0) / span, (FIRST_STEP if dt0 is None else dt0) / span


def controller_in_unit_time(controller, t0, span):
    """`controller` with the times it holds (PID's `dtmin`/`dtmax`; `StepTo`'s `ts`;
    `ClipStepSizeController`'s `step_ts`/`jump_ts`) in the unit time (`unit_time`), so that
    a controller given in the unit of `ts` steps as it would there. A controller whose
    times rbdyn_jax does not know is refused rather than misread."""

    def dt(x):
        return None if x is None else x / span

    def t(x):
        return None if x is None else (jnp.asarray(x) - t0) / span

    if isinstance(controller, diffrax.ConstantStepSize):
        return controller
    if isinstance(controller, diffrax.PIDController):
        return dataclasses.replace(
            controller, dtmin=dt(controller.dtmin), dtmax=dt(controller.dtmax)
        )
    if isinstance(controller, diffrax.StepTo):
        return dataclasses.replace(controller, ts=t(controller.ts))
    if isinstance(controller, diffrax.ClipStepSizeController):
        return dataclasses.replace(
            controller,
            controller=controller_in_unit_time(controller.controller, t0, span),
            step_ts=t(controller.step_ts),
            jump_ts=t(controller.jump_ts),
        )
    raise ValueError(
        f"rbdyn_jax does not know which times a {type(controller).__name__} holds (its "
        "solves run in a rescaled time): use a diffrax PIDController, ConstantStepSize, "
        "StepTo or ClipStepSizeController."
    )


def per_unit_time(span, tree):
    """A rate dy/dt as dy/ds (`unit_time`)."""
    return jax.tree_util.tree_map(lambda x: span * x, tree)


@nested_filter_jit
def field(model, t, y):
    """`model.vector_field(t, y, None)`, traced once per solve. A solve traces the field
    several times (its start, diffeqsolve's check of the term, the Runge–Kutta step of its
    loop body for its structure and for the loop, and more under `vmap`); as one `jit` it
    is traced, batched and lowered once, and XLA inlines it again: the same program."""
    return model.vector_field(t, y, None)


class Guarded(eqx.Module):
    """The model's vector field in the unit time s (`unit_time`), or dy/ds = 0 for a
    trajectory flagged bad (`args` = ok flag), so a bad trajectory takes a few steps
    instead of stalling its batch. A module, not a closure, so adjoints
    (BacksolveAdjoint) see the model's parameters (and `t0`, `span`) as inputs."""

    model: AbstractRigidBody
    t0: Array
    span: Array

    def __call__(self, s, y, ok):
        f = field(self.model, self.t0 + s * self.span, y)
        return per_unit_time(self.span, where_tree(ok, f, 0.0))


def solve_dtype(model, y0, t):
    """The dtype a solve runs in: that of the times, the model's arrays and `y0` together
    (standard promotion, also under the caller's strict promotion)."""
    inexact = [
        x
        for x in jax.tree_util.tree_leaves((t, model, y0))
        if eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.inexact)
    ]
    with jax.numpy_dtype_promotion("standard"):
        return jnp.result_type(*inexact)


def promoted(model, y0, t):
    """`y0` with every leaf an array in the dtype its steps give it (`solve_dtype`; an
    explicit cast). A float32 `y0` with float64 times starts in float64, and is normalised
    there; an integer one (`[1, 0, 0, 0]`) starts as the floats it holds."""
    dtype = solve_dtype(model, y0, t)
    return jax.tree_util.tree_map(lambda y: jnp.asarray(y).astype(dtype), y0)


def start(model, y0, t0):
    """The normalised initial state, whether it (and its derivative) is finite, and the
    state actually integrated: a harmless stand-in for a non-finite one, which would make
    the step controller reject step after step until `max_steps` (and hold a whole batch
    in its loop). The trajectory is then reported as `nonfinite_state`. The initial
    attitude is normalised (the torques assume a unit quaternion; a zero one becomes NaN
    and is reported as non-finite). A state whose derivative is already non-finite (NaN
    parameters, a singular inertia) is caught here too. Also returns f(t0, ·) of the state
    integrated, for a caller that needs it."""
    y0, _ = model.normalize(y0)
    ok0 = all_finite(y0)
    y_run = where_tree(ok0, y0, 1.0)
    f0 = field(model, t0, y_run)
    ok0 = ok0 & all_finite(f0)
    return ok0, where_tree(ok0, y0, 1.0), f0


def finish(model, ts, ys, ok0, result, counts) -> Trajectory:
    """A `Trajectory` from raw solver output (one trajectory): renormalise, NaN out a
    non-finite start, and report a non-finite state as `nonfinite_state`."""
    ys, drift = model.normalize(ys)
    ys = where_tree(ok0, ys, jnp.nan)
    if not isinstance(result, RESULTS):  # diffrax's own codes
        result = as_result(result_code(result))
    bad_state = ~ok0 | ((result == RESULTS.successful) & ~all_finite(ys))
    result = RESULTS.where(bad_state, RESULTS.nonfinite_state, result)
    stats = {
        "num_steps": counts[0],
        "num_accepted_steps": counts[1],
        "num_rejected_steps": counts[2],
        "norm_drift": drift,
    }
    return Trajectory(ts=ts, ys=ys, stats=stats, result=result)
