"""The devices a program runs on: one mesh, and one way to split a batch over it.

A batch is split along its leading axis, named `"batch"`, over a one-dimensional mesh of
local devices; each device runs the same function on its share, with no collective
inside it (a solver's while loops run on each device at its own pace), and the outputs
are its shares concatenated in the devices' order. The lane solver and a sweep's chunk
program both run over devices so.
"""

from collections.abc import Callable, Sequence

import jax
import numpy as np
from jax.sharding import PartitionSpec

BATCH = PartitionSpec("batch")  # split along the leading axis
WHOLE = PartitionSpec()  # every device holds all of it


def platform() -> str:
    """The platform ("cpu", "gpu", …) a program with no committed input runs on: that of
    JAX's default device where one is set (`jax.default_device`, a device or a platform's
    name), else the default backend's."""
    device = jax.config.jax_default_device
    if device is None:
        return jax.default_backend()
    name = getattr(device, "platform", device)
    return "gpu" if name in ("cuda", "rocm") else str(name)


def mesh(devices: Sequence) -> jax.sharding.Mesh:
    """The one-dimensional mesh (axis `"batch"`) of `devices`."""
    return jax.sharding.Mesh(np.asarray(devices), ("batch",))


def over_devices(fn: Callable, on: jax.sharding.Mesh, split: Sequence[bool]) -> Callable:
    """`fn` on each device of `on`, its arguments split along the leading axis where
    `split` is true (else given whole to every device), its outputs concatenated along the
    leading axis: `jax.shard_map` with no collective inside."""
    specs = tuple(BATCH if s else WHOLE for s in split)
    return jax.shard_map(fn, mesh=on, in_specs=specs, out_specs=BATCH, check_vma=False)


def on_mesh(tree, on: jax.sharding.Mesh):
    """`tree` with each array committed to devices other than `on`'s placed on all of
    `on`'s (replicated): a program over `on` (`over_devices`) refuses an argument committed
    elsewhere, such as one a user put on one device (`jax.device_put(x, device)`) or an
    output of a stored program (`traces.cached`). Uncommitted arrays and tracers stay as
    they are: the program places them."""
    devices = set(on.devices.flat)
    whole = jax.sharding.NamedSharding(on, WHOLE)

    def place(x):
        if (
            isinstance(x, jax.Array)
            and not isinstance(x, jax.core.Tracer)
            and x.committed
            and x.sharding.device_set != devices
        ):
            return jax.device_put(x, whole)
        return x

    return jax.tree_util.tree_map(place, tree)
