"""A batch's raw solve on each device of a mesh: `dealt`, which the lane loop and the
kernel share (`Lanes(devices=…)`, `Kernel(devices=…)`)."""

import equinox as eqx
import jax
import jax.numpy as jnp

from .._program.devices import over_devices


def dealt(run, system, y0s, ts, tols, cstatic, batched, mesh):
    """`run(system, y0s, ts, controller)` (the lane loop or the kernel: raw outputs per
    trajectory) on each device's share of the batch (`shard_map`: every device runs its
    own solve, no collective inside it), its outputs in the batch's order. The batch is
    padded to a multiple of the devices by repeating its last trajectory and dealt out in
    turn (device d takes trajectories d, d + devices, …), so that a batch ordered by
    difficulty (a sweep over spin rates, say) still gives every device an equal share of
    the work."""
    n_dev = mesh.devices.size
    N = jax.tree_util.tree_leaves(y0s)[0].shape[0]
    pad = -N % n_dev

    def padded(x):  # padded to P = N + pad, dealt: row d·(P/devices) + i holds i·devices + d
        x = jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]) if pad else x
        return x.reshape((-1, n_dev) + x.shape[1:]).swapaxes(0, 1).reshape(x.shape)

    def collected(x):  # the inverse of the deal, without the padding
        return x.reshape((n_dev, -1) + x.shape[1:]).swapaxes(0, 1).reshape(x.shape)[:N]

    y0s = jax.tree_util.tree_map(padded, y0s)
    dyn, static = eqx.partition(system, eqx.is_array)
    if batched:
        dyn = jax.tree_util.tree_map(padded, dyn)

    def local(dyn, y0s, ts, tols):
        return run(eqx.combine(dyn, static), y0s, ts, eqx.combine(tols, cstatic))

    out = over_devices(local, mesh, (batched, True, False, False))(dyn, y0s, ts, tols)
    return jax.tree_util.tree_map(collected, out)
