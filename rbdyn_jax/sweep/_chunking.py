"""Chunk size and lanes: how many trajectories a chunk holds and how many lanes solve them, for
the devices at hand.
"""

from __future__ import annotations

import jax
import numpy as np

from ..integrate import (
    default_lanes,
    device_memory,
)
from ..scenario import Scenario

CPU_CHUNK, CPU_LANES = 1024, 64  # the defaults on a CPU
# On an accelerator: a chunk's share of one device at most 2²⁰ trajectories, their
# footprint within half the device's memory (8 GiB assumed where it does not say), and a
# stored zarr chunk of at most 1 GiB (Blosc compresses at most 2 GiB at once).
MAX_SHARE, MEMORY_SHARE, FALLBACK_MEMORY, MAX_STORED_CHUNK = 1 << 20, 0.5, 8 << 30, 1 << 30
# Copies of a trajectory's state and drawn values the lane solver holds per lane: the
# Runge–Kutta stages, the dense output, the step's temporaries.
LANE_COPIES = 64


def trajectory_bytes(sc: Scenario) -> tuple[int, int]:
    """`(device, stored)` bytes of one trajectory of `sc` for `chunking`.

    `device`: its footprint on the device while a chunk is solved. The lane solver saves
    every trajectory's states on the device whatever the store keeps (the summaries are
    computed from them), the program's outputs hold them again, and the outputs of the
    chunk before wait there while this one is solved: three copies of the outputs (n_times
    × 7 states, the 9 inertia components and the summaries in the scenario's dtype,
    `status` and `num_steps`), and `LANE_COPIES` of its state and drawn values in its lane.

    `stored`: its bytes in the largest stored zarr chunk, uncompressed: `quat` (n_times × 4
    values) in a store keeping every trajectory's states, 1/K of that keeping every K-th,
    and `inertia` (9 values) keeping none."""
    item = np.dtype(sc.dtype).itemsize
    values = jax.eval_shape(lambda k: sc.sample(sc.dists, k, 0), jax.random.key(0))
    drawn = sum(int(np.prod(v.shape)) for v in values.values())
    states = sc.n_times * 7 * item
    outputs = states + (9 + len(sc.summaries)) * item + 4 + 8
    quat = sc.n_times * 4 * item
    if sc.trajectories == "all":
        stored = quat
    elif sc.trajectories == "none":
        stored = 9 * item
    else:
        stored = max(-(-quat // sc.trajectories), 9 * item)
    return 3 * outputs + LANE_COPIES * (7 + drawn) * item, stored


def _power_of_two(x: int, up: bool = False) -> int:
    """The largest power of two ≤ `x` (≥ `x` with `up`), for `x` ≥ 1."""
    return 1 << (x - 1).bit_length() if up else 1 << (x.bit_length() - 1)


def chunking(
    n: int,
    *,
    platform: str,
    devices: int,
    memory: int | None,
    trajectory_bytes: tuple[int, int],
    chunk: int | None = None,
    lanes: int | None = None,
    every: int | None = None,
) -> tuple[int, int]:
    """The `(chunk, lanes)` a sweep of `n` trajectories runs with on `devices` devices of
    `platform` with `memory` bytes each (`None`: not known), given the `chunk` and `lanes`
    asked for (`None`: chosen here) and `trajectory_bytes` (`trajectory_bytes(scenario)`).

    - On a CPU: `chunk` 1024 and 64 `lanes`; each device solves its share in blocks of 8 ×
      `lanes`, one after the other.
    - On an accelerator (a GPU): a device solves its share of the chunk in one block,
      through `lanes` lanes, refilled: by default those `simulate_batch` takes for a batch
      of that size (`rbdyn_jax.integrate.default_lanes`: a lane per trajectory up to
      16,384, then a third of the share, at most 131,072). The chunk's footprint (below)
      counts a lane's working set for every trajectory, so the lanes fit. The
      chunk, when not given, is `devices` × the largest power of two that keeps a share's
      footprint (`trajectory_bytes[0]` a trajectory) within `MEMORY_SHARE` of `memory`
      (`FALLBACK_MEMORY` when not known), is at most `MAX_SHARE` (2²⁰), and keeps a
      stored zarr chunk (`trajectory_bytes[1]` a trajectory) within `MAX_STORED_CHUNK`
      (1 GiB); and no larger than `n` needs (a power of two ≥ `n / devices`).
    - With `every` = K (a store keeping every K-th trajectory's states) and K < chunk, the
      chunk is rounded down to a multiple of K, so that each chunk's sampled states fill
      whole zarr chunks of chunk / K rows (a Dask task then never shares one with another).

    A pure function of its arguments, so that the rule is tested anywhere."""
    device, stored = trajectory_bytes
    if chunk is None:
        if platform == "cpu":
            chunk = CPU_CHUNK
        else:
            fits = min(
                MAX_SHARE,
                int(MEMORY_SHARE * (memory or FALLBACK_MEMORY)) // device,
                MAX_STORED_CHUNK // (stored * devices),
            )
            share = min(_power_of_two(max(1, fits)), _power_of_two(-(-n // devices), up=True))
            chunk = share * devices
    if every is not None and every < chunk:
        chunk -= chunk % every
    if lanes is None:
        lanes = CPU_LANES if platform == "cpu" else default_lanes(-(-chunk // devices), 1, platform)
    return chunk, lanes


def _devices_info(devices: int | None) -> tuple[str, int, int | None]:
    """`(platform, count, memory)` of the first `devices` (default all) of this process's
    `jax.local_devices()`: a Dask worker's, asked before the store is made."""
    local = jax.local_devices()
    return local[0].platform, len(local) if devices is None else devices, device_memory(local[0])
