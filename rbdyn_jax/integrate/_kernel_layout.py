"""How the kernel lays a batch out: in blocks of lanes, a block a program (`kernel_block`:
128 lanes on a GPU, a lane a Triton thread, `triton_warps`; else the whole batch up to
1024), and in rows, each scalar of a pytree with a leading trajectory axis a row of lanes
(`_flat_rows`), rebuilt in the kernel as object arrays of rows (`_unflat_rows`, as
`_rows.rowwise` takes them), read and replaced in order (`_elements`, `_with_elements`)
and selected per lane (`_select`). The kernel moves its rows through few memory
operations (`_packed`, `read_rows`, `write_rows`): the per-lane rows of a dtype in one 2-D
array read by one load in a loop, a value every lane shares as one element, and the rows
it writes by one store in a loop. Triton's coalescing pass costs each memory operation a
pass over the whole kernel, which is most of the kernel's compilation.
"""

import jax
import jax.numpy as jnp
import numpy as np

from ._rows import objects

# The block on a GPU: 128 lanes a program, 4 warps (`benchmarks/gpu.py --blocks` measures
# other widths, each a lane a thread); elsewhere
# (interpret mode, where a program's cost hardly depends on its width) the whole batch in
# one program, up to `MAX_INTERPRET_BLOCK` lanes.
GPU_BLOCK, MAX_INTERPRET_BLOCK = 128, 1024


def next_power_of_two(n: int) -> int:
    return 1 << max(0, int(n) - 1).bit_length()


def triton_warps(block: int) -> int:
    """Triton's warps for a program of `block` lanes: a lane a thread (32 a warp), at
    least one warp and at most 32 (1024 threads, CUDA's most a block)."""
    return min(32, max(1, block // 32))


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


def _packed(rows):
    """The kernel's inputs for `rows` (`(P,)` a row of lanes, `(1,)` a value every lane
    shares): the per-lane rows of each dtype stacked into one `(R, P)` array (R a power of
    two, the rest zeros), each shared value as it is; and for each input, the positions in
    `rows` of the rows it holds."""
    groups, shared = {}, []
    for k, r in enumerate(rows):
        if r.shape[0] == 1:
            shared.append(k)
        else:
            groups.setdefault(r.dtype, []).append(k)
    inputs, where = [], []
    for ks in groups.values():
        stack = [rows[k] for k in ks]
        stack += [jnp.zeros_like(stack[0])] * (next_power_of_two(len(ks)) - len(ks))
        inputs.append(jnp.stack(stack))
        where.append(ks)
    for k in shared:
        inputs.append(rows[k])
        where.append([k])
    return inputs, where


def read_rows(ref, count: int) -> list:
    """In the kernel, rows 0 … `count` − 1 of a 2-D block `ref`, by one load in a loop: each
    row is kept where the loop's index is its own (a select), bit for bit."""

    def body(r, rows):
        x = ref[r, :]
        return tuple(jnp.where(r == k, x, rows[k]) for k in range(count))

    zeros = tuple(jnp.zeros(ref.shape[1:], ref.dtype) for _ in range(count))
    return list(jax.lax.fori_loop(0, count, body, zeros))


def write_rows(ref, rows: list, at) -> None:
    """In the kernel, `rows` into the flat block `ref`, row k at the positions `at(k)` (`k`
    traced), by one store in a loop: the row stored is picked by selects on the index."""

    def body(c, carry):
        v = rows[0]
        for k in range(1, len(rows)):
            v = jnp.where(c == k, rows[k], v)
        ref[at(c)] = v
        return carry

    jax.lax.fori_loop(0, len(rows), body, 0)
