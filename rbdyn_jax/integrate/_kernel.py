"""The kernel strategy: one Pallas kernel (`jax.experimental.pallas`) whose every program
integrates a block of trajectories from start to end.

A program holds its block's lanes in rows: each scalar of a trajectory's state (and of
its model's parameters, the controller's state, the last step's dense output) is a row of
`block` lanes. For each output time in turn, the lanes that have not reached it step
(`lax.while_loop` until none needs to: each lane's own step size, accepted or rejected by
diffrax's `PIDController`), and then every lane saves its value there by the solver's
interpolant of its last accepted step: one row of the output a component. A lane steps
exactly as `diffeqsolve` would; waiting at an output time for the block's slowest lane
changes none of its steps.

The arithmetic per lane is the lane solver's (`_lane_step`): `unrolled_step` (the solver's
Butcher tableau, its stages unrolled), `lane_control` (diffrax's controller, the clip at
t1), `lane_first` (the start and first step), and the solver's own interpolant. Each runs
on rows by `_rows.rowwise`, which evaluates the function traced for one trajectory
operation by operation on rows, so a model's `vector_field` enters the kernel as written;
a model whose field has an operation with no form on rows is refused by name.

Trajectories are handed to blocks longest-first (as to the lane solver's lanes), so that
a block's lanes finish nearly together; the batch is padded to a multiple of the block by
repeating its last trajectory.
"""

import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._program.program import Program
from .._program.xla import COMPILER_OPTIONS
from ._field import (
    checked_before_tracing,
    checked_times,
    controller_in_unit_time,
    finish,
    promoted,
    unit_time,
)
from ._lane_step import clip_floor, guarded_term, lane_control, lane_first, unrolled_step
from ._lane_system import Plain
from ._rows import objects, rowwise, trace, unsupported
from ._sensitivity import lane_jvp
from ._solution import RESULTS, Trajectory, as_result, result_code

# The block on a GPU: 128 lanes a program (a Pallas kernel of this form solved 5.6 M
# trajectories/s on an H100 with blocks of 128; other widths are untuned); elsewhere
# (interpret mode, where a program's cost hardly depends on its width) the whole batch in
# one program, up to `MAX_INTERPRET_BLOCK` lanes.
GPU_BLOCK, MAX_INTERPRET_BLOCK = 128, 1024
TRITON_WARPS = 4  # 128 threads: a lane a thread at the GPU block


def next_power_of_two(n: int) -> int:
    return 1 << max(0, int(n) - 1).bit_length()


def kernel_refuse(model, solver, controller, adjoint) -> str | None:
    """Why `Kernel` cannot run this solve's solver, controller or adjoint, or `None`: it
    needs an explicit Runge–Kutta solver, a `PIDController` and no adjoint. (Whether the
    model's field runs on rows of lanes is `field_refuse`'s question.)"""
    if not isinstance(solver, diffrax.AbstractERK):
        return (
            "needs an explicit Runge–Kutta solver (a `diffrax.AbstractERK`: Tsit5, "
            f"Dopri5, Dopri8, Bosh3, …), got {type(solver).__name__}"
        )
    if not isinstance(controller, diffrax.PIDController):
        return f"needs a `diffrax.PIDController`, got {type(controller).__name__}"
    if adjoint is not None:
        return f"takes no `adjoint`, got {type(adjoint).__name__}"
    return None


def field_refuse(model, y0s, model_axes) -> str | None:
    """Why the kernel cannot evaluate `model`'s vector field on rows of lanes (the
    operations it cannot run, by name), or `None`. Traces the field for one trajectory
    from the shapes of `model` (mapped by `model_axes`) and `y0s` (a leading batch axis);
    the verdict is kept for the next call with the same structure, static values, shapes
    and dtypes (the default's choice on a GPU then costs no trace per call)."""
    key = _signature(model, y0s, model_axes)
    try:
        verdict = _VERDICTS.get(key, _MISSING) if key is not None else _MISSING
    except (TypeError, ValueError):  # a static value that cannot be compared (an array)
        key, verdict = None, _MISSING
    if verdict is _MISSING:
        verdict = _field_refuse(model, y0s, model_axes)
        if key is not None:
            _VERDICTS[key] = verdict
            while len(_VERDICTS) > 256:  # the oldest first
                del _VERDICTS[next(iter(_VERDICTS))]
    return verdict


_VERDICTS: dict = {}
_MISSING = object()


def _signature(model, y0s, model_axes):
    """What `field_refuse`'s verdict depends on: the pytrees' structure (static fields
    included), each array's shape and dtype and each other leaf's value; `None` where a
    value is unhashable."""
    leaves, tree = jax.tree_util.tree_flatten((model, y0s, model_axes))
    key = (
        tree,
        tuple((type(x), x.shape, x.dtype) if hasattr(x, "dtype") else (type(x), x) for x in leaves),
    )
    try:
        hash(key)
    except (TypeError, ValueError):
        return None
    return key


def _field_refuse(model, y0s, model_axes) -> str | None:
    def one(x):
        return jax.ShapeDtypeStruct(x.shape[1:], x.dtype)

    if model_axes is not None:
        model = eqx.filter_eval_shape(
            lambda m: eqx.filter_vmap(lambda x: x, in_axes=(model_axes,))(m), model
        )
        model = jax.tree_util.tree_map(one, model)
    dyn, static = eqx.partition(
        model, lambda x: eqx.is_array(x) or isinstance(x, jax.ShapeDtypeStruct)
    )
    dyn = jax.tree_util.tree_map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), dyn)
    y = jax.tree_util.tree_map(one, y0s)
    t = jax.ShapeDtypeStruct((), jax.tree_util.tree_leaves(y)[0].dtype)
    closed, _ = trace(lambda d, t, y: eqx.combine(d, static).vector_field(t, y, None), dyn, t, y)
    bad = unsupported(closed.jaxpr)
    if not bad:
        return None
    return (
        f"cannot run this model on rows of lanes: its vector field uses {sorted(bad)}, "
        "which have no form on rows (write the field on vector components)"
    )


def kernel_block(block, n: int, gpu: bool) -> int:
    """The block `Kernel(block)` takes for `n` trajectories: `block`, or 128 on a GPU,
    else the batch to the next power of two, at most 1024."""
    if block is not None:
        return int(block)
    return GPU_BLOCK if gpu else min(next_power_of_two(n), MAX_INTERPRET_BLOCK)


def _flat_rows(tree):
    """The leaves of `tree` (a leading trajectory axis on each) as rows `(N,)`, and how to
    rebuild them (`_unflat_rows`)."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    rows, spec = [], []
    for x in leaves:
        shape = x.shape[1:]
        spec.append((shape, x.dtype))
        flat = x.reshape(x.shape[:1] + (-1,))
        if flat.dtype == jnp.bool_:
            flat = flat.astype(jnp.int32)
        rows += [flat[:, i] for i in range(flat.shape[1])]
    return rows, (treedef, spec)


def _unflat_rows(layout, rows):
    """`_flat_rows`'s pytree back, each leaf an object array of rows (`_rows`)."""
    treedef, spec = layout
    leaves, at = [], 0
    for shape, dtype in spec:
        k = int(np.prod(shape, dtype=int))
        chunk = rows[at : at + k]
        at += k
        if dtype == jnp.bool_:
            chunk = [r != 0 for r in chunk]
        leaves.append(
            objects(
                shape,
                lambda idx, c=chunk, s=shape: c[int(np.ravel_multi_index(idx, s)) if s else 0],
            )
        )
    return jax.tree_util.tree_unflatten(treedef, leaves)


def _elements(tree):
    """Every row of a pytree of object arrays, in order."""
    return [e for x in jax.tree_util.tree_leaves(tree) for e in x.flat]


def _with_elements(tree, rows):
    """`tree` (of object arrays) with its rows replaced by `rows`, in order."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    it = iter(rows)
    return jax.tree_util.tree_unflatten(
        treedef, [objects(x.shape, lambda idx: next(it)) for x in leaves]
    )


def _select(mask, new, old):
    """Per lane `where` on pytrees of object arrays of rows."""
    return _with_elements(
        old, [jnp.where(mask, a, b) for a, b in zip(_elements(new), _elements(old))]
    )


def kernel_solve(
    model, y0s, ts, solver, controller, max_steps, dt0, model_axes, block, interpret
) -> Trajectory:
    """The kernel (`Kernel`) over the batch, and its `Trajectory`s.

    Differentiable in both modes by forward sensitivities, by the lane solver's rule
    (`_sensitivity.lane_jvp`, see `_batching.lane_solve`): the kernel integrates the model
    extended by the variational equations (`_sensitivity.Sensitivity`, whose field is one
    `jax.jvp` of the model's, run on rows as the field is) by the same steps, for the
    state leaves the caller reads only, and the rule contracts them with the tangents. A
    derivative of that derivative is refused."""
    ts = checked_times(ts)
    batched = model_axes is not None
    if batched:  # every array leaf with a leading trajectory axis
        model = eqx.filter_vmap(lambda m: m, in_axes=(model_axes,))(model)
    dyn, static = eqx.partition(model, eqx.is_array)
    y0s = promoted(dyn, y0s, ts)
    tols, cstatic = eqx.partition(controller, eqx.is_array)

    def loop(system, y0s, ts, tols):
        return kernel_run(
            system,
            y0s,
            ts,
            eqx.combine(tols, cstatic),
            solver,
            max_steps,
            dt0,
            batched,
            block,
            interpret,
        )

    @jax.custom_jvp
    def solve(dyn, y0s, ts, tols):
        return loop(Plain(eqx.combine(dyn, static)), y0s, ts, tols)

    solve.defjvp(functools.partial(lane_jvp, loop, static, batched), symbolic_zeros=True)
    ys, ok0, result, counts = solve(dyn, y0s, ts, tols)

    def finished(m, ys, ok, result, counts):
        return finish(m, ts, ys, ok, as_result(result), list(counts))

    return eqx.filter_vmap(finished, in_axes=(0 if batched else None, 0, 0, 0, 0))(
        model, ys, ok0, result, counts
    )


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
    axis = 0 if batched else None
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

    def shared(x):
        return jnp.broadcast_to(x, (P,) + jnp.shape(x))

    ctrl_dyn, cstatic = eqx.partition(controller, eqx.is_array)
    params = (
        jax.tree_util.tree_map(lanes if batched else shared, dyn),
        jax.tree_util.tree_map(shared, ctrl_dyn),
        shared(jnp.asarray(start_time, dtype)),
        shared(jnp.asarray(span, dtype)),
    )
    init = jax.tree_util.tree_map(lanes, (y0r, sstate0, cstate0, tnext0, ok0))
    in_rows, in_layout = _flat_rows((params, init))
    n_in = len(in_rows)
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
    n_pad = next_power_of_two(n)
    ts_pad = jnp.concatenate([uts, jnp.ones((n_pad - n,), dtype)])
    int_t = jnp.int32

    def kernel(ts_ref, *refs):
        in_refs, out_refs = refs[:n_in], refs[n_in:]
        ys_refs, counts_refs, result_ref = (
            out_refs[:n_y],
            out_refs[n_y : n_y + 3],
            out_refs[n_y + 3],
        )
        params, (y, f, cstate, tnext, ok) = _unflat_rows(in_layout, [r[...] for r in in_refs])
        rows = (block,)
        zero_f = jnp.zeros(rows, dtype)
        zero_i = jnp.zeros(rows, int_t)

        def full(x):
            return jnp.broadcast_to(x, rows)

        dense = jax.tree_util.tree_map(
            lambda d: objects(d.shape, lambda idx: full(jnp.zeros((), d.dtype))), dense_shape
        )
        state = dict(
            tprev=zero_f,
            tnext=tnext[()],
            y=y,
            f=f,
            cstate=cstate,
            ok=ok[()],
            dense=dense,
            dt0=zero_f - 2,
            dt1=zero_f - 1,
            steps=zero_i,
            accepted=zero_i,
            rejected=zero_i,
            result=zero_i,
        )
        # The loops carry plain arrays: every row, broadcast to the block.
        template = jax.tree_util.tree_map(
            lambda x: x if isinstance(x, np.ndarray) else objects((), lambda idx: x), state
        )

        def pack(s):
            return [
                full(e)
                for e in _elements(
                    jax.tree_util.tree_map(
                        lambda x: x if isinstance(x, np.ndarray) else objects((), lambda idx: x), s
                    )
                )
            ]

        def unpack(carry):
            s = _with_elements(template, carry)
            return {
                k: (
                    v[()]
                    if k
                    in (
                        "tprev",
                        "tnext",
                        "ok",
                        "dt0",
                        "dt1",
                        "steps",
                        "accepted",
                        "rejected",
                        "result",
                    )
                    else v
                )
                for k, v in s.items()
            }

        def output(i, carry):
            t_i = ts_ref[i]

            def wanted(s):  # lanes that have not reached t_i and can step
                return (s["dt1"] < t_i) & (s["tprev"] < 1) & (s["result"] == 0)

            def cond(carry):
                return jnp.max(wanted(unpack(carry)).astype(int_t)) > 0

            def body(carry):
                s = unpack(carry)
                go = wanted(s)
                obj = functools.partial(objects, ())
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
                s = dict(
                    s,
                    y=_select(accept, y1, s["y"]),
                    f=_select(accept, f1, s["f"]),
                    cstate=_select(go, cs, s["cstate"]),
                    dense=_select(accept, dense, s["dense"]),
                    dt0=jnp.where(accept, s["tprev"], s["dt0"]),
                    dt1=jnp.where(accept, s["tnext"], s["dt1"]),
                    tprev=jnp.where(go, tp, s["tprev"]),
                    tnext=jnp.where(go, tn, s["tnext"]),
                    steps=s["steps"] + go.astype(int_t),
                    accepted=s["accepted"] + accept.astype(int_t),
                    rejected=s["rejected"] + (go & ~keep).astype(int_t),
                    result=jnp.where(go, code, s["result"]),
                )
                maxed = go & (s["steps"] >= max_steps) & (s["tprev"] < 1) & (s["result"] == 0)
                s["result"] = jnp.where(maxed, result_code(RESULTS.max_steps_reached), s["result"])
                return pack(s)

            s = unpack(jax.lax.while_loop(cond, body, carry))
            obj = functools.partial(objects, ())
            vals = rowwise(
                interpolate,
                obj(lambda idx: s["dt0"]),
                obj(lambda idx: s["dt1"]),
                s["dense"],
                obj(lambda idx: full(t_i)),
            )
            reached = s["dt1"] >= t_i
            for ref, v in zip(ys_refs, _elements(vals)):
                ref[i, :] = jnp.where(reached, full(v), jnp.inf).astype(ref.dtype)
            return pack(s)

        s = unpack(jax.lax.fori_loop(0, n, output, pack(state)))
        for ref, k in zip(counts_refs, ("steps", "accepted", "rejected")):
            ref[...] = s[k]
        result_ref[...] = s["result"]

    row_spec = pl.BlockSpec((block,), lambda i: (i,))
    out_shape = [jax.ShapeDtypeStruct((n_pad, P), d) for d in y_dtypes] + [
        jax.ShapeDtypeStruct((P,), int_t)
    ] * 4
    out_specs = [pl.BlockSpec((n_pad, block), lambda i: (0, i))] * n_y + [row_spec] * 4
    call = pl.pallas_call(
        kernel,
        out_shape=out_shape,
        grid=(P // block,),
        in_specs=[pl.BlockSpec((n_pad,), lambda i: (0,))] + [row_spec] * n_in,
        out_specs=out_specs,
        interpret=interpret,
        name="rbdyn_kernel",
        # Triton's lowering, asked for by its parameters: JAX's default for a GPU is Mosaic
        # GPU (`jax_pallas_use_mosaic_gpu`), whose copies are of whole warpgroups.
        compiler_params=None
        if interpret
        else pltriton.CompilerParams(num_warps=TRITON_WARPS, num_stages=1),
    )
    outs = _undifferentiated(call)(ts_pad, *in_rows)
    ys_rows, counts, result = outs[:n_y], outs[n_y : n_y + 3], outs[n_y + 3]

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


# In interpret mode (a CPU: for checking, not for speed) the kernel is thousands of
# operations on rows, which XLA compiles markedly faster at its backend optimisation level
# 1 than at its default. Level 0 would be faster still, but rounds some float32 operations
# otherwise than `Vmap`'s program, and the steps would then differ. A Pallas program is not
# stored by the cache of traced programs (`jax.export` does not serialize it).
INTERPRET_OPTIONS = {**COMPILER_OPTIONS, "xla_backend_optimization_level": 1}
kernel_compiled = Program(kernel_solve, validated=checked_before_tracing, store=False)
kernel_interpreted = Program(
    kernel_solve, validated=checked_before_tracing, options=INTERPRET_OPTIONS, store=False
)
