"""The Pallas kernel (`jax.experimental.pallas`) whose every program integrates a block of
trajectories from start to end: `kernel_run`.

A program holds its block's lanes in rows: each scalar of a trajectory's state (and of
its model's parameters, the controller's state) is a row of `block` lanes
(`_kernel_layout`). The lanes step in one `lax.while_loop` until each has reached the end
or failed, each with its own step size, accepted or rejected by diffrax's
`PIDController`. A step that reaches output times saves its lane's value at each of them
at once, by the solver's interpolant of that step, into the lane's column of the output:
the step's stages are not carried to the next step, which keeps the loop's state (and a
GPU thread's registers) to the trajectory's state, its last stage, the controller's
state and the step's ends. A lane steps exactly as `diffeqsolve` would.

The arithmetic per lane is the lane solver's (`_lane_step`): `unrolled_step` (the solver's
Butcher tableau, its stages unrolled), `lane_control` (diffrax's controller, the clip at
t1), `lane_first` (the start and first step), and the solver's own interpolant. Each runs
on rows by `_rows.rowwise`, which evaluates the function traced for one trajectory
operation by operation on rows, so a model's `vector_field` enters the kernel as written;
a model whose field has an operation with no form on rows is refused by name.

Trajectories are handed to blocks longest-first (as to the lane solver's lanes), so that
a block's lanes finish nearly together; the batch is padded to a multiple of the block by
repeating its last trajectory. The kernel's call is not differentiated
(`_undifferentiated`): a solve's derivative is `_kernel_solve.kernel_solve`'s rule.
"""

import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._field import controller_in_unit_time, unit_time
from ._kernel_layout import (
    _elements,
    _flat_rows,
    _packed,
    _select,
    _unflat_rows,
    _with_elements,
    next_power_of_two,
    read_rows,
    triton_warps,
    write_rows,
)
from ._lane_step import clip_floor, guarded_term, lane_control, lane_first, unrolled_step
from ._rows import objects, rowwise, trace, unsupported
from ._solution import RESULTS, result_code


def kernel_run(system, y0s, ts, controller, solver, max_steps, dt0, batched, block, interpret):
    """The kernel over the batch `y0s` of what `system` integrates (`_lane_system.
    AbstractLaneSystem`: the model, or the model and its sensitivities; a leading
    trajectory axis on its array leaves when `batched`): the raw saved states `(N, n, …)`
    (+inf where never saved), the start flags, result codes and step counts, in the
    batch's order, as `_lane_loop.lane_loop` gives them. The steps are the model's own: the
    controller sees the model's state alone (`system.primal`)."""
    from jax.experimental import pallas as pl  # imported with the first kernel solve
    from jax.experimental.pallas import triton as pltriton

    dyn, static = eqx.partition(system, eqx.is_array)
    N = jax.tree_util.tree_leaves(y0s)[0].shape[0]
    n = ts.shape[0]
    start_time, span, uts, dt0 = unit_time(ts, dt0)
    controller = controller_in_unit_time(controller, start_time, span)
    dtype = uts.dtype
    axis = eqx.if_array(0) if batched else None
    first = functools.partial(
        lane_first, controller=controller, solver=solver, start_time=start_time, span=span, dt0=dt0
    )
    ok0, y0r, tnext0, sstate0, cstate0, difficulty = eqx.filter_vmap(first, in_axes=(axis, 0))(
        system, y0s
    )

    # Longest first, padded to a multiple of the block by the last.
    order = jnp.argsort(-difficulty)
    P = -(-N // block) * block
    picks = jnp.concatenate([order, jnp.repeat(order[-1:], P - N)])

    def lanes(x):
        return x[picks]

    def shared(x):  # one value for every lane: rows of one element, read as scalars
        return jnp.asarray(x)[None]

    ctrl_dyn, cstatic = eqx.partition(controller, eqx.is_array)
    params = (
        jax.tree_util.tree_map(lanes if batched else shared, dyn),
        jax.tree_util.tree_map(shared, ctrl_dyn),
        shared(jnp.asarray(start_time, dtype)),
        shared(jnp.asarray(span, dtype)),
    )
    init = jax.tree_util.tree_map(lanes, (y0r, sstate0, cstate0, tnext0, ok0))
    in_rows, in_layout = _flat_rows((params, init))
    inputs, where = _packed(in_rows)
    n_in = len(inputs)
    error_order = solver.error_order(diffrax.ODETerm(lambda t, y, a: y))
    t1_floor = clip_floor(dtype)

    def step(params, tprev, tnext, y, ok, f0, cstate):
        m_dyn, c_dyn, t0_, span_ = params
        m = eqx.combine(m_dyn, static)
        ctrl = eqx.combine(c_dyn, cstatic)
        term = guarded_term(m, t0_, span_)
        y1, y_error, dense, f1 = unrolled_step(solver, term, tprev, tnext, y, ok, f0)
        keep, tp, tn, cs, code = lane_control(
            ctrl,
            error_order,
            jnp.asarray(t1_floor),
            tprev,
            tnext,
            m.primal(y),
            m.primal(y1),
            m.primal(y_error),
            cstate,
        )
        return y1, dense, f1, keep, tp, tn, cs, code

    def interpolate(tprev, tnext, dense, t):
        return solver.interpolation_cls(t0=tprev, t1=tnext, **dense).evaluate(t)

    # The refusal, before the kernel is traced: the per-lane functions' operations.
    example = _unflat_rows(in_layout, [jnp.zeros((), r.dtype) for r in in_rows])
    ex_params, (ex_y, ex_f, ex_c, ex_tn, ex_ok) = example
    dense_shape = jax.eval_shape(
        lambda *a: step(*a)[1],
        *jax.tree_util.tree_map(
            lambda x: jax.ShapeDtypeStruct(x.shape, x.flat[0].dtype),
            (ex_params, ex_tn, ex_tn, ex_y, ex_ok, ex_f, ex_c),
        ),
    )
    ex_dense = jax.tree_util.tree_map(
        lambda s: objects(s.shape, lambda idx: jnp.zeros((), s.dtype)), dense_shape
    )
    bad = set()
    for fn, args in (
        (step, (ex_params, ex_tn, ex_tn, ex_y, ex_ok, ex_f, ex_c)),
        (interpolate, (ex_tn, ex_tn, ex_dense, ex_tn)),
    ):
        bad |= unsupported(trace(fn, *args)[0].jaxpr)
    if bad:
        reason = (
            f"cannot run this model on rows of lanes: its vector field (or the "
            f"solver's step, controller or interpolant) uses {sorted(bad)}, which "
            "have no form on rows (write the field on vector components)"
        )
        raise ValueError(f"`Kernel` {reason}; `batching=Lanes()` or `Vmap()` takes it.")

    y_spec = [x.shape[1:] for x in jax.tree_util.tree_leaves(y0s)]
    # Each saved row in its state element's dtype (a float64 state with float32 times too)
    y_dtypes = [e.dtype for x in jax.tree_util.tree_leaves(ex_y) for e in x.flat]
    n_y = len(y_dtypes)
    y_groups = {}  # the saved components by dtype: one output of each
    for k, d in enumerate(y_dtypes):
        y_groups.setdefault(d, []).append(k)
    widths = [next_power_of_two(len(ks)) for ks in y_groups.values()]
    counted = ("steps", "accepted", "rejected", "result", "saved")
    n_counts = next_power_of_two(len(counted))
    # Rows of the output: the n times and a spare row n, where a lane with nothing to save
    # writes when others save (a store is of every lane).
    n_rows = next_power_of_two(n + 1)
    ts_pad = jnp.concatenate([uts, jnp.ones((n_rows - n,), dtype)])
    int_t = jnp.int32
    state_keys = ("tprev", "tnext", "ok", "steps", "accepted", "rejected", "result", "saved")

    def kernel(ts_ref, *refs):
        in_refs, ys_refs, counts_ref = refs[:n_in], refs[n_in:-1], refs[-1]
        rows = (block,)
        flat = [None] * len(in_rows)
        for ref, ks in zip(in_refs, where):
            parts = read_rows(ref, len(ks)) if len(ref.shape) == 2 else [ref[0]]
            for k, row in zip(ks, parts):
                flat[k] = jnp.broadcast_to(row, rows)
        params, (y, f, cstate, tnext, ok) = _unflat_rows(in_layout, flat)
        zero_f = jnp.zeros(rows, dtype)
        zero_i = jnp.zeros(rows, int_t)
        lane = jax.lax.broadcasted_iota(int_t, rows, 0)
        obj = functools.partial(objects, ())

        def full(x):
            return jnp.broadcast_to(x, rows)

        state = dict(
            tprev=zero_f,
            tnext=tnext[()],
            y=y,
            f=f,
            cstate=cstate,
            ok=ok[()],
            steps=zero_i,
            accepted=zero_i,
            rejected=zero_i,
            result=zero_i,
            saved=zero_i,  # the outputs saved so far: times 0 … saved − 1
        )
        # The loop carries plain arrays: every row, broadcast to the block.
        template = jax.tree_util.tree_map(
            lambda x: x if isinstance(x, np.ndarray) else obj(lambda idx: x), state
        )

        def pack(s):
            return [
                full(e)
                for e in _elements(
                    jax.tree_util.tree_map(
                        lambda x: x if isinstance(x, np.ndarray) else obj(lambda idx: x), s
                    )
                )
            ]

        def unpack(carry):
            s = _with_elements(template, carry)
            return {k: v[()] if k in state_keys else v for k, v in s.items()}

        def going(s):  # lanes that have not reached the end and can step
            return (s["tprev"] < 1) & (s["result"] == 0)

        def cond(carry):
            return jnp.max(going(unpack(carry)).astype(int_t)) > 0

        def body(carry):
            s = unpack(carry)
            go = going(s)
            y1, dense, f1, keep, tp, tn, cs, code = rowwise(
                step,
                params,
                obj(lambda idx: s["tprev"]),
                obj(lambda idx: s["tnext"]),
                s["y"],
                obj(lambda idx: s["ok"]),
                s["f"],
                s["cstate"],
            )
            keep, tp, tn, code = (full(x[()]) for x in (keep, tp, tn, code))
            accept = go & keep
            t0, t1 = s["tprev"], s["tnext"]

            # Every output time an accepted step reaches is saved now, by the step's
            # interpolant: its stages are not kept past the step.
            def due(saved):  # the lanes whose next output time this step reached
                t_out = ts_ref[jnp.minimum(saved, n - 1)]
                return saved, accept & (saved < n) & (t_out <= t1), t_out

            def save(carry):
                saved, now, t_out = carry
                vals = rowwise(
                    interpolate,
                    obj(lambda idx: t0),
                    obj(lambda idx: t1),
                    dense,
                    obj(lambda idx: t_out),
                )
                row = jnp.where(now, saved, n)
                comps = _elements(vals)
                for ref, ks, width in zip(ys_refs, y_groups.values(), widths):
                    write_rows(
                        ref,
                        [full(comps[k]).astype(ref.dtype) for k in ks],
                        lambda c, w=width: (row * w + c) * block + lane,
                    )
                return due(saved + now.astype(int_t))

            saved, _, _ = jax.lax.while_loop(
                lambda carry: jnp.max(carry[1].astype(int_t)) > 0, save, due(s["saved"])
            )
            s = dict(
                s,
                y=_select(accept, y1, s["y"]),
                f=_select(accept, f1, s["f"]),
                cstate=_select(go, cs, s["cstate"]),
                tprev=jnp.where(go, tp, t0),
                tnext=jnp.where(go, tn, t1),
                steps=s["steps"] + go.astype(int_t),
                accepted=s["accepted"] + accept.astype(int_t),
                rejected=s["rejected"] + (go & ~keep).astype(int_t),
                result=jnp.where(go, code, s["result"]),
                saved=saved,
            )
            maxed = go & (s["steps"] >= max_steps) & (s["tprev"] < 1) & (s["result"] == 0)
            s["result"] = jnp.where(maxed, result_code(RESULTS.max_steps_reached), s["result"])
            return pack(s)

        s = unpack(jax.lax.while_loop(cond, body, pack(state)))
        write_rows(counts_ref, [s[k] for k in counted], lambda c: c * block + lane)

    # A block's outputs are contiguous: time by time, component by component, each a row of
    # its lanes; then its counts, a row each.
    out_shape = [jax.ShapeDtypeStruct((P * n_rows * w,), d) for d, w in zip(y_groups, widths)] + [
        jax.ShapeDtypeStruct((P * n_counts,), int_t)
    ]
    out_specs = [pl.BlockSpec((n_rows * w * block,), lambda i: (i,)) for w in widths] + [
        pl.BlockSpec((n_counts * block,), lambda i: (i,))
    ]
    call = pl.pallas_call(
        kernel,
        out_shape=out_shape,
        grid=(P // block,),
        # The per-lane rows of a dtype: the block's columns of one 2-D array; a value every
        # lane shares: one element, read as a scalar.
        in_specs=[pl.BlockSpec((n_rows,), lambda i: (0,))]
        + [
            pl.BlockSpec((x.shape[0], block), lambda i: (0, i))
            if x.ndim == 2
            else pl.BlockSpec((1,), lambda i: (0,))
            for x in inputs
        ],
        out_specs=out_specs,
        interpret=interpret,
        name="rbdyn_kernel",
        # Triton's lowering, asked for by its parameters: JAX's default for a GPU is Mosaic
        # GPU (`jax_pallas_use_mosaic_gpu`), whose copies are of whole warpgroups.
        compiler_params=None
        if interpret
        else pltriton.CompilerParams(num_warps=triton_warps(block), num_stages=1),
    )
    outs = _undifferentiated(call)(ts_pad, *inputs)
    steps, accepted, rejected, result, saved = (
        outs[-1].reshape(P // block, n_counts, block).transpose(1, 0, 2).reshape(n_counts, P)
    )[: len(counted)]
    counts = [steps, accepted, rejected]
    # (n, P) rows; a time a lane never reached (its rows past `saved`, never written) is +inf.
    unreached = jnp.arange(n, dtype=int_t)[:, None] >= saved[None, :]
    ys_rows = [None] * n_y
    for out, ks, width in zip(outs[:-1], y_groups.values(), widths):
        x = out.reshape(P // block, n_rows, width, block)[:, :n].transpose(1, 2, 0, 3)
        for j, k in enumerate(ks):
            ys_rows[k] = jnp.where(unreached, jnp.inf, x[:, j].reshape(n, P)).astype(out.dtype)

    # Back to the batch's order: position p of the kernel holds trajectory order[p].
    back = jnp.argsort(order)
    leaves, at = [], 0
    for shape in y_spec:
        k = int(np.prod(shape, dtype=int))
        x = jnp.stack(ys_rows[at : at + k], axis=-1)[:n, :N]  # (n, N, k)
        at += k
        leaves.append(jnp.moveaxis(x, 1, 0)[back].reshape((N, n) + shape))
    ys = jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(y0s), leaves)
    counts = jnp.stack(counts, axis=-1)[:N][back].astype(int)
    return ys, ok0, result[:N][back], counts


def _undifferentiated(call):
    """`call`, refusing a derivative by name (`jax.grad`, `jax.jvp`, … through it) rather
    than differentiating the kernel's discrete program. A solve's derivative is
    `kernel_solve`'s rule, which calls the kernel undifferentiated; this refuses a
    derivative of that derivative."""

    @jax.custom_jvp
    def run(*args):
        return call(*args)

    def refused(primals, tangents):
        raise ValueError(
            "`Kernel` differentiates a solve once (forward sensitivities "
            "integrated in the kernel), not its derivative: take a second "
            "derivative through `batching=Lanes()` or `Vmap()`."
        )

    run.defjvp(refused)
    return run
