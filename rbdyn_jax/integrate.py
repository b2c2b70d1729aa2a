"""Integration of a model with diffrax (the only module that calls diffrax; DESIGN.md).

`simulate(model, y0, ts, ...)` solves one trajectory; `simulate_batch(model, y0s, ts, ...)`
vmaps it over initial conditions and, with `model_axes`, over model parameters. Both are
compiled once per model *structure* (`eqx.filter_jit`): changing parameter values, initial
conditions, times or tolerances reuses the compiled solve.

With JAX's persistent compilation cache configured, the traced solves are stored beside it
(`_traces.py`), so that a later process skips tracing as well as compiling.

`COMPILER_OPTIONS` are the XLA options of every program rbdyn_jax compiles (a shorter
compile on CPU, the same run time; `_xla.py`). Pass them to your own `jax.jit` around a
solve, a gradient of a loss say: `jax.jit(jax.grad(loss), compiler_options=COMPILER_OPTIONS)`.
`configure_xla()`, called before JAX computes anything, sets XLA's process-wide flags for
faster solves on CPU (its loops compiled whole; `_xla.py`).
"""

import functools
import numbers

import diffrax
import equinox as eqx
import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PyTree

from . import _cheapest, _traces
from ._checks import as_float_array, checks_as_nan
from ._xla import COMPILER_OPTIONS, configure_xla, filter_jit, nested_filter_jit
from .models import AbstractRigidBody


class RESULTS(diffrax.RESULTS):  # pyright: ignore[reportGeneralTypeIssues]
    """Outcome of a solve: diffrax's codes (`successful`, `max_steps_reached`, …) and one
    of ours. The text of each item is its error message."""

    nonfinite_state = (
        "The state or its derivative is not finite (NaN or inf, or a zero quaternion): "
        "check the initial condition and the model's parameters."
    )


def _code(result) -> Array:
    """The `RESULTS` code (an int32 array) of a diffrax or rbdyn_jax result item.

    diffrax's codes are the first of ours with the same values (tested), so promoting one
    is the identity on its value. `RESULTS.promote` would look the value up in a table with
    `jax.ensure_compile_time_eval`: when the code is a constant (diffrax's step-size
    controller and Runge–Kutta step return the constant `successful`), that lookup runs
    eagerly while the solve is traced and compiles seven small programs on a first call
    (measured ~0.2 s)."""
    return jnp.asarray(result._value, jnp.int32)


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


# diffeqsolve's first step when given `dt0=None` (diffrax 0.7.2): its controller picks a step
# by Hairer's heuristic only for a bare `ODETerm`, and diffeqsolve hands it the term wrapped
# (`WrapTerm`), so it takes 0.01. Kept in the unit of `ts` when the solves run in the unit
# time (`_unit_time`), so that they take the steps they took in t (tested against a plain
# `diffeqsolve` in t, `test_benchmarks.py`).
_FIRST_STEP = 0.01


def _unit_time(ts, dt0):
    """The solves run in the time s = (t − t0)/span ∈ [0, 1], `t0, span = ts[0], ts[-1] −
    ts[0]`: returns `t0`, `span`, the output times in s and the first step in s (`dt0`, or
    `_FIRST_STEP`, in the unit of `ts`).

    diffeqsolve's `t0` and `t1` are then the constants 0 and 1, whatever `ts` is. It
    computes its end-of-interval clip, t1 less 100 floats, as 100 chained `prevbefore`
    calls: on a traced t1 (one compiled solve for all `ts`) they were ~1900 of a vmapped
    solve's ~3450 XLA instructions, and on a constant XLA folds them. With dy/ds = span·f
    and the first step given in t, the steps are those of the solve in t, to round-off
    (the controller's error estimates and step factors do not depend on the time unit)."""
    t0, span = ts[0], ts[-1] - ts[0]
    return t0, span, (ts - t0) / span, (_FIRST_STEP if dt0 is None else dt0) / span


def _per_unit_time(span, tree):
    """A rate dy/dt as dy/ds (`_unit_time`)."""
    return jax.tree_util.tree_map(lambda x: span * x, tree)


@nested_filter_jit
def _field(model, t, y):
    """`model.vector_field(t, y, None)`, traced once per solve. A solve traces the field
    four times (`_start`, diffeqsolve's check of the term, and the Runge–Kutta step of its
    loop body twice: for the body's output structure and for the loop), and under `vmap`
    JAX batches the loop body two or three times (its fixed point over which parts of the
    loop's state are batched). As one `jit` the field is traced, batched and lowered once,
    and XLA inlines it again: the default batch's first call 2.08–2.10 → 1.90–1.91 s
    (N = 256, interleaved), the same program and bitwise the same trajectories."""
    return model.vector_field(t, y, None)


# The jitted functions a solve traces whose traces depend on the check mode (`_checks.
# checks_as_nan`): their cached traces are dropped when the mode changes.
MODE_DEPENDENT_JITS = (diffrax.diffeqsolve, _field)


class _Guarded(eqx.Module):
    """The model's vector field in the unit time s (`_unit_time`), or dy/ds = 0 for a lane
    flagged bad (`args` = ok flag), so a bad lane takes a few steps instead of stalling its
    batch. A module, not a closure, so adjoints (BacksolveAdjoint) see the model's
    parameters (and `t0`, `span`) as inputs."""

    model: AbstractRigidBody
    t0: Array
    span: Array

    def __call__(self, s, y, ok):
        f = _field(self.model, self.t0 + s * self.span, y)
        return _per_unit_time(self.span, _where_tree(ok, f, 0.0))


def _promoted(model, y0, t):
    """`y0` with its floating leaves in the dtype its steps give it: that of the times, the
    model's arrays and `y0` together (standard promotion; an explicit cast, so also under
    the caller's strict promotion). A float32 `y0` with float64 times starts in float64,
    and is normalised there."""
    inexact = [x for x in jax.tree_util.tree_leaves((t, model, y0))
               if eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.inexact)]
    with jax.numpy_dtype_promotion("standard"):
        dtype = jnp.result_type(*inexact)
    return jax.tree_util.tree_map(
        lambda y: y.astype(dtype) if jnp.issubdtype(y.dtype, jnp.inexact) else y, y0)


def _start(model, y0, t0):
    """The normalised initial state, whether it (and its derivative) is finite, and the
    state actually integrated: a harmless stand-in for a non-finite one, which would make
    the step controller reject step after step until `max_steps` (and hold a whole vmapped
    batch in its loop). The trajectory is then reported as `nonfinite_state`. The initial
    attitude is normalised (the torques assume a unit quaternion; a zero one becomes NaN and
    is reported as non-finite). A state whose derivative is already non-finite (NaN
    parameters, a singular inertia) is caught here too. Also returns f(t0, ·) of the state
    integrated, for a caller that needs it."""
    y0, _ = model.normalise(y0)
    ok0 = _all_finite(y0)
    y_run = _where_tree(ok0, y0, 1.0)
    f0 = _field(model, t0, y_run)
    ok0 = ok0 & _all_finite(f0)
    return ok0, _where_tree(ok0, y0, 1.0), f0


def _finish(model, ts, ys, ok0, result, counts) -> Trajectory:
    """A `Trajectory` from raw solver output (one trajectory): renormalise, NaN out a
    non-finite start, and report a non-finite state as `nonfinite_state`."""
    ys, drift = model.normalise(ys)
    ys = _where_tree(ok0, ys, jnp.nan)
    if not isinstance(result, RESULTS):  # diffrax's own codes
        result = _as_result(_code(result))
    bad_state = ~ok0 | ((result == RESULTS.successful) & ~_all_finite(ys))
    result = RESULTS.where(bad_state, RESULTS.nonfinite_state, result)
    stats = {
        "num_steps": counts[0],
        "num_accepted_steps": counts[1],
        "num_rejected_steps": counts[2],
        "norm_drift": drift,
    }
    return Trajectory(ts=ts, ys=ys, stats=stats, result=result)


def _solve(model, y0, ts, solver, controller, adjoint, max_steps, dt0) -> Trajectory:
    ts = eqx.error_if(ts, jnp.any(jnp.diff(ts) <= 0), "`ts` must be strictly increasing.")
    ok0, y0_run, _ = _start(model, _promoted(model, y0, ts), ts[0])
    t0, span, s, ds0 = _unit_time(ts, dt0)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(_Guarded(model, t0, span)),
        solver,
        t0=0.0,  # constants, not arrays (`_unit_time`)
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
    return _finish(model, ts, sol.ys, ok0, sol.result, counts)


def _compiled(fn):
    """`fn` under `eqx.filter_jit` twice: `[False]` keeps the runtime checks (host
    callbacks); `[True]` is traced with the checks as NaN (`checks_as_nan`), for inputs
    validated before tracing: its program can be stored in JAX's persistent compilation
    cache, and its trace in rbdyn_jax's beside it (`_traces.py`). Two wrappers, so that the
    two kinds of trace never share a cache entry."""

    @functools.wraps(fn)
    def checks_nan(*args):
        with checks_as_nan(jitted=MODE_DEPENDENT_JITS):
            return fn(*args)

    return {False: filter_jit(fn), True: _traces.cached(checks_nan, filter_jit(checks_nan))}


_solve_jit = _compiled(_solve)


# ----------------------------------------------------------------------------------------
# The lane solver: the batch flows through a fixed number of lanes, refilled as they finish
# ----------------------------------------------------------------------------------------


class _LaneField(eqx.Module):
    """The vector field of `lanes` trajectories as one batched state (leading lane axis on
    every leaf), each lane with its own unit time `s[:, 0]` (`_unit_time`) and `ok` flag.
    diffrax's solver step then runs on whole `(lanes, …)` arrays: its stage loop combines
    contiguous blocks instead of a vmapped loop of tiny ones (measured 2.4× faster per step,
    bitwise the same arithmetic). `model` carries a leading lane axis when `batched`."""

    model: AbstractRigidBody
    batched: bool = eqx.field(static=True)
    t0: Array
    span: Array

    def __call__(self, s, y, ok):  # `_Guarded` per lane: the default path's arithmetic
        axis = 0 if self.batched else None
        return eqx.filter_vmap(lambda m, s, x, ok: _Guarded(m, self.t0, self.span)(s, x, ok),
                               in_axes=(axis, 0, 0, 0))(self.model, s[:, 0], y, ok)


def _lane_select(mask, new, old, axis=0):
    """Per-lane `where` on pytrees whose lane axis is `axis`."""

    def sel(a, b):
        return jnp.where(mask.reshape((1,) * axis + mask.shape + (1,) * (b.ndim - axis - 1)),
                         a, b)

    return jax.tree_util.tree_map(sel, new, old)


def _as_result(values) -> RESULTS:
    """A `RESULTS` item holding an integer array of codes (as the loop carries them)."""
    return eqx.tree_at(lambda r: r._value, RESULTS.successful, values)


def _clip_floor(dtype) -> np.floating:
    """diffeqsolve's end-of-interval threshold (a step ending above it ends at t1) for the
    unit time's t1 = 1 (`_unit_time`): 1 moved down by 100 floats, as its 100 calls of
    equinox's `prevbefore` move t1, i.e. 1 − 100·ε⁻ (ε⁻ the spacing of the floats just
    below 1; exact in the dtype). A NumPy constant."""
    dtype = np.dtype(dtype)
    return dtype.type(1) - dtype.type(100) * np.finfo(dtype).epsneg


def _take(tree, i):
    return jax.tree_util.tree_map(lambda x: x[i], tree)


_SYMMETRIC = ((0, 0), (1, 1), (2, 2), (1, 0), (2, 0), (2, 1))  # an inertia's 6 elements


def _unit_columns(leaves, offsets, P, symmetric=()):
    """One `(P, *shape)` array per leaf: row p is the unit perturbation of the leaf's
    element p − offset (zero outside the leaf's block of rows). A leaf flagged in
    `symmetric` (a 3×3 inertia) has six rows, its symmetric unit perturbations
    (E_ii; E_ij + E_ji for i > j, in `_SYMMETRIC`'s order)."""
    out = []
    for k, (x, o) in enumerate(zip(leaves, offsets)):
        if k < len(symmetric) and symmetric[k]:
            e = np.zeros((P, 3, 3))
            for r, (i, j) in enumerate(_SYMMETRIC):
                e[o + r, i, j] = e[o + r, j, i] = 1.0
            out.append(jnp.asarray(e, x.dtype))
        else:
            out.append(jnp.eye(P, dtype=x.dtype)[:, o:o + x.size].reshape((P,) + x.shape))
    return out


def _symmetric_part(dJ):
    """The coefficients of dJ's symmetric part on `_unit_columns`' symmetric rows."""
    return jnp.stack([0.5 * (dJ[..., i, j] + dJ[..., j, i]) for i, j in _SYMMETRIC], axis=-1)


def _pick(tree, which):
    """`tree`'s array leaves number `which` (`_with_leaves`' numbering)."""
    leaves = jax.tree_util.tree_leaves(eqx.filter(tree, eqx.is_array))
    return [leaves[i] for i in which]


def _with_leaves(tree, which, new):
    """`tree` with its array leaves number `which` replaced by `new`."""
    dyn, static = eqx.partition(tree, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(dyn)
    leaves = list(leaves)
    for i, x in zip(which, new):
        leaves[i] = x
    return eqx.combine(jax.tree_util.tree_unflatten(treedef, leaves), static)


class _Sensitivity(eqx.Module):
    """A model extended by its forward sensitivities: the state `(y, S)`, `S` a tuple with
    one array per state leaf numbered in `carried` (`y`'s leaves, flattened order): that
    leaf's `P` columns as a `(*shape, P)` array, flattened (so that a lane's time step
    broadcasts against the one axis of every leaf), and

        dy/dt = f(t, y; p),    dS/dt = ∂f/∂y · S + ∂f/∂p,

    p the model's array leaves number `which`, whose elements are the columns `offsets[k]
    …` of S; the other columns (initial conditions, the start time) have no ∂f/∂p. The
    columns are one `jax.jvp` of the model's vector field, vmapped. The leaves not carried
    enter it with zero columns, so `carried` must be closed (`_closed_groups`): the carried
    leaves' rates do not read the others' columns. Integrated by the same explicit
    Runge–Kutta steps as y, S is exactly the derivative of the discrete solution for those
    steps (Runge–Kutta methods commute with linearisation).

    The columns are the last axis, of S and of the vmapped `jvp`, so that each element of a
    leaf is a contiguous block of S. XLA:CPU fuses the concatenation that assembles a leaf
    from its elements with all that is computed upstream of it, and recomputes that for
    every number it writes; with the columns first, that concatenation is on the minor
    axis, a select per number, unvectorised. With the columns last and the written-out
    arithmetic of `dynamics.py`, the lane gradient of `benchmarks/gradients.py` cost
    ~15 % less on 2 devices and ~30 % less on one (`benchmarks/README.md`, stop 24); the
    written-out arithmetic alone gained nothing, the layout alone ~10 %."""

    model: AbstractRigidBody
    which: tuple[int, ...] = eqx.field(static=True)
    offsets: tuple[int, ...] = eqx.field(static=True)
    P: int = eqx.field(static=True)
    symmetric: tuple[bool, ...] = eqx.field(static=True)
    carried: tuple[int, ...] = eqx.field(static=True)

    def vector_field(self, t, ys, args):
        y, S = ys
        leaves, treedef = jax.tree_util.tree_flatten(y)
        cols = [jnp.zeros(x.shape + (self.P,), x.dtype) for x in leaves]
        for i, s in zip(self.carried, S):
            cols[i] = s.reshape(leaves[i].shape + (self.P,))
        p = _pick(self.model, self.which)

        def field(p, y):
            return _with_leaves(self.model, self.which, p).vector_field(t, y, args)

        basis = _unit_columns(p, self.offsets, self.P, self.symmetric)
        f, dS = jax.vmap(lambda b, s: jax.jvp(field, (p, y), (b, s)), in_axes=(0, -1),
                         out_axes=(None, -1))(basis, jax.tree_util.tree_unflatten(treedef, cols))
        dS = jax.tree_util.tree_leaves(dS)
        return f, tuple(jnp.ravel(dS[i]) for i in self.carried)


def _reads(jaxpr) -> list[set[int]]:
    """For each output of `jaxpr`, the inputs it is computed from: a dependency analysis
    over its equations, exact through nested `jit`s and conservative (every output reads
    every input) through any other equation that holds a sub-program."""
    deps = {v: {i} for i, v in enumerate(jaxpr.invars)}

    def of(v):
        return deps.get(v, set()) if isinstance(v, jax.extend.core.Var) else set()

    for eqn in jaxpr.eqns:
        ins = [of(v) for v in eqn.invars]
        sub = eqn.params.get("jaxpr") if eqn.primitive.name in ("jit", "pjit") else None
        if sub is not None and len(sub.jaxpr.invars) == len(ins):
            outs = [set().union(*(ins[j] for j in d)) for d in _reads(sub.jaxpr)]
        else:
            outs = [set().union(*ins)] * len(eqn.outvars)
        for v, d in zip(eqn.outvars, outs):
            deps[v] = d
    return [of(v) for v in jaxpr.outvars]


def _closed_groups(model, t, y) -> list[tuple[int, ...]]:
    """For each leaf i of the state `y` (one trajectory), the smallest set of leaves,
    containing i, whose tangents' rates read only their own tangents (in the jaxpr of the
    field's `jax.jvp`, `_reads`): the columns a sensitivity solve of leaf i must carry. For
    a torque-free body, or a torque fixed in the body, ω̇ does not read the attitude:
    (ω) for ω and (ω, q) for q; under gravity, (ω, q) for both."""
    n = len(jax.tree_util.tree_leaves(y))

    def tangent(y, dy):
        return jax.jvp(lambda y: model.vector_field(t, y, None), (y,), (dy,))[1]

    jaxpr = jax.make_jaxpr(tangent)(y, y).jaxpr
    reads = [{j - n for j in d if j >= n} for d in _reads(jaxpr)]
    groups = []
    for i in range(n):
        group, todo = {i}, [i]
        while todo:
            new = reads[todo.pop()] - group
            group |= new
            todo += list(new)
        groups.append(tuple(sorted(group)))
    return groups


def _lane_solve(model, y0s, ts, solver, controller, max_steps, dt0, model_axes, lanes,
                mesh=None):
    """The lane solver (`_lane_loop`; on each device of `mesh`, `_lane_sharded`) and its
    `Trajectory`s.

    Differentiable in both modes by forward sensitivities: the rule of its `custom_jvp`
    integrates, once, the variational equations for every input element with a tangent
    (`_Sensitivity`; p parameters per trajectory add p columns to each state; a model's
    symmetric 3×3 `inertia` six) by the same steps as the solve, and contracts them with
    the tangents (an inertia's by their symmetric part). That contraction is linear, so
    `jax.grad` transposes it, and `jax.jacfwd`'s tangents share the one solve; the
    tangents never enter the loop. The derivative is that of the discrete solve
    (the step sizes are not differentiated, as in `diffeqsolve`); for `ts` it is
    f(tᵢ, y(tᵢ)) at the output times and the column −f(t0, y0) for the start time. The
    rule is outside the devices' `shard_map`, which the sensitivities' solve enters as
    the forward solve does. Only the columns of the state leaves the caller reads are
    integrated, where the field allows (`_closed_groups`, `_cheapest`): a loss on a
    torque-free body's ω alone carries 18 of the 42 columns of six inertia parameters
    (`gradients.py`, N = 64, XLA's defaults: `grad` 3.23 → 2.43× the lane forward)."""
    if not isinstance(solver, diffrax.AbstractERK):
        raise ValueError(
            "`lanes` needs an explicit Runge–Kutta solver (a `diffrax.AbstractERK`: Tsit5, "
            f"Dopri5, Dopri8, Bosh3, Heun, …), got {type(solver).__name__}; the default "
            "path (`lanes=None`) takes any solver diffeqsolve takes.")
    batched = model_axes is not None
    if batched:  # every array leaf with a leading trajectory axis
        model = eqx.filter_vmap(lambda m: m, in_axes=(model_axes,))(model)
    dyn, static = eqx.partition(model, eqx.is_array)
    y0s = _promoted(dyn, y0s, ts)  # before the loop's buffers take its dtype
    tols, cstatic = eqx.partition(controller, eqx.is_array)

    stored = _traces.embedder()  # inside a caller's transformation, stored programs

    def loop(m, y0s, ts, tols):
        return stored(_lane_run, m, y0s, ts, tols, cstatic, solver, max_steps, dt0, batched,
                      lanes, mesh)

    @jax.custom_jvp
    def solve(dyn, y0s, ts, tols):
        return loop(eqx.combine(dyn, static), y0s, ts, tols)

    solve.defjvp(functools.partial(_lane_jvp, loop, static, batched), symbolic_zeros=True)
    ys, ok0, result, counts = solve(dyn, y0s, ts, tols)

    def finish(m, ys, ok, result, counts):
        return _finish(m, ts, ys, ok, _as_result(result), list(counts))

    return eqx.filter_vmap(finish, in_axes=(0 if batched else None, 0, 0, 0, 0))(
        model, ys, ok0, result, counts)


def _lane_run(m, y0s, ts, tols, cstatic, solver, max_steps, dt0, batched, lanes, mesh):
    """The lane loop (`_lane_loop`), on one device or on each of `mesh`'s."""
    run = functools.partial(_lane_loop, solver=solver, max_steps=max_steps, dt0=dt0,
                            batched=batched, lanes=lanes)
    if mesh is None or mesh.devices.size == 1:
        return run(m, y0s, ts, eqx.combine(tols, cstatic))
    return _lane_sharded(run, m, y0s, ts, tols, cstatic, batched, mesh)


def _lane_sharded(run, model, y0s, ts, tols, cstatic, batched, mesh):
    """`run` (the lane loop) on each device's share of the batch (`shard_map`: every device
    runs its own loop, no collective inside it), its raw outputs in the batch's order. The
    batch is padded to a multiple of the devices by repeating its last trajectory and dealt
    out in turn (device d takes trajectories d, d + devices, …), so that a batch ordered by
    difficulty (a sweep over spin rates, say) still gives every device an equal share of
    the work."""
    from jax.sharding import PartitionSpec as P

    n_dev = mesh.devices.size
    N = jax.tree_util.tree_leaves(y0s)[0].shape[0]
    pad = -N % n_dev

    def padded(x):  # padded to P = N + pad, dealt: row d·(P/devices) + i holds i·devices + d
        x = jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]) if pad else x
        return x.reshape((-1, n_dev) + x.shape[1:]).swapaxes(0, 1).reshape(x.shape)

    def collected(x):  # the inverse of the deal, without the padding
        return x.reshape((n_dev, -1) + x.shape[1:]).swapaxes(0, 1).reshape(x.shape)[:N]

    y0s = jax.tree_util.tree_map(padded, y0s)
    dyn, static = eqx.partition(model, eqx.is_array)
    if batched:
        dyn = jax.tree_util.tree_map(padded, dyn)
    spec = P("batch") if batched else P()

    def local(dyn, y0s, ts, tols):
        return run(eqx.combine(dyn, static), y0s, ts, eqx.combine(tols, cstatic))

    out = jax.shard_map(local, mesh=mesh, in_specs=(spec, P("batch"), P(), P()),
                        out_specs=P("batch"), check_vma=False)(dyn, y0s, ts, tols)
    return jax.tree_util.tree_map(collected, out)


def _lane_jvp(loop, static, batched, primals, tangents):
    """The `custom_jvp` rule of `_lane_solve`'s loop (see there). The tolerances take no
    tangent."""
    dyn, y0s, ts, tols = primals
    tdyn, ty0s, tts, _ = tangents
    zero = jax.custom_derivatives.SymbolicZero

    def live(tree, tangent):  # the array leaves with a tangent, and all the tangents
        xs = jax.tree_util.tree_leaves(tree)
        dxs = jax.tree_util.tree_leaves(tangent, is_leaf=lambda x: isinstance(x, zero))
        return [i for i, (x, dx) in enumerate(zip(xs, dxs)) if not isinstance(dx, zero)
                and jnp.issubdtype(x.dtype, jnp.inexact)], xs, dxs

    m_which, m_leaves, m_dots = live(dyn, tdyn)
    y_which, y_leaves, y_dots = live(y0s, ty0s)
    t_live = not isinstance(tts, zero)
    N = y_leaves[0].shape[0]
    model = eqx.combine(dyn, static)
    # Columns: the differentiated model elements (per trajectory), then those of y0, then t0.
    # The inertia is a symmetric tensor: six columns, and a tangent counts by its
    # symmetric part.
    paths = [path for path, _ in jax.tree_util.tree_flatten_with_path(dyn)[0]]
    symmetric = tuple(paths[i] == (jax.tree_util.GetAttrKey("inertia"),)
                      and m_leaves[i].shape[batched:] == (3, 3) for i in m_which)
    sizes = ([6 if sym else m_leaves[i][0].size if batched else m_leaves[i].size
              for i, sym in zip(m_which, symmetric)]
             + [y_leaves[i][0].size for i in y_which])
    offsets = tuple(int(o) for o in np.cumsum([0] + sizes)[:-1])
    P = sum(sizes) + t_live
    if P == 0:  # tangents on the tolerances only
        out = loop(model, y0s, ts, tols)
        return out, (jax.tree_util.tree_map(jnp.zeros_like, out[0]),) + tuple(
            np.zeros(x.shape, jax.dtypes.float0) for x in out[1:])

    def initial(m, y0):  # S at t0: the derivative of the normalised y0, and −f(t0, y0)
        p = _pick(m, m_which)
        q = _pick(y0, y_which)

        def start(p, q):
            return _with_leaves(m, m_which, p).normalise(_with_leaves(y0, y_which, q))[0]

        basis = _unit_columns(p + q, offsets, P, symmetric)
        _, S0 = jax.vmap(lambda b: jax.jvp(start, (p, q), (b[:len(p)], b[len(p):])),
                         axis_size=P)(basis)
        if t_live:
            f0 = m.vector_field(ts[0], m.normalise(y0)[0], None)
            S0 = jax.tree_util.tree_map(lambda s, f: s.at[-1].set(-f), S0, f0)
        return [jnp.ravel(jnp.moveaxis(s, 0, -1)) for s in jax.tree_util.tree_leaves(S0)]

    S0 = eqx.filter_vmap(initial, in_axes=(0 if batched else None, 0))(model, y0s)
    # One sensitivity solve per closed group of the state's leaves (`_closed_groups`), the
    # smallest first, then one of every leaf: `_cheapest` runs the first that gives what the
    # caller reads. A loss on a torque-free body's ω alone integrates ω's columns only (18
    # of the 42), a loss on the attitude the whole state's.
    one = eqx.combine(_take(dyn, 0) if batched else dyn, static)
    y_flat, treedef = jax.tree_util.tree_flatten(y0s)
    groups = _closed_groups(one, ts[0], _take(y0s, 0))
    every = tuple(range(len(y_flat)))
    programs = sorted(set(groups) | {every}, key=lambda g: (len(g), g))

    def program(carried, dyn, y0s, S0, ts, tols):
        aug = _Sensitivity(eqx.combine(dyn, static), tuple(m_which), offsets[:len(m_which)],
                           P, symmetric, carried)
        (ys, S), ok0, result, counts = loop(aug, (y0s, tuple(S0[i] for i in carried)), ts,
                                            tols)
        out = {("ys", i): y for i, y in enumerate(jax.tree_util.tree_leaves(ys))}
        out.update({("S", i): s for i, s in zip(carried, S)})
        return dict(out, ok0=ok0, result=result, counts=counts)

    got = _cheapest.cheapest([functools.partial(program, c) for c in programs],
                             dyn, y0s, S0, ts, tols)
    ok0, result, counts = got["ok0"], got["result"], got["counts"]
    leaves = [got[("ys", i)] for i in every]
    # Rows never saved (a trajectory out of steps) stay +inf, and a row that diverged is not
    # finite: their tangents are zero, and masked on both sides of the contraction, so that
    # reverse mode does not multiply inf or NaN by a zero cotangent into every shared
    # parameter's gradient.
    finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(y.reshape(y.shape[:2] + (-1,))), -1)
                                for y in leaves]), 0)  # (N, n)

    def masked(x):
        return jnp.where(finite.reshape(finite.shape + (1,) * (x.ndim - 2)), x, 0.0)

    coef = [_symmetric_part(m_dots[i]) if sym else m_dots[i]
            for i, sym in zip(m_which, symmetric)]
    coef = [c.reshape(N, -1) if batched else jnp.broadcast_to(c.reshape(1, -1), (N, c.size))
            for c in coef]
    coef += [y_dots[i].reshape(N, -1) for i in y_which]
    coef += [jnp.broadcast_to(tts[0], (N, 1))] if t_live else []
    if t_live:  # the output times themselves: f(tᵢ, y(tᵢ)) dtᵢ

        def rates(m, ys, ok):
            f = jax.vmap(lambda t, y: m.vector_field(t, y, None))(ts, ys)
            return _where_tree(ok, f, 0.0)

        F = jax.tree_util.tree_leaves(eqx.filter_vmap(
            rates, in_axes=(0 if batched else None, 0, 0))(
                model, jax.tree_util.tree_unflatten(treedef, leaves), ok0))
    dys = []
    for i, y in enumerate(leaves):
        s = got[("S", i)].reshape(y.shape + (P,))
        # The tangent: S contracted with the inputs' tangents, per trajectory.
        d = jnp.einsum("nt...p,np->nt...", masked(s), jnp.concatenate(
            [c.astype(s.dtype) for c in coef], axis=1))
        if t_live:
            d = d + masked(F[i]) * tts.reshape((1, -1) + (1,) * (y.ndim - 2))
        dys.append(masked(d))
    ys = jax.tree_util.tree_unflatten(treedef, leaves)
    dys = jax.tree_util.tree_unflatten(treedef, dys)
    out = (ys, ok0, result, counts)
    return out, (dys,) + tuple(np.zeros(x.shape, jax.dtypes.float0) for x in out[1:])


def _lane_loop(model, y0s, ts, controller, *, solver, max_steps, dt0, batched, lanes):
    """All trajectories of `y0s` through `lanes` lanes of one while loop; the raw saved
    states (before `_finish`), the start flags, result codes and step counts.

    Each loop iteration (1) saves at most one output time per lane from the lane's last
    step (diffrax's interpolant, as `SaveAt(ts=…)` does), (2) hands every finished lane the
    next waiting trajectory, and (3) takes one diffrax solver step in every lane that has no
    output left to save, with diffrax's step-size controller deciding acceptance and the
    next step per lane. The steps, accepted/rejected decisions and saved values are those of
    `diffeqsolve` for the same trajectory (tested), but no lane idles while the slowest
    trajectory of a vmapped batch finishes (the lockstep waste of `jax.vmap(diffeqsolve)`).
    Trajectories are handed out longest-first, by |f(t0, y0)| in the tolerance scale (rank
    correlation with the step count 0.99 for a torque-free body and 0.97 for a heavy top,
    measured), so the last ones are short and the lanes finish nearly together.

    `model` has a leading trajectory axis on every array leaf when `batched`. It may be a
    `_Sensitivity` (its states `(y, S)`): the controller, the start checks and the order
    then see `y` alone, so the steps are those of the model's own solve.
    """
    from diffrax._term import WrapTerm  # exactly the term diffeqsolve hands its solver

    if getattr(solver, "scan_kind", "lax") is None:
        # Runge–Kutta stages in a plain while loop rather than diffrax's checkpointed one
        # (a custom VJP, which forward-mode autodiff cannot pass); the same arithmetic.
        solver = eqx.tree_at(lambda s: s.scan_kind, solver, "lax", is_leaf=lambda x: x is None)
    N = jax.tree_util.tree_leaves(y0s)[0].shape[0]
    L = min(lanes, N)
    n = ts.shape[0]
    # The loop runs in the unit time s ∈ [0, 1], as `_solve` does (`_unit_time`).
    start_time, span, ts, dt0 = _unit_time(ts, dt0)
    t0, t1 = jnp.zeros((), ts.dtype), jnp.ones((), ts.dtype)
    t1_floor = jnp.asarray(_clip_floor(ts.dtype))  # diffeqsolve's clip
    dyn, static = eqx.partition(model, eqx.is_array)
    axis = 0 if batched else None
    sens = isinstance(model, _Sensitivity)
    primal = (lambda y: y[0]) if sens else (lambda y: y)  # what the controller sees

    def start(m, y0):
        if sens:
            ok, y, f = _start(m.model, y0[0], start_time)
            term = WrapTerm(diffrax.ODETerm(_Guarded(m.model, start_time, span)), 1)
            y_aug = (y, _where_tree(ok, y0[1], 0.0))
            f_aug = m.vector_field(start_time, y_aug, None)  # masked with `ok` below
        else:
            ok, y, f = _start(m, y0, start_time)  # f = f(t0, y): y the stand-in where not ok
            term = WrapTerm(diffrax.ODETerm(_Guarded(m, start_time, span)), 1)
            y_aug, f_aug = y, f
        tnext, cstate = controller.init(term, t0, t1, y, dt0, ok, solver.func,
                                        solver.error_order(term))
        tnext = jnp.minimum(tnext, t1)
        if getattr(getattr(solver, "tableau", None), "fsal", False):
            # An explicit FSAL Runge–Kutta step starts from f(t0, y0): give it now (what
            # `solver.init` would compute), so that a refilled lane does not make every
            # lane re-evaluate its first stage.
            sstate = (jnp.array(False), _per_unit_time(span, _where_tree(ok, f_aug, 0.0)))
        else:
            sstate = solver.init(WrapTerm(diffrax.ODETerm(_Guarded(m, start_time, span)), 1),
                                 t0, tnext, y_aug, ok)
        # How long the trajectory will take: |f(t0, y0)| in the controller's tolerance
        # scale, the rate the state moves at, which sets the step count of these rotational
        # problems (|ω| for a free body). An ordering only: no tangents through it.
        f, y_ = jax.lax.stop_gradient((f, y))
        d = sum(jnp.sum((a / (controller.atol + controller.rtol * jnp.abs(b))) ** 2)
                for a, b in zip(jax.tree_util.tree_leaves(f), jax.tree_util.tree_leaves(y_)))
        d = jnp.where(ok & ~jnp.isnan(d), d, -1.0)  # an overflow to inf goes first
        return ok, y_aug, tnext, sstate, jax.tree_util.tree_map(jnp.asarray, cstate), d

    ok0, y0r, tnext0, sstate0, cstate0, difficulty = eqx.filter_vmap(
        start, in_axes=(axis, 0))(model, y0s)
    # Longest first: lanes take the trajectories in decreasing order of an estimate of
    # their step count, so that the last ones handed out are short and the lanes finish
    # together (a random order leaves a tail of idle lanes behind the slowest).
    order = jnp.argsort(-difficulty)
    error_order = solver.error_order(diffrax.ODETerm(_Guarded(model, start_time, span)))

    def control(tprev, tnext, y, y1, y_error, cstate):
        y_error = jax.tree_util.tree_map(lambda x: jnp.where(jnp.isnan(x), jnp.inf, x), y_error)
        keep, tp, tn, _, cstate, result = controller.adapt_step_size(
            tprev, tnext, y, y1, None, y_error, error_order, cstate)
        tp = jnp.minimum(tp, t1)
        tn = jnp.where(tn > t1_floor, jnp.where(keep, t1, tp + 0.5 * (t1 - tp)), tn)
        cstate = jax.tree_util.tree_map(jnp.asarray, cstate)
        return keep, tp, tn, cstate, _code(result)

    def interpolate(tprev, tnext, dense, t):
        # diffrax's Runge–Kutta interpolants are linear in the step's dense information
        # (y0, y1 and the stage increments k), with weights depending on θ = (t − t0)/(t1 −
        # t0) only. The weights come from the solver's own interpolant evaluated on unit
        # vectors (one row per lane: a plain matrix product); the lanes' states are then
        # combined elementwise. (Evaluating the interpolant vmapped over lanes makes one
        # tiny batched dot per lane: measured ~300 ns per lane and step on CPU, 40 % of
        # the whole loop.)
        dt = tnext - tprev
        theta = jnp.where(dt > 0, (t - tprev) / jnp.where(dt > 0, dt, 1.0), 0.0)
        keys = sorted(k for k in dense if k != "k")
        stages = jax.tree_util.tree_leaves(dense["k"])[0].shape[0]
        eye = jnp.eye(len(keys) + stages, dtype=theta.dtype)
        probe = dict(zip(keys, eye), k=eye[len(keys):])
        zero, one = jnp.zeros((), theta.dtype), jnp.ones((), theta.dtype)
        w = jax.vmap(lambda th: solver.interpolation_cls(t0=zero, t1=one, **probe)
                     .evaluate(th))(theta).T  # (keys + stages, lanes)

        def combine(*leaves):  # unrolled: XLA:CPU's reductions over 7 rows are slow
            *ys, k = leaves
            terms = [(w[i], y) for i, y in enumerate(ys)]
            terms += [(w[len(keys) + j], k[j]) for j in range(stages)]
            out = None
            for wi, x in terms:
                term = wi.reshape(wi.shape + (1,) * (x.ndim - 1)) * x
                out = term if out is None else out + term
            return out

        return jax.tree_util.tree_map(combine, *[dense[k] for k in keys], dense["k"])

    lane = order[:L]
    first = dict(idx=jnp.arange(L, dtype=jnp.int32), next=jnp.asarray(L, jnp.int32),
                 tprev=jnp.full(L, t0), tnext=tnext0[lane],
                 y=_take(y0r, lane), ss=_take(sstate0, lane), cs=_take(cstate0, lane),
                 ok=ok0[lane], m=_take(dyn, lane) if batched else None)
    struct = jax.eval_shape(lambda: solver.step(
        WrapTerm(diffrax.ODETerm(_LaneField(eqx.combine(first["m"] if batched else dyn,
                                                        static), batched, start_time, span)), 1),
        first["tprev"][:, None], first["tnext"][:, None], first["y"], first["ok"],
        first["ss"], False)[2])
    carry = dict(
        first,
        dense=jax.tree_util.tree_map(lambda x: jnp.zeros(x.shape, x.dtype), struct),
        dense_t=jnp.zeros((2, L), ts.dtype), pending=jnp.zeros(L, bool),
        save=jnp.zeros(L, jnp.int32), counts=jnp.zeros((3, L), int),
        result=jnp.zeros(L, jnp.int32),
        ys=jax.tree_util.tree_map(lambda x: jnp.full((N, n) + x.shape[1:], jnp.inf, x.dtype),
                                  y0s),
        out_counts=jnp.zeros((N, 3), int), out_result=jnp.zeros(N, jnp.int32),
    )
    # The state, the solver's state, the step's dense output and the saved values take a
    # batch axis (`jax.vmap`) from the model and the initial states (and tangents, for a
    # derivative of the sensitivities themselves), but the buffers start as constants and
    # some lane states from y0 alone. JAX finds which carries of a while loop take them by
    # a fixpoint that re-traces the whole body on each pass; tying those carries to the
    # inputs from the start (a select that always picks the initial value) makes it
    # converge in one pass (`jacfwd` through the loop traced ~1 s faster, measured).
    inputs = [x for x in jax.tree_util.tree_leaves((dyn, y0s, sstate0)) if
              jnp.issubdtype(x.dtype, jnp.inexact)]
    if inputs:
        anchor = sum(jnp.sum(x) for x in inputs)
        never = jnp.zeros((), bool)

        def tied(x):
            if not jnp.issubdtype(x.dtype, jnp.inexact):
                return x
            return jnp.where(never, anchor.astype(x.dtype), x)

        for k in ("y", "ss", "dense", "ys"):
            carry[k] = jax.tree_util.tree_map(tied, carry[k])

    lane_ids = jnp.arange(L, dtype=order.dtype)

    def cond(c):
        return jnp.any(c["idx"] < N)

    def body(c):
        c = dict(c)
        active = c["idx"] < N
        current = order[jnp.minimum(c["idx"], N - 1)]  # each lane's row of the batch
        # (1) Save one output time from each lane's last step.
        s = jnp.minimum(c["save"], n - 1)
        vals = interpolate(c["dense_t"][0], c["dense_t"][1], c["dense"], ts[s])
        # Lanes with nothing to save write to rows N + lane, out of bounds and dropped. Every
        # row is then distinct, as `unique_indices` promises, and forward-mode autodiff
        # scatters the tangents as it scatters the values. Without the promise, JAX's
        # scatter JVP masks the whole (N, n, …) output buffer at every iteration, a cost
        # quadratic in N (measured: a jvp of 8192 trajectories cost 10.0× the forward
        # solve, 1.85× with the promise).
        row = jnp.where(c["pending"], current, N + lane_ids)
        c["ys"] = jax.tree_util.tree_map(
            lambda o, v: o.at[row, s].set(v, mode="drop", unique_indices=True), c["ys"], vals)
        c["save"] = c["save"] + c["pending"].astype(jnp.int32)
        s = jnp.minimum(c["save"], n - 1)
        c["pending"] = c["pending"] & (c["save"] < n) & (ts[s] <= c["dense_t"][1])
        # (2) Finished lanes report and take the next trajectory.
        done = active & ~c["pending"] & ((c["tprev"] >= t1) | (c["result"] != 0))
        row = jnp.where(done, current, N + lane_ids)
        c["out_counts"] = c["out_counts"].at[row].set(c["counts"].T, mode="drop",
                                                      unique_indices=True)
        c["out_result"] = c["out_result"].at[row].set(c["result"], mode="drop",
                                                      unique_indices=True)
        new = c["next"] + jnp.cumsum(done, dtype=jnp.int32) - 1
        c["next"] = c["next"] + jnp.sum(done, dtype=jnp.int32)
        take = order[jnp.minimum(new, N - 1)]
        c["idx"] = jnp.where(done, jnp.where(new < N, new, N), c["idx"])
        c["tprev"] = jnp.where(done, t0, c["tprev"])
        for k, src in (("tnext", tnext0), ("y", y0r), ("ss", sstate0), ("cs", cstate0),
                       ("ok", ok0), ("m", dyn if batched else None)):
            if src is not None:
                c[k] = _lane_select(done, _take(src, take), c[k])
        c["save"] = jnp.where(done, 0, c["save"])
        c["counts"] = jnp.where(done, 0, c["counts"])
        c["result"] = jnp.where(done, 0, c["result"])
        # (3) One solver step in every lane with nothing left to save.
        go = (c["idx"] < N) & ~c["pending"] & (c["tprev"] < t1) & (c["result"] == 0)
        m = eqx.combine(c["m"] if batched else dyn, static)
        term = WrapTerm(diffrax.ODETerm(_LaneField(m, batched, start_time, span)), 1)
        y1, y_error, dense, ss1, _ = solver.step(
            term, c["tprev"][:, None], c["tnext"][:, None], c["y"], c["ok"], c["ss"], False)
        ss1 = jax.tree_util.tree_map(lambda a, b: jnp.broadcast_to(a, b.shape), ss1, c["ss"])
        keep, tp, tn, cs1, result = jax.vmap(control)(
            c["tprev"], c["tnext"], primal(c["y"]), primal(y1), primal(y_error), c["cs"])
        accept = go & keep
        c["y"] = _lane_select(accept, y1, c["y"])
        c["ss"] = _lane_select(accept, ss1, c["ss"])
        c["cs"] = _lane_select(go, cs1, c["cs"])
        c["dense"] = dict(_lane_select(accept, {k: v for k, v in dense.items() if k != "k"},
                                       {k: v for k, v in c["dense"].items() if k != "k"}),
                          k=_lane_select(accept, dense["k"], c["dense"]["k"], axis=1))
        c["dense_t"] = jnp.where(accept, jnp.stack([c["tprev"], c["tnext"]]), c["dense_t"])
        c["tprev"] = jnp.where(go, tp, c["tprev"])
        c["tnext"] = jnp.where(go, tn, c["tnext"])
        counts = c["counts"] + jnp.stack([go, accept, go & ~keep]).astype(int)
        c["counts"] = counts
        result = jnp.where(go, result, c["result"])
        maxed = go & (counts[0] >= max_steps) & (c["tprev"] < t1) & (result == 0)
        c["result"] = jnp.where(maxed, RESULTS.max_steps_reached._value, result)
        s = jnp.minimum(c["save"], n - 1)
        c["pending"] = c["pending"] | (accept & (c["save"] < n) & (ts[s] <= c["dense_t"][1]))
        return c

    c = jax.lax.while_loop(cond, body, carry)
    return c["ys"], ok0, c["out_result"], c["out_counts"]


def _solve_batch(model, y0s, ts, solver, controller, adjoint, max_steps, dt0, model_axes):
    def one(m, y0):
        return _solve(m, y0, ts, solver, controller, adjoint, max_steps, dt0)

    return eqx.filter_vmap(one, in_axes=(model_axes, 0))(model, y0s)


def _lane_batch(models, y0s, ts, solver, rtol, atol, max_steps, lanes) -> Trajectory:
    """The lane solver for a caller that traces it inside its own program (the sweep, under
    its own `checks_as_nan`): no jit wrapper of its own, per-trajectory `models` (every
    array leaf batched), one device."""
    controller = diffrax.PIDController(rtol=rtol, atol=atol)
    return _lane_solve(models, y0s, ts, solver, controller, max_steps, None, 0, lanes)


def _succeeded_now(result: RESULTS) -> bool:
    """Whether every code of a concrete `result` is `successful`, read on the host (`False`
    for a traced one): `throw`'s check then needs no `error_if`, whose eager comparison and
    check compile two programs on first use (~0.05 s)."""
    code = result._value
    return not isinstance(code, jax.core.Tracer) and bool(
        np.all(np.asarray(code) == np.asarray(RESULTS.successful._value)))


def _cacheable(ts, *tols) -> bool:
    """Whether the inputs were validated before tracing (concrete, not traced): the solve
    is then traced with its checks as NaN, holds no host callback, and JAX's persistent
    compilation cache can store it."""
    return not any(isinstance(x, jax.core.Tracer) for x in (ts, *tols))


def _mesh(devices) -> jax.sharding.Mesh:
    available = jax.local_devices()
    if devices is None:
        devices = len(available)
    if not isinstance(devices, numbers.Integral) or not 1 <= devices <= len(available):
        raise ValueError(f"`devices` must be an int in [1, {len(available)}] (the local "
                         f"devices), got {devices!r}.")
    return jax.sharding.Mesh(np.asarray(available[:devices]), ("batch",))


_solve_batch_jit = _compiled(_solve_batch)
_lane_solve_jit = _compiled(_lane_solve)


def _prepare(model, ts, rtol, atol, max_steps):
    if not isinstance(model, AbstractRigidBody):
        raise ValueError(f"`model` must be a rigid-body model, got {type(model).__name__}.")
    ts = as_float_array(ts, "ts")
    if ts.ndim != 1 or ts.shape[0] < 2:
        raise ValueError(f"`ts` must be a 1-D array of at least 2 times, got shape {ts.shape}.")
    if not isinstance(ts, jax.core.Tracer):  # checked here, so not in the compiled solve
        t = np.asarray(ts)  # NumPy: concrete even while a caller's function is traced
        if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
            raise ValueError("`ts` must be finite and strictly increasing.")
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
    - `dt0`: initial step; `None` takes 0.01 (in the unit of `ts`), what `diffeqsolve`
      takes.
    - `throw`: raise a runtime error when the result is not `RESULTS.successful`;
      otherwise the code is returned in `Trajectory.result`.

    **Returns:** a `Trajectory`.
    """
    ts, controller, max_steps = _prepare(model, ts, rtol, atol, max_steps)
    traj = _solve_jit[_cacheable(ts, rtol, atol)](model, y0, ts, solver, controller, adjoint,
                                                  max_steps, dt0)
    if throw and not _succeeded_now(traj.result):
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
    lanes: int | None = None,
    devices: int | None = None,
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
    - `lanes`: `None` (default) vmaps `diffeqsolve`, differentiable in both modes with any
      `adjoint`. An int selects the **lane solver**, for large forward batches: the batch
      flows through `lanes` lanes of one loop that drives diffrax's solver step and
      step-size controller itself (an explicit Runge–Kutta `solver`, a
      `diffrax.AbstractERK`), and a lane whose trajectory has finished takes the next
      one at once (a vmapped `diffeqsolve` runs every lane until the slowest trajectory of
      the batch finishes). Trajectories are handed out longest-first (by |f(t0, y0)|), and
      the devices are dealt them in turn; use fewer lanes than trajectories per device
      (2–8 trajectories per lane) so that lanes refill and finish together. Same steps,
      same saved values (to round-off) and same `stats` and `result` as the default.
      Differentiable in both modes (`jax.grad`, `jax.jacfwd`, w.r.t. the model, `y0s` and
      `ts`) by forward sensitivities: one solve carries, beside each state, its derivative
      w.r.t. every differentiated element (p per trajectory: 6 for an inertia, 7 for an
      initial state; per-trajectory models count their own only), by the same steps, so
      the derivative equals reverse mode through the default path (to round-off; w.r.t.
      `ts` it is f(tᵢ, y(tᵢ)) where the default path differentiates its interpolant: the
      two agree to the local error of a step, ~3e-7 relative at rtol 1e-9). The
      inertia is differentiated as the symmetric tensor it is: a tangent counts by its
      symmetric part, and a gradient w.r.t. a raw J is symmetric, (g + gᵀ)/2 of the
      default path's g (equal along every symmetric direction). The cost grows with p,
      not with the number of tangents (measured with `configure_xla`: ~4.1–4.5× the
      forward solve for an inertia, ~2.7–3.5× for a loss on a torque-free body's ω
      alone, whose sensitivities need no attitude's: only those the caller reads are
      integrated); `adjoint` is ignored. Second derivatives: forward mode over either
      mode (`jax.jacfwd(jax.jacrev(loss))`, a Hessian); reverse mode over either is
      refused by JAX's while loop. On a CPU at 10³–10⁴ trajectories, 64 lanes per device
      suit XLA configured by `configure_xla` (as `rbdyn sweep` runs), 256 XLA's
      defaults (see `benchmarks/`).
    - `devices`: with `lanes`, the number of local devices the batch is split over
      (default: all of the default backend; on CPU that is one unless XLA was started with
      several host devices, e.g. by `configure_xla(host_devices=2)` first).

    **Returns:** a `Trajectory` with a leading batch axis on every leaf (including `ts`,
    `stats` and `result`).
    """
    ts, controller, max_steps = _prepare(model, ts, rtol, atol, max_steps)
    cacheable = _cacheable(ts, rtol, atol)
    if lanes is None:
        traj = _solve_batch_jit[cacheable](model, y0s, ts, solver, controller, adjoint,
                                           max_steps, dt0, model_axes)
    else:
        if not isinstance(lanes, numbers.Integral) or isinstance(lanes, bool) or lanes < 1:
            raise ValueError(f"`lanes` must be a positive int or None, got {lanes!r}.")
        traj = _lane_solve_jit[cacheable](model, y0s, ts, solver, controller, max_steps, dt0,
                                          model_axes, int(lanes), _mesh(devices))
    if throw and not _succeeded_now(traj.result):
        traj = traj.result.error_if(traj, jnp.any(traj.result != RESULTS.successful))
    return traj


__all__ = ["COMPILER_OPTIONS", "RESULTS", "Trajectory", "configure_xla", "simulate",
           "simulate_batch"]
