"""Forward sensitivities of the lane loop: the derivative of a lane solve with respect
to the model's parameters, the initial states and the times, integrated beside the state
by the same steps, and the `custom_jvp` rule that contracts them with the tangents."""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..models import AbstractRigidBody
from ._cheapest import cheapest
from ._dependencies import closed_groups
from ._field import array_axes, checked_times, finish, promoted, where_tree
from ._lane_arrays import take
from ._lane_system import AbstractLaneSystem, Plain
from ._solution import Trajectory, as_result

SYMMETRIC = ((0, 0), (1, 1), (2, 2), (1, 0), (2, 0), (2, 1))  # an inertia's 6 elements


def unit_columns(leaves, offsets, P, symmetric=()):
    """One `(P, *shape)` array per leaf: row p is the unit perturbation of the leaf's
    element p − offset (zero outside the leaf's block of rows). A leaf flagged in
    `symmetric` (a 3×3 inertia) has six rows, its symmetric unit perturbations
    (E_ii; E_ij + E_ji for i > j, in `SYMMETRIC`'s order)."""
    out = []
    for k, (x, o) in enumerate(zip(leaves, offsets)):
        if k < len(symmetric) and symmetric[k]:
            e = np.zeros((P, 3, 3))
            for r, (i, j) in enumerate(SYMMETRIC):
                e[o + r, i, j] = e[o + r, j, i] = 1.0
            out.append(jnp.asarray(e, x.dtype))
        else:
            out.append(jnp.eye(P, dtype=x.dtype)[:, o : o + x.size].reshape((P,) + x.shape))
    return out


def symmetric_part(dJ):
    """The coefficients of dJ's symmetric part on `unit_columns`' symmetric rows."""
    return jnp.stack([0.5 * (dJ[..., i, j] + dJ[..., j, i]) for i, j in SYMMETRIC], axis=-1)


def pick(tree, which):
    """`tree`'s array leaves number `which` (`with_leaves`' numbering)."""
    leaves = jax.tree_util.tree_leaves(eqx.filter(tree, eqx.is_array))
    return [leaves[i] for i in which]


def with_leaves(tree, which, new):
    """`tree` with its array leaves number `which` replaced by `new`."""
    dyn, static = eqx.partition(tree, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(dyn)
    leaves = list(leaves)
    for i, x in zip(which, new):
        leaves[i] = x
    return eqx.combine(jax.tree_util.tree_unflatten(treedef, leaves), static)


class Sensitivity(AbstractLaneSystem):
    """A model extended by its forward sensitivities: the state `(y, S)`, `S` a tuple with
    one array per state leaf numbered in `carried` (`y`'s leaves, flattened order): that
    leaf's `P` columns as a `(*shape, P)` array, flattened (so that a lane's time step
    broadcasts against the one axis of every leaf), and

        dy/dt = f(t, y; p),    dS/dt = ∂f/∂y · S + ∂f/∂p,

    p the model's array leaves number `which`, whose elements are the columns `offsets[k]
    …` of S; the other columns (initial conditions, the start time) have no ∂f/∂p. The
    columns are one `jax.jvp` of the model's vector field, vmapped. The leaves not carried
    enter it with zero columns, so `carried` must be closed (`closed_groups`): the carried
    leaves' rates do not read the others' columns. Integrated by the same explicit
    Runge–Kutta steps as y, S is exactly the derivative of the discrete solution for those
    steps (Runge–Kutta methods commute with linearisation).

    The columns are the last axis, of S and of the vmapped `jvp`, so that each element of a
    leaf is a contiguous block of S. XLA:CPU fuses the concatenation that assembles a leaf
    from its elements with all that is computed upstream of it, and recomputes that for
    every number it writes; with the columns first, that concatenation is on the minor
    axis, a select per number, unvectorised."""

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
        p = pick(self.model, self.which)

        def field(p, y):
            return with_leaves(self.model, self.which, p).vector_field(t, y, args)

        basis = unit_columns(p, self.offsets, self.P, self.symmetric)
        f, dS = jax.vmap(
            lambda b, s: jax.jvp(field, (p, y), (b, s)), in_axes=(0, -1), out_axes=(None, -1)
        )(basis, jax.tree_util.tree_unflatten(treedef, cols))
        dS = jax.tree_util.tree_leaves(dS)
        return f, tuple(jnp.ravel(dS[i]) for i in self.carried)

    def primal(self, y):
        return y[0]

    def extend(self, ok, y, f, y0, t):
        y_run = (y, where_tree(ok, y0[1], 0.0))
        return y_run, self.vector_field(t, y_run, None)  # masked with `ok` by the loop


def lane_jvp(loop, static, batched, primals, tangents):
    """The `custom_jvp` rule of a lane or kernel solve (`sensitivity_solve`). The tolerances
    take no tangent."""
    dyn, y0s, ts, tols = primals
    tdyn, ty0s, tts, _ = tangents
    zero = jax.custom_derivatives.SymbolicZero

    def live(tree, tangent):  # the array leaves with a tangent, and all the tangents
        xs = jax.tree_util.tree_leaves(tree)
        dxs = jax.tree_util.tree_leaves(tangent, is_leaf=lambda x: isinstance(x, zero))
        return (
            [
                i
                for i, (x, dx) in enumerate(zip(xs, dxs))
                if not isinstance(dx, zero) and jnp.issubdtype(x.dtype, jnp.inexact)
            ],
            xs,
            dxs,
        )

    m_which, m_leaves, m_dots = live(dyn, tdyn)
    y_which, y_leaves, y_dots = live(y0s, ty0s)
    t_live = not isinstance(tts, zero)
    N = y_leaves[0].shape[0]
    model = eqx.combine(dyn, static)
    # Columns: the differentiated model elements (per trajectory), then those of y0, then t0.
    # The inertia is a symmetric tensor: six columns, and a tangent counts by its
    # symmetric part.
    paths = [path for path, _ in jax.tree_util.tree_flatten_with_path(dyn)[0]]
    symmetric = tuple(
        paths[i] == (jax.tree_util.GetAttrKey("inertia"),) and m_leaves[i].shape[batched:] == (3, 3)
        for i in m_which
    )
    sizes = [
        6 if sym else m_leaves[i][0].size if batched else m_leaves[i].size
        for i, sym in zip(m_which, symmetric)
    ] + [y_leaves[i][0].size for i in y_which]
    offsets = tuple(int(o) for o in np.cumsum([0] + sizes)[:-1])
    P = sum(sizes) + t_live
    if P == 0:  # tangents on the tolerances only
        out = loop(Plain(model), y0s, ts, tols)
        return out, (jax.tree_util.tree_map(jnp.zeros_like, out[0]),) + tuple(
            np.zeros(x.shape, jax.dtypes.float0) for x in out[1:]
        )

    def initial(m, y0):  # S at t0: the derivative of the normalised y0, and −f(t0, y0)
        p = pick(m, m_which)
        q = pick(y0, y_which)

        def start(p, q):
            return with_leaves(m, m_which, p).normalize(with_leaves(y0, y_which, q))[0]

        basis = unit_columns(p + q, offsets, P, symmetric)
        _, S0 = jax.vmap(lambda b: jax.jvp(start, (p, q), (b[: len(p)], b[len(p) :])), axis_size=P)(
            basis
        )
        if t_live:
            f0 = m.vector_field(ts[0], m.normalize(y0)[0], None)
            S0 = jax.tree_util.tree_map(lambda s, f: s.at[-1].set(-f), S0, f0)
        return [jnp.ravel(jnp.moveaxis(s, 0, -1)) for s in jax.tree_util.tree_leaves(S0)]

    S0 = eqx.filter_vmap(initial, in_axes=(eqx.if_array(0) if batched else None, 0))(model, y0s)
    # One sensitivity solve per closed group of the state's leaves (`closed_groups`), the
    # smallest first, then one of every leaf: `_cheapest` runs the first that gives what the
    # caller reads. A loss on a torque-free body's ω alone integrates ω's columns only (18
    # of the 42), a loss on the attitude the whole state's.
    one = eqx.combine(take(dyn, 0) if batched else dyn, static)
    y_flat, treedef = jax.tree_util.tree_flatten(y0s)
    groups = closed_groups(one, ts[0], take(y0s, 0))
    every = tuple(range(len(y_flat)))
    programs = sorted(set(groups) | {every}, key=lambda g: (len(g), g))

    def program(carried, dyn, y0s, S0, ts, tols):
        aug = Sensitivity(
            eqx.combine(dyn, static), tuple(m_which), offsets[: len(m_which)], P, symmetric, carried
        )
        (ys, S), ok0, result, counts = loop(aug, (y0s, tuple(S0[i] for i in carried)), ts, tols)
        out = {("ys", i): y for i, y in enumerate(jax.tree_util.tree_leaves(ys))}
        out.update({("S", i): s for i, s in zip(carried, S)})
        return dict(out, ok0=ok0, result=result, counts=counts)

    got = cheapest([functools.partial(program, c) for c in programs], dyn, y0s, S0, ts, tols)
    ok0, result, counts = got["ok0"], got["result"], got["counts"]
    leaves = [got[("ys", i)] for i in every]
    # Rows never saved (a trajectory out of steps) stay +inf, and a row that diverged is not
    # finite: their tangents are zero, and masked on both sides of the contraction, so that
    # reverse mode does not multiply inf or NaN by a zero cotangent into every shared
    # parameter's gradient.
    finite = jnp.all(
        jnp.stack([jnp.all(jnp.isfinite(y.reshape(y.shape[:2] + (-1,))), -1) for y in leaves]), 0
    )  # (N, n)

    def masked(x):
        return jnp.where(finite.reshape(finite.shape + (1,) * (x.ndim - 2)), x, 0.0)

    coef = [symmetric_part(m_dots[i]) if sym else m_dots[i] for i, sym in zip(m_which, symmetric)]
    coef = [
        c.reshape(N, -1) if batched else jnp.broadcast_to(c.reshape(1, -1), (N, c.size))
        for c in coef
    ]
    coef += [y_dots[i].reshape(N, -1) for i in y_which]
    coef += [jnp.broadcast_to(tts[0], (N, 1))] if t_live else []
    if t_live:  # the output times themselves: f(tᵢ, y(tᵢ)) dtᵢ

        def rates(m, ys, ok):
            f = jax.vmap(lambda t, y: m.vector_field(t, y, None))(ts, ys)
            return where_tree(ok, f, 0.0)

        F = jax.tree_util.tree_leaves(
            eqx.filter_vmap(rates, in_axes=(eqx.if_array(0) if batched else None, 0, 0))(
                model, jax.tree_util.tree_unflatten(treedef, leaves), ok0
            )
        )
    dys = []
    for i, y in enumerate(leaves):
        s = got[("S", i)].reshape(y.shape + (P,))
        # The tangent: S contracted with the inputs' tangents, per trajectory.
        d = jnp.einsum(
            "nt...p,np->nt...",
            masked(s),
            jnp.concatenate([c.astype(s.dtype) for c in coef], axis=1),
        )
        if t_live:
            d = d + masked(F[i]) * tts.reshape((1, -1) + (1,) * (y.ndim - 2))
        dys.append(masked(d))
    ys = jax.tree_util.tree_unflatten(treedef, leaves)
    dys = jax.tree_util.tree_unflatten(treedef, dys)
    out = (ys, ok0, result, counts)
    return out, (dys,) + tuple(np.zeros(x.shape, jax.dtypes.float0) for x in out[1:])


def sensitivity_solve(loop, model, y0s, ts, controller, model_axes) -> Trajectory:
    """A batch solved by `loop(system, y0s, ts, tols, cstatic)` (the lane loop, the kernel:
    raw outputs `ys, ok, result, counts` per trajectory, `cstatic` the controller's static
    part, `tols` its arrays), and its `Trajectory`s: the solve both strategies share.

    Differentiable in both modes by forward sensitivities: the rule of its `custom_jvp`
    (`lane_jvp`) integrates, once, the variational equations for every input element with
    a tangent by the same steps as the solve (`loop` run on a `Sensitivity`), and contracts
    them with the tangents. That contraction is linear, so `jax.grad` transposes it, and
    `jax.jacfwd`'s tangents share the one solve; the tangents never enter the loop. The
    derivative is that of the discrete solve (the step sizes are not differentiated, as in
    `diffeqsolve`)."""
    ts = checked_times(ts)
    batched = model_axes is not None
    if batched:  # every array leaf with a leading trajectory axis
        model = eqx.filter_vmap(lambda m: m, in_axes=(array_axes(model_axes),))(model)
    dyn, static = eqx.partition(model, eqx.is_array)
    y0s = promoted(dyn, y0s, ts)  # before the loop's buffers take its dtype
    tols, cstatic = eqx.partition(controller, eqx.is_array)

    def run(system, y0s, ts, tols):
        return loop(system, y0s, ts, tols, cstatic)

    @jax.custom_jvp
    def solve(dyn, y0s, ts, tols):
        return run(Plain(eqx.combine(dyn, static)), y0s, ts, tols)

    solve.defjvp(functools.partial(lane_jvp, run, static, batched), symbolic_zeros=True)
    ys, ok0, result, counts = solve(dyn, y0s, ts, tols)

    def finished(m, ys, ok, result, counts):
        return finish(m, ts, ys, ok, as_result(result), list(counts))

    return eqx.filter_vmap(finished, in_axes=(eqx.if_array(0) if batched else None, 0, 0, 0, 0))(
        model, ys, ok0, result, counts
    )
