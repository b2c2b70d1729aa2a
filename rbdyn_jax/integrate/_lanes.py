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

import abc
import dataclasses
import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, PyTree

from .. import _compat
from ..models import AbstractRigidBody
from ._field import (
    Guarded,
    controller_in_unit_time,
    per_unit_time,
    start,
    unit_time,
    where_tree,
)
from ._solution import RESULTS, result_code


class AbstractLaneSystem(eqx.Module):
    """What the lane loop integrates: a rigid-body `model`'s state, possibly extended (by
    its sensitivities, say). The loop's start checks, step-size controller and ordering
    see the model's own state alone (`primal`), so the steps are those of the model's own
    solve."""

    model: eqx.AbstractVar[AbstractRigidBody]

    @abc.abstractmethod
    def vector_field(self, t, y, args):
        """The rate of the whole (extended) state."""

    @abc.abstractmethod
    def primal(self, y):
        """The model's own state within the state `y`."""

    @abc.abstractmethod
    def extend(self, ok, y, f, y0, t):
        """The state integrated and its rate at the start `t`, from the model's checked
        start `y` (finite where `ok`), its rate `f` and the given initial state `y0`."""


class Plain(AbstractLaneSystem):
    """The model's own trajectories."""

    model: AbstractRigidBody

    def vector_field(self, t, y, args):
        return self.model.vector_field(t, y, args)

    def primal(self, y):
        return y

    def extend(self, ok, y, f, y0, t):
        return y, f


class LaneField(eqx.Module):
    """The vector field of `lanes` trajectories as one batched state (the lane axis last on
    every leaf), each lane with its own unit time `s` (`unit_time`) and `ok` flag. diffrax's
    solver step then runs on whole `(…, lanes)` arrays: its stage loop combines contiguous
    blocks instead of a vmapped loop of tiny ones (bitwise the same arithmetic), and each
    component of the state is a contiguous row of lanes, which XLA vectorises across lanes
    (with the lanes first, a component is a strided column). `system` carries a lane axis
    last when `batched`."""

    system: AbstractLaneSystem
    batched: bool = eqx.field(static=True)
    t0: Array
    span: Array

    def __call__(self, s, y, ok):  # `Guarded` per lane: the vmapped path's arithmetic
        axis = -1 if self.batched else None
        return eqx.filter_vmap(
            lambda m, s, x, ok: Guarded(m, self.t0, self.span)(s, x, ok),
            in_axes=(axis, 0, -1, 0),
            out_axes=-1,
        )(self.system, s, y, ok)


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


def lane_select(mask, new, old):
    """Per-lane `where` on pytrees whose lane axis is the last."""
    return jax.tree_util.tree_map(
        lambda a, b: jnp.where(jnp.broadcast_to(mask, b.shape), a, b), new, old
    )


def first_select(mask, new, old):
    """Per-lane `where` on pytrees whose lane axis is the first."""
    return jax.tree_util.tree_map(
        lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (b.ndim - 1)), a, b), new, old
    )


def clip_floor(dtype) -> np.floating:
    """diffeqsolve's end-of-interval threshold (a step ending above it ends at t1) for the
    unit time's t1 = 1 (`unit_time`): 1 moved down by 100 floats, as its 100 calls of
    equinox's `prevbefore` move t1, i.e. 1 − 100·ε⁻ (ε⁻ the spacing of the floats just
    below 1; exact in the dtype). A NumPy constant."""
    dtype = np.dtype(dtype)
    return dtype.type(1) - dtype.type(100) * np.finfo(dtype).epsneg


def take(tree, i):
    return jax.tree_util.tree_map(lambda x: x[i], tree)


def take_last(tree, i):
    return jax.tree_util.tree_map(lambda x: x[..., i], tree)


def lanes_last(tree):
    """A table of trajectories, `(N, …)` on every leaf, as `(…, N)`."""
    return jax.tree_util.tree_map(lambda x: jnp.moveaxis(x, 0, -1), tree)


def lanes_first(tree):
    """`(…, L)` on every leaf as `(L, …)`."""
    return jax.tree_util.tree_map(lambda x: jnp.moveaxis(x, -1, 0), tree)


LAYOUTS = ("cpu", "array")


def scatter_rows(buf, index, vals, write):
    """`buf` with `vals[l]` written at `buf[index[0][l], index[1][l], …]` for each lane l
    where `write[l]`: one scatter. A lane that writes nothing aims past the buffer's end,
    at a row of its own, which the scatter drops; the indices are then unique, and XLA
    writes without atomics."""
    lane = jnp.arange(vals.shape[0], dtype=jnp.int32)
    rows = jnp.where(write, index[0].astype(jnp.int32), buf.shape[0] + lane)
    idx = (rows, *(i.astype(jnp.int32) for i in index[1:]))
    return buf.at[idx].set(vals, mode="drop", unique_indices=True)


def write_rows(buf, index, vals):
    """`buf` with `vals[l]` written at `buf[index[0][l], index[1][l], …]` for each lane l,
    in turn (a loop of `dynamic_update_slice`s, not a scatter: XLA:CPU compiles a while
    loop holding a scatter as a sequence of kernels its runtime dispatches one by one at
    every iteration, and one without as a single function, `_program.flags.LOOP_OPTION`)."""

    def one(l, buf):
        start = tuple(i[l].astype(jnp.int32) for i in index)
        start += (jnp.zeros((), jnp.int32),) * (buf.ndim - len(index))
        v = vals[l]
        return jax.lax.dynamic_update_slice(buf, v.reshape((1,) * len(index) + v.shape), start)

    return jax.lax.fori_loop(0, vals.shape[0], one, buf)


def unrolled_step(solver, term, t0, t1, y0, args, f0):
    """One step of the explicit Runge–Kutta `solver` from `y0` at `t0` to `t1`, its stages
    unrolled from its Butcher tableau; `(y1, y_error, dense, f1)` as `solver.step` gives
    them (`f1` the FSAL stage, or `None`). `f0` is f(t0, y0) for an FSAL method.

    The arithmetic of diffrax's step (`diffrax.AbstractRungeKutta`): the increments
    kᵢ = f(tᵢ, yᵢ)·Δt with yᵢ = y0 + Σⱼ aᵢⱼ kⱼ and tᵢ = t0 + cᵢΔt (t1 where cᵢ = 1),
    y1 = y0 + Σ bⱼ kⱼ (the last stage's yᵢ for a method whose last stage is its solution),
    y_error = Σ eⱼ kⱼ, and the dense output `{y0, y1, k}` its interpolant reads. diffrax
    runs the stages as a loop over a buffer, each a dot with a row of the tableau padded
    by zeros; here each stage is a fixed sum over the stages before it, so the two round
    differently in the last bits."""
    tab = solver.tableau
    control = term.contr(t0, t1)
    dt = t1 - t0
    c = (tab.c1, *(float(x) for x in tab.c))

    def combine(out, weights, ks):  # out + Σ wⱼ kⱼ over the nonzero weights
        for w, k in zip(weights, ks):
            if w != 0:
                out = jax.tree_util.tree_map(lambda o, x, w=float(w): o + w * x, out, k)
        return out

    ks = []
    fi = None
    y_stage = y0
    for i in range(tab.num_stages):
        if i == 0 and tab.fsal:
            fi = f0
        else:
            y_stage = y0 if i == 0 else combine(y0, tab.a_lower[i - 1], ks)
            ti = t1 if c[i] == 1 else t0 + c[i] * dt
            fi = term.vf(ti, y_stage, args)
        ks.append(term.prod(fi, control))
    y1 = y_stage if tab.ssal else combine(y0, tab.b_sol, ks)
    y_error = combine(jax.tree_util.tree_map(jnp.zeros_like, y0), tab.b_error, ks)
    k = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *ks)
    return y1, y_error, dict(y0=y0, y1=y1, k=k), fi if tab.fsal else None


def guarded_term(model, t0, span):
    return _compat.wrapped_term(diffrax.ODETerm(Guarded(model, t0, span)))


def _interpolate(solver, tprev, tnext, dense, t):
    """The solver's interpolant of each lane's last step at the unit time `t`.

    diffrax's Runge–Kutta interpolants are linear in the step's dense information (y0, y1
    and the stage increments k), with weights depending on θ = (t − t0)/(t1 − t0) only.
    The weights come from the solver's own interpolant evaluated on unit vectors (one row
    per lane: a plain matrix product); the lanes' states are then combined elementwise,
    where the interpolant vmapped over lanes would make one tiny batched dot per lane."""
    dt = tnext - tprev
    theta = jnp.where(dt > 0, (t - tprev) / jnp.where(dt > 0, dt, 1.0), 0.0)
    keys = sorted(k for k in dense if k != "k")
    stages = jax.tree_util.tree_leaves(dense["k"])[0].shape[0]
    eye = jnp.eye(len(keys) + stages, dtype=theta.dtype)
    probe = dict(zip(keys, eye), k=eye[len(keys) :])
    zero, one = jnp.zeros((), theta.dtype), jnp.ones((), theta.dtype)
    w = jax.vmap(lambda th: solver.interpolation_cls(t0=zero, t1=one, **probe).evaluate(th))(
        theta
    ).T  # (keys + stages, lanes)

    def combine(*leaves):  # unrolled: XLA:CPU's reductions over a few rows are slow
        *ys, k = leaves
        terms = [(w[i], y) for i, y in enumerate(ys)]
        terms += [(w[len(keys) + j], k[j]) for j in range(stages)]
        out = None
        for wi, x in terms:
            term = jnp.broadcast_to(wi, x.shape) * x  # the lane axis last
            out = term if out is None else out + term
        return out

    return jax.tree_util.tree_map(combine, *[dense[k] for k in keys], dense["k"])


def lane_first(m: AbstractLaneSystem, y0, *, controller, solver, start_time, span, dt0):
    """One trajectory's start in the unit time (`unit_time`): its `ok` flag, the state
    integrated, the first step's end, the FSAL stage f(t0, y0) in the unit time (`None`
    for a method without one), the controller's state, and how long the trajectory will
    take (|f(t0, y0)| in the controller's tolerance scale; −1 for a bad start, which goes
    first only where the rate overflowed)."""
    t0, t1 = jnp.zeros((), span.dtype), jnp.ones((), span.dtype)
    ok, y, f = start(m.model, m.primal(y0), start_time)  # f at y: the stand-in if not ok
    y_run, f_run = m.extend(ok, y, f, y0, start_time)
    term = guarded_term(m.model, start_time, span)
    tnext, cstate = controller.init(term, t0, t1, y, dt0, ok, solver.func, solver.error_order(term))
    tnext = jnp.minimum(tnext, t1)
    # An FSAL step starts from f(t0, y0), the last stage of the step before: give it
    # now, so that a refilled lane needs no extra evaluation of the field. (Another
    # method evaluates its first stage in the step.)
    sstate = per_unit_time(span, where_tree(ok, f_run, 0.0)) if solver.tableau.fsal else None
    # How long the trajectory will take: |f(t0, y0)| in the controller's tolerance
    # scale. An ordering only: no tangents through it.
    f, y_ = jax.lax.stop_gradient((f, y))
    d = sum(
        jnp.sum((a / (controller.atol + controller.rtol * jnp.abs(b))) ** 2)
        for a, b in zip(jax.tree_util.tree_leaves(f), jax.tree_util.tree_leaves(y_))
    )
    d = jnp.where(ok & ~jnp.isnan(d), d, -1.0)  # an overflow to inf goes first
    return ok, y_run, tnext, sstate, jax.tree_util.tree_map(jnp.asarray, cstate), d


def lane_control(controller, error_order, t1_floor, tprev, tnext, y, y1, y_error, cstate):
    """diffrax's step-size `controller` on one trajectory's step in the unit time: whether
    the step is kept, the next step's start and end (clipped to t1 = 1 as diffeqsolve clips
    them, `clip_floor`), the controller's state and the `RESULTS` code. A NaN error
    estimate counts as an infinite one (the step is rejected)."""
    t1 = jnp.ones((), t1_floor.dtype)
    y_error = jax.tree_util.tree_map(lambda x: jnp.where(jnp.isnan(x), jnp.inf, x), y_error)
    keep, tp, tn, _, cstate, result = controller.adapt_step_size(
        tprev, tnext, y, y1, None, y_error, error_order, cstate
    )
    tp = jnp.minimum(tp, t1)
    tn = jnp.where(tn > t1_floor, jnp.where(keep, t1, tp + 0.5 * (t1 - tp)), tn)
    cstate = jax.tree_util.tree_map(jnp.asarray, cstate)
    return keep, tp, tn, cstate, result_code(result)


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
    axis = 0 if batched else None
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
        lanes_now = (
            c.idx,
            c.tprev,
            c.tnext,
            c.y,
            c.solver_state,
            c.controller_state,
            c.ok,
            c.model,
            save,
            c.counts,
            c.result,
            c.out_counts,
            c.out_result,
            c.next,
        )

        def refill(lanes_now):
            (
                idx,
                tprev,
                tnext,
                y,
                sstate,
                cstate,
                ok,
                m,
                save,
                counts,
                result,
                out_counts,
                out_result,
                nxt,
            ) = lanes_now
            out_counts = write(out_counts, (current,), counts.T, done)
            out_result = write(out_result, (current,), result, done)
            new = nxt + jnp.cumsum(done, dtype=jnp.int32) - 1
            nxt = nxt + jnp.sum(done, dtype=jnp.int32)
            pick = order[jnp.minimum(new, N - 1)]
            idx = jnp.where(done, jnp.where(new < N, new, N), idx)
            tprev = jnp.where(done, t0, tprev)
            tnext = jnp.where(done, tnext0[pick], tnext)
            y = lane_select(done, take_last(y0r, pick), y)
            sstate = lane_select(done, take_last(sstate0, pick), sstate)
            cstate = first_select(done, take(cstate0, pick), cstate)
            ok = jnp.where(done, ok0[pick], ok)
            m = lane_select(done, take_last(lane_dyn, pick), m) if batched else None
            save = jnp.where(done, 0, save)
            counts = jnp.where(done, 0, counts)
            result = jnp.where(done, 0, result)
            return (
                idx,
                tprev,
                tnext,
                y,
                sstate,
                cstate,
                ok,
                m,
                save,
                counts,
                result,
                out_counts,
                out_result,
                nxt,
            )

        if array:  # a branch would wait for the host: refill, selecting per lane
            refilled = refill(lanes_now)
        else:  # skipped at the iterations where no lane finished
            refilled = jax.lax.cond(jnp.any(done), refill, lambda x: x, lanes_now)
        (
            idx,
            tprev,
            tnext,
            y,
            sstate,
            cstate,
            ok,
            m,
            save,
            counts,
            result,
            out_counts,
            out_result,
            nxt,
        ) = refilled
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
            next=nxt,
            ys=ys,
            out_counts=out_counts,
            out_result=out_result,
        )

    c = jax.lax.while_loop(cond, body, state)
    return take(c.ys, slice(N)), ok0, c.out_result[:N], c.out_counts[:N]
