"""The solve of one trajectory by `diffrax.diffeqsolve`, and its vmapped batch."""

import diffrax
import equinox as eqx

from ._field import (
    Guarded,
    array_axes,
    checked_times,
    controller_in_unit_time,
    finish,
    promoted,
    start,
    unit_time,
)
from ._solution import Trajectory


def solve(model, y0, ts, solver, controller, adjoint, max_steps, dt0) -> Trajectory:
    """One trajectory: `diffeqsolve` in the unit time (`unit_time`), from the checked start
    (`start`), saving at `ts`; a failure is reported in `Trajectory.result`, not raised."""
    ts = checked_times(ts)
    ok0, y0_run, _ = start(model, promoted(model, y0, ts), ts[0])
    t0, span, s, ds0 = unit_time(ts, dt0)
    controller = controller_in_unit_time(controller, t0, span)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(Guarded(model, t0, span)),
        solver,
        t0=0.0,  # constants, not arrays (`unit_time`)
        t1=1.0,
        dt0=ds0,
        y0=y0_run,
        args=ok0,
        saveat=diffrax.SaveAt(ts=s),
        stepsize_controller=controller,
        adjoint=adjoint,
        max_steps=max_steps,
        throw=False,
    )
    counts = [sol.stats[k] for k in ("num_steps", "num_accepted_steps", "num_rejected_steps")]
    return finish(model, ts, sol.ys, ok0, sol.result, counts)


def solve_vmapped(
    model, y0s, ts, solver, controller, adjoint, max_steps, dt0, model_axes
) -> Trajectory:
    """`solve` vmapped over `y0s` and, along `model_axes`, over the model."""

    def one(m, y0):
        return solve(m, y0, ts, solver, controller, adjoint, max_steps, dt0)

    return eqx.filter_vmap(one, in_axes=(array_axes(model_axes), 0))(model, y0s)
