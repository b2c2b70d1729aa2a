"""The lane loop: a batch of trajectories flowing through a fixed number of lanes of one
while loop, each lane refilled with the next trajectory as soon as its own finishes.

A vmapped `diffeqsolve` runs every trajectory of a batch in lockstep until the slowest
finishes. Here each loop iteration (1) saves at most one output time per lane from the
lane's last step (diffrax's interpolant, as `SaveAt(ts=…)` does), (2) hands every finished
lane the next waiting trajectory, and (3) takes one diffrax solver step in every lane that
has no output left to save, with diffrax's step-size controller deciding acceptance and the
next step per lane. The steps, accepted/rejected decisions and saved values are those of
`diffeqsolve` for the same trajectory (tested), and no lane idles behind the slowest.

The loop has two layouts of the same iteration (`LAYOUTS`), chosen by the backend:

- `"cpu"`: tuned for XLA:CPU, whose compiled while loop runs the whole iteration as one
  function: outputs written by a loop of `dynamic_update_slice`s, the refill of finished
  lanes under a `lax.cond`, diffrax's own solver step (its loop over stages).
- `"array"`: for an accelerator, where every operation of the iteration is at least one
  kernel launch and every loop or branch a round trip to the host: outputs written by one
  scatter, the refill computed every iteration and selected, the Runge–Kutta stages
  unrolled from the solver's tableau (`unrolled_step`), so that an iteration is a fixed
  sequence of whole-array kernels whatever the lane count.

Both take the same steps and save the same values to round-off (tested).
"""

import dataclasses
import functools
from typing import Any, NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int, PyTree

from .. import _compat
from ._field import Guarded, controller_in_unit_time, unit_time
from ._lane_arrays import (
    _interpolate,
    first_select,
    lane_select,
    lanes_first,
    lanes_last,
    scatter_rows,
    take,
    take_last,
    write_rows,
)
from ._lane_step import clip_floor, lane_control, lane_first, unrolled_step
from ._lane_system import AbstractLaneSystem, LaneField
from ._solution import RESULTS, result_code

LAYOUTS = ("cpu", "array")


class LaneState(eqx.Module):
    """The lane loop's state. `L` lanes, `N` trajectories, `n` output times; times in the
    unit time s ∈ [0, 1] (`unit_time`). The lane axis is the last of `y`, `solver_state`,
    `model` and `dense` (`LaneField`), the first of the controller's state."""

    # Per lane:
    idx: Int[Array, " L"]  # the lane's trajectory, as a position in the hand-out order; N: idle
    tprev: Float[Array, " L"]  # start of the lane's next step
    tnext: Float[Array, " L"]  # end of the lane's next step
    y: PyTree  # the state at `tprev`
    solver_state: PyTree  # f(tprev, y) for an FSAL method (the next step's first stage); else None
    controller_state: PyTree  # the step-size controller's
    ok: Bool[Array, " L"]  # the trajectory's start was finite
    model: PyTree  # the lanes' model arrays, when every trajectory has its own; else None
    dense: PyTree  # the last accepted step's dense output (for the interpolant)
    dense_t: Float[Array, "2 L"]  # the last accepted step's interval
    pending: Bool[Array, " L"]  # an output time falls in the last accepted step
    save: Int[Array, " L"]  # the next output time's index
    counts: Int[Array, "3 L"]  # steps, accepted steps, rejected steps
    result: Int[Array, " L"]  # the `RESULTS` code so far
    # Shared:
    next: Int[Array, ""]  # the next position in the hand-out order
    ys: PyTree  # (N, n, …) the saved outputs; +inf where never saved
    out_counts: Int[Array, "N 3"]  # each trajectory's `counts`, once finished
    out_result: Int[Array, " N"]  # each trajectory's code, once finished


class _Lanes(NamedTuple):
    """What a refill replaces in the lanes that finished, and the reports it writes."""

    idx: Any
    tprev: Any
    tnext: Any
    y: Any
    sstate: Any
    cstate: Any
    ok: Any
    m: Any
    save: Any
    counts: Any
    result: Any
    out_counts: Any
    out_result: Any
    nxt: Any


def lane_loop(
    system: AbstractLaneSystem,
    y0s,
    ts,
    controller,
    *,
    solver,
    max_steps,
    dt0,
    batched,
    lanes,
    layout="cpu",
):
    """All trajectories of `y0s` through `lanes` lanes of one while loop (in the `layout`
    of `LAYOUTS`); the raw saved states (before `finish`), the start flags, result codes
    and step counts.

    Trajectories are handed out longest-first, by |f(t0, y0)| in the tolerance scale (the
    rate the state moves at, which sets the step count of these rotational problems), so
    the last ones are short and the lanes finish nearly together. `system` has a leading
    trajectory axis on every array leaf when `batched`.
    """
    if layout not in LAYOUTS:
        raise ValueError(f"`layout` must be one of {LAYOUTS}, got {layout!r}.")
    array = layout == "array"
    if solver.scan_kind is None:
        # Runge–Kutta stages in a plain while loop rather than diffrax's checkpointed one
        # (a custom VJP, which forward-mode autodiff cannot pass); the same arithmetic.
        solver = eqx.tree_at(lambda s: s.scan_kind, solver, "lax", is_leaf=lambda x: x is None)
    N = jax.tree_util.tree_leaves(y0s)[0].shape[0]
    L = min(lanes, N)
    n = ts.shape[0]
    start_time, span, ts, dt0 = unit_time(ts, dt0)
    controller = controller_in_unit_time(controller, start_time, span)
    t0, t1 = jnp.zeros((), ts.dtype), jnp.ones((), ts.dtype)
    t1_floor = jnp.asarray(clip_floor(ts.dtype))  # diffeqsolve's clip
    dyn, static = eqx.partition(system, eqx.is_array)
    axis = eqx.if_array(0) if batched else None
    first = functools.partial(
        lane_first, controller=controller, solver=solver, start_time=start_time, span=span, dt0=dt0
    )

    ok0, y0r, tnext0, sstate0, cstate0, difficulty = eqx.filter_vmap(first, in_axes=(axis, 0))(
        system, y0s
    )
    y0r, sstate0 = lanes_last((y0r, sstate0))
    lane_dyn = lanes_last(dyn) if batched else dyn
    order = jnp.argsort(-difficulty)  # longest first
    error_order = solver.error_order(diffrax.ODETerm(Guarded(system, start_time, span)))
    control = functools.partial(lane_control, controller, error_order, t1_floor)
    primal = system.primal

    def step(m, tprev, tnext, y, ok, f0):
        term = _compat.wrapped_term(diffrax.ODETerm(LaneField(m, batched, start_time, span)))
        # diffrax multiplies each lane's rows by its time step, `(L,)` against `(…, L)`:
        # NumPy's broadcasting, which a caller's `jax_numpy_rank_promotion="raise"` refuses.
        with jax.numpy_rank_promotion("allow"):
            if array:
                return unrolled_step(solver, term, tprev, tnext, y, ok, f0)
            y1, y_error, dense, sstate, _ = solver.step(
                term, tprev, tnext, y, ok, None if f0 is None else (jnp.array(False), f0), False
            )
        return y1, y_error, dense, None if sstate is None else sstate[1]

    def write(buf, index, vals, mask):  # only the lanes where `mask` write
        if array:
            return scatter_rows(buf, index, vals, mask)
        return write_rows(buf, (jnp.where(mask, index[0], N), *index[1:]), vals)

    lane = order[:L]
    m0 = take_last(lane_dyn, lane) if batched else None
    tprev0 = jnp.full(L, t0)
    y_lane, ss_lane, ok_lane = take_last(y0r, lane), take_last(sstate0, lane), ok0[lane]
    dense_struct = jax.eval_shape(
        lambda: step(
            eqx.combine(m0 if batched else dyn, static),
            tprev0,
            tnext0[lane],
            y_lane,
            ok_lane,
            ss_lane,
        )[2]
    )
    state = LaneState(
        idx=jnp.arange(L, dtype=jnp.int32),
        tprev=tprev0,
        tnext=tnext0[lane],
        y=y_lane,
        solver_state=ss_lane,
        controller_state=take(cstate0, lane),
        ok=ok_lane,
        model=m0,
        dense=jax.tree_util.tree_map(lambda x: jnp.zeros(x.shape, x.dtype), dense_struct),
        dense_t=jnp.zeros((2, L), ts.dtype),
        pending=jnp.zeros(L, bool),
        save=jnp.zeros(L, jnp.int32),
        counts=jnp.zeros((3, L), int),
        result=jnp.zeros(L, jnp.int32),
        next=jnp.asarray(L, jnp.int32),
        ys=jax.tree_util.tree_map(
            lambda x: jnp.full((N + 1, n) + x.shape[1:], jnp.inf, x.dtype), y0s
        ),
        out_counts=jnp.zeros((N + 1, 3), int),
        out_result=jnp.zeros(N + 1, jnp.int32),
    )
    # The state, the solver's state, the step's dense output and the saved values take a
    # batch axis (`jax.vmap`) from the model and the initial states (and tangents, for a
    # derivative of the sensitivities themselves), but the buffers start as constants and
    # some lane states from y0 alone. JAX finds which carries of a while loop take them by
    # a fixpoint that re-traces the whole body on each pass; tying those carries to the
    # inputs from the start (a select that always picks the initial value) makes it
    # converge in one pass.
    inputs = [
        x
        for x in jax.tree_util.tree_leaves((dyn, y0s, sstate0))
        if jnp.issubdtype(x.dtype, jnp.inexact)
    ]
    if inputs:
        anchor = sum(jnp.sum(x) for x in inputs)
        never = jnp.zeros((), bool)

        def tied(x):
            if not jnp.issubdtype(x.dtype, jnp.inexact):
                return x
            return jnp.where(never, anchor.astype(x.dtype), x)

        state = dataclasses.replace(
            state,
            **{
                k: jax.tree_util.tree_map(tied, getattr(state, k))
                for k in ("y", "solver_state", "dense", "ys")
            },
        )

    def cond(c: LaneState):
        return jnp.any(c.idx < N)

    def body(c: LaneState) -> LaneState:
        active = c.idx < N
        current = order[jnp.minimum(c.idx, N - 1)]  # each lane's row of the batch
        # (1) Save one output time from each lane's last step.
        s = jnp.minimum(c.save, n - 1)
        vals = lanes_first(_interpolate(solver, c.dense_t[0], c.dense_t[1], c.dense, ts[s]))
        ys = jax.tree_util.tree_map(lambda o, v: write(o, (current, s), v, c.pending), c.ys, vals)
        save = c.save + c.pending.astype(jnp.int32)
        s = jnp.minimum(save, n - 1)
        pending = c.pending & (save < n) & (ts[s] <= c.dense_t[1])
        # (2) Finished lanes report and take the next trajectory.
        done = active & ~pending & ((c.tprev >= t1) | (c.result != 0))
        lanes_now = _Lanes(
            idx=c.idx,
            tprev=c.tprev,
            tnext=c.tnext,
            y=c.y,
            sstate=c.solver_state,
            cstate=c.controller_state,
            ok=c.ok,
            m=c.model,
            save=save,
            counts=c.counts,
            result=c.result,
            out_counts=c.out_counts,
            out_result=c.out_result,
            nxt=c.next,
        )

        def refill(r: _Lanes) -> _Lanes:
            new = r.nxt + jnp.cumsum(done, dtype=jnp.int32) - 1
            pick = order[jnp.minimum(new, N - 1)]
            return r._replace(
                out_counts=write(r.out_counts, (current,), r.counts.T, done),
                out_result=write(r.out_result, (current,), r.result, done),
                nxt=r.nxt + jnp.sum(done, dtype=jnp.int32),
                idx=jnp.where(done, jnp.where(new < N, new, N), r.idx),
                tprev=jnp.where(done, t0, r.tprev),
                tnext=jnp.where(done, tnext0[pick], r.tnext),
                y=lane_select(done, take_last(y0r, pick), r.y),
                sstate=lane_select(done, take_last(sstate0, pick), r.sstate),
                cstate=first_select(done, take(cstate0, pick), r.cstate),
                ok=jnp.where(done, ok0[pick], r.ok),
                m=lane_select(done, take_last(lane_dyn, pick), r.m) if batched else None,
                save=jnp.where(done, 0, r.save),
                counts=jnp.where(done, 0, r.counts),
                result=jnp.where(done, 0, r.result),
            )

        if array:  # a branch would wait for the host: refill, selecting per lane
            r = refill(lanes_now)
        else:  # skipped at the iterations where no lane finished
            r = jax.lax.cond(jnp.any(done), refill, lambda x: x, lanes_now)
        idx, tprev, tnext, y, ok, m = r.idx, r.tprev, r.tnext, r.y, r.ok, r.m
        sstate, cstate, save, counts, result = r.sstate, r.cstate, r.save, r.counts, r.result
        # (3) One solver step in every lane with nothing left to save.
        go = (idx < N) & ~pending & (tprev < t1) & (result == 0)
        y1, y_error, dense, ss1 = step(
            eqx.combine(m if batched else dyn, static), tprev, tnext, y, ok, sstate
        )
        keep, tp, tn, cs1, step_result = jax.vmap(control, in_axes=(0, 0, -1, -1, -1, 0))(
            tprev, tnext, primal(y), primal(y1), primal(y_error), cstate
        )
        accept = go & keep
        y = lane_select(accept, y1, y)
        sstate = lane_select(accept, ss1, sstate)
        cstate = first_select(go, cs1, cstate)
        dense = lane_select(accept, dense, c.dense)
        dense_t = jnp.where(accept, jnp.stack([tprev, tnext]), c.dense_t)
        tprev = jnp.where(go, tp, tprev)
        tnext = jnp.where(go, tn, tnext)
        counts = counts + jnp.stack([go, accept, go & ~keep]).astype(int)
        result = jnp.where(go, step_result, result)
        maxed = go & (counts[0] >= max_steps) & (tprev < t1) & (result == 0)
        result = jnp.where(maxed, result_code(RESULTS.max_steps_reached), result)
        s = jnp.minimum(save, n - 1)
        pending = pending | (accept & (save < n) & (ts[s] <= dense_t[1]))
        return LaneState(
            idx=idx,
            tprev=tprev,
            tnext=tnext,
            y=y,
            solver_state=sstate,
            controller_state=cstate,
            ok=ok,
            model=m,
            dense=dense,
            dense_t=dense_t,
            pending=pending,
            save=save,
            counts=counts,
            result=result,
            next=r.nxt,
            ys=ys,
            out_counts=r.out_counts,
            out_result=r.out_result,
        )

    c = jax.lax.while_loop(cond, body, state)
    return take(c.ys, slice(N)), ok0, c.out_result[:N], c.out_counts[:N]
