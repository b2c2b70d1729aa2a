"""Operations on arrays of lanes, as the lane loop (`_lane_loop`) holds them: the lane axis
last on the state's leaves, first on the controller's state.

Per-lane selects (`lane_select`, `first_select`) and takes (`take`, `take_last`), the moves
between a table of trajectories and lanes (`lanes_last`, `lanes_first`), the writes of
each lane's row into a shared buffer in the loop's two layouts (`scatter_rows` for an
accelerator, `write_rows` for XLA:CPU), and the solver's interpolant of every lane's last
step at once (`_interpolate`).
"""

import jax
import jax.numpy as jnp


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
