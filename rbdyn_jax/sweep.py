"""Monte Carlo sweeps of a scenario: chunks solved in this process or as tasks on a Dask
cluster, each written straight into a zarr store; resume; summaries; netCDF export.

The scenario (model, distributions, output times, solver settings, summaries; TOML) is
`rbdyn_jax.scenario.Scenario`. `run(scenario, n, out)` draws trajectory `i` from
`fold_in(key(seed), i)` (and every random quantity from a further `fold_in` with a hash of
its key path), so a trajectory's sample does not depend on the chunking, the devices, the
workers or the other random quantities. A chunk is solved by one compiled program: each
device takes its part with `jax.shard_map` (no collectives inside the solver loop) and
solves it in blocks by the batching `simulate_batch`'s default takes: on a GPU backend the
Pallas kernel (`Kernel`, a program of 128 trajectories each, every trajectory in its own
lane from start to end) where the scenario's model runs on rows of lanes, and otherwise the
lane solver (`Lanes(lanes, devices=1)`: `lanes` trajectories step together, and a lane
whose trajectory has finished takes the next one of its block at once). On a CPU a block is
8 × `lanes` trajectories (1024 and 64 by default); on a GPU a device solves its whole share
in one block (through the kernel, or through the lanes `simulate_batch` takes for a batch
that size), and the chunk is sized from the device's memory (`chunking`). On a CPU, because
the block shape is fixed and every drawn quantity enters as a runtime argument (the output
times and tolerances, the same for every trajectory, are constants of the program), the
results are **bitwise identical for any chunk size, any number of devices and any number
of Dask workers** at a given `lanes` (tested at 4, 16 and 64 lanes; at 8, with XLA's while
loops compiled whole, a trajectory's last bits can depend on its lane within the block).
On a GPU they are so through the kernel for any chunk (its program's arithmetic per lane
is fixed; tested on a CPU with the kernel in interpret mode), and through the lanes for a
given chunk and lanes.

In this process (the default) the chunks are solved one after the other. With
`client=dask.distributed.Client(...)` every chunk is a task (`solve_chunk`): a worker
solves it and writes its own region of the store, so nothing but two counts per chunk
passes through the scheduler; a chunk lost with its worker is run again by Dask.

The store is zarr (format 3, consolidated metadata; `xarray.open_zarr(path)` reads it),
with dimensions `trajectory × time × axis|quat_component` and CF-style metadata (`units`,
`long_name`, `description` on every variable, labelled coordinates, `status` meanings as
`flag_values`/`flag_meanings`): `omega`, `quat`, `inertia` (`trajectory × row × col`),
`status` (a `RESULTS` code per trajectory; −1 = not run yet), `num_steps`, and one
variable per summary. The scenario's `trajectories` chooses whose states (`omega`, `quat`)
are kept: all, none (the summaries and the drawn inertia only, about 100 bytes a
trajectory), or every K-th trajectory's over the dimension `sampled_trajectory`; the
program is the same, so the other variables hold the same bits whatever is kept. Its
`dtype` (float64, or float32) is what the sweep samples, solves, summarises and stores in.
`status` is written last in a chunk, so a run that is killed keeps every finished chunk and
`run(..., resume=True)` solves exactly the trajectories still marked −1. Where nothing is
written the store reads as not solved (fill values NaN and −1), every chunk is written and
carries a CRC32C checksum: `verify` lists the chunks a store lost or whose bytes changed,
the readers refuse such a store, and `resume` solves their trajectories again. An existing
store is replaced only with `overwrite=True`. `to_netcdf` exports a store to a netCDF-4
file.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import pathlib
import shutil
import time
import uuid
import warnings
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding, PartitionSpec as P

from ._plots import plots_dir
from ._program.program import Program
from ._program.xla import jit
from .integrate import (
    RESULTS,
    Kernel,
    Lanes,
    Vmap,
    default_batching,
    default_lanes,
    device_memory,
    result_code,
    result_names,
    simulate_batch,
)
from .scenario import SUMMARIES, Scenario

CONVENTIONS = (
    "Conventions of the rbdyn_jax physics guide (docs/physics.md#conventions): "
    "quat = [w, x, y, z] (scalar first), unit, rotating body "
    "components into the parent frame (O0 for rigid_body, the transport frame O1 for "
    "relative_rigid_body); omega in body components, rad/s (the rate relative to O1 for "
    "relative_rigid_body); inertia in body axes; times in s; angles in rad."
)


# ----------------------------------------------------------------------------------------
# The compiled chunk solver
# ----------------------------------------------------------------------------------------

def _solve_block(scenario: Scenario, dists, key, idx, lanes):
    """Sample and solve the trajectories `idx` (through `lanes` lanes of the lane solver);
    per-trajectory outputs."""
    values = jax.vmap(lambda i: scenario.sample(dists, key, i))(idx)
    # A non-finite draw (an overflowing lognormal, …) would fail the model's checks for the
    # whole block: solve the nominal values in its lane instead and mark it non-finite.
    ok = jnp.ones(idx.shape, bool)
    for v in values.values():
        ok = ok & jnp.all(jnp.isfinite(v.reshape(v.shape[0], -1)), axis=-1)
    nominal = {p: d.centre() for p, d in dists.items()}

    def lane(x):
        return ok.reshape((-1,) + (1,) * (x.ndim - 1))

    values = {p: jnp.where(lane(v), v, nominal[p]) for p, v in values.items()}
    models, y0s = jax.vmap(scenario.build)(values)
    # The scenario's times and tolerances are constants of the trace: the solve is then
    # traced with its checks as NaN (its inputs validated), and its loops can be stored.
    traj = simulate_batch(models, y0s, scenario.ts, model_axes=0,
                          solver=scenario.diffrax_solver,
                          stepsize_controller=scenario.stepsize_controller,
                          dt0=scenario.dt, max_steps=scenario.max_steps,
                          batching=_batching(scenario, models, y0s, lanes))
    status = jnp.where(ok, result_code(traj.result), result_code(RESULTS.nonfinite_state))

    def summaries(m, tr):
        return {name: SUMMARIES[name].fn(m, tr) for name in scenario.summaries}

    summ = jax.vmap(summaries)(models, traj)
    good = status == 0
    out = {"omega": traj.ys.omega, "quat": traj.ys.quat, "inertia": models.inertia}
    out = {k: jnp.where(lane(v) if k == "inertia" else good[:, None, None], v, jnp.nan)
           for k, v in out.items()}
    return {
        **out,
        "status": status.astype(jnp.int32),
        "num_steps": traj.stats["num_steps"].astype(_index_dtype()),
        **{k: jnp.where(good, v, jnp.nan) for k, v in summ.items()},
    }


def _batching(scenario: Scenario, models, y0s, lanes):
    """How a block is solved: `Vmap` for a fixed-step method (`LiePoissonSplitting` steps
    every trajectory in lockstep, so `Vmap` wastes nothing, and the lane solver and the
    kernel take only adaptive Runge–Kutta methods); `Kernel` where `simulate_batch`'s
    default takes it (a GPU backend, and the scenario's model field runs on rows of lanes);
    else the lane solver through `lanes` lanes on the block's device. A kernel's trajectory
    is integrated by its own lane of a program, its arithmetic the same whatever the other
    lanes hold, so a sweep's bits do not depend on its chunking either way."""
    if scenario.fixed_step:
        return Vmap()
    chosen = default_batching(scenario.diffrax_solver, scenario.stepsize_controller, None,
                              models, y0s, model_axes=0)
    return chosen if isinstance(chosen, Kernel) else Lanes(lanes, devices=1)


_PER_LANE = 8  # trajectories per lane in one CPU block (a block: 8 × lanes)
_STATES = ("omega", "quat")  # the variables `trajectories` keeps all, some or none of


def _index_dtype():
    """Integers in the program: int64 with 64-bit types enabled, else int32."""
    return jax.dtypes.canonicalize_dtype(np.int64)


def _quantum(platform: str, lanes: int) -> int:
    """What a device's share of a chunk is a multiple of: its blocks of 8 × `lanes` on a
    CPU, where a device runs its share through the same block program one block after the
    other; one trajectory on an accelerator, where one block takes the whole share at once
    (through `lanes` lanes, refilled)."""
    return _PER_LANE * lanes if platform == "cpu" else 1


def _chunk_program(sc: Scenario, lanes: int, mesh, idx, key) -> dict:
    """Sample and solve the trajectories `idx` (sharded over `mesh`'s devices) of the
    scenario `sc`, a pytree whose leaves are its distributions' parameters.

    The scenario's structure is static and exactly described by its source, so the cache
    of traced programs can store the program: a later process with the cache configured
    loads it instead of tracing it. Traced with the solves' checks as NaN (a `Program` of
    validated inputs: the scenario was validated, and a failing trajectory is reported in
    `status`), so the program holds no host callback and can be stored."""
    dists = sc.dists
    quantum = _quantum(mesh.devices.flat[0].platform, lanes)

    def per_device(idx, dists, key):
        block = idx.shape[0] if quantum == 1 else quantum
        # On a CPU, fixed blocks, one after the other: the block's program is then the same
        # for every chunk size and device count, so the results are bitwise identical
        # across them (a lane-solver loop over the whole share compiles differently for
        # each share size and rounds differently). Fixed blocks also avoid a hang in the
        # XLA runtime (all threads asleep) that one loop over a large share (2048 on 2
        # XLA:CPU host devices) runs into. On an accelerator, one block: the device's
        # whole share through `lanes` lanes, refilled.
        out = jax.lax.map(lambda b: _solve_block(sc, dists, key, b, lanes),
                          idx.reshape(-1, block))
        return jax.tree_util.tree_map(lambda x: x.reshape((-1,) + x.shape[2:]), out)

    # No collectives inside the solver loop: each device runs its own while loops.
    sharded = jax.shard_map(per_device, mesh=mesh, in_specs=(P("batch"), P(), P()),
                            out_specs=P("batch"), check_vma=False)
    # A float32 sweep's matrix products (the energies' `einsum`s, …) in full float32: at
    # JAX's default precision, NVIDIA GPUs since Ampere take them in TF32 (a 10-bit
    # mantissa), errors of 1e-4 in a float32 sweep's energy drifts where float32 gives 1e-6.
    precision = (jax.default_matmul_precision("highest") if sc.dtype == "float32"
                 else contextlib.nullcontext())
    with precision:
        return sharded(idx, dists, key)


_solve_chunk = Program(_chunk_program)


@jit
def _take(states, pos):
    """The rows `pos` of each array of `states`: a K store's sampled states, gathered on the
    device so that only they are copied to the host."""
    return [x[pos] for x in states]


@dataclasses.dataclass
class _Runner:
    """The compiled chunk solver: every call has the same padded size (one compilation)."""

    scenario: Scenario
    lanes: int
    devices: list
    chunk: int
    mesh: Any = dataclasses.field(init=False)
    solved: Scenario = dataclasses.field(init=False)  # what the chunk program solves

    def __post_init__(self):
        self.mesh = jax.sharding.Mesh(np.asarray(self.devices), ("batch",))
        # Which states a store keeps is chosen after the solve: stores keeping all, some or
        # none of them run one program, and hold the same bits.
        self.solved = self.scenario.with_settings(trajectories="all")

    @property
    def size(self) -> int:
        """The padded chunk: a multiple of the block (`_block`) × devices."""
        quantum = _quantum(self.devices[0].platform, self.lanes) * len(self.devices)
        return -(-self.chunk // quantum) * quantum

    @property
    def every(self) -> int | None:
        """K of a store keeping every K-th trajectory's states, else `None`."""
        keep = self.scenario.trajectories
        return keep if isinstance(keep, int) else None

    def launch(self, idx: np.ndarray, key) -> dict:
        """Start solving the trajectories `idx` (≤ chunk of them) and return at once: JAX
        dispatches the program and hands back its outputs before they are computed. The
        states the store does not keep are dropped on the device."""
        n = len(idx)  # padded with copies of the last index (solved, then dropped)
        full = np.concatenate([idx, np.full(self.size - n, idx[-1], idx.dtype)])
        full = full.astype(_index_dtype())
        arr = jax.make_array_from_callback(
            (self.size,), NamedSharding(self.mesh, P("batch")), lambda i: full[i])
        out = dict(_solve_chunk(self.solved, self.lanes, self.mesh, arr, key))
        states = [out.pop(k) for k in _STATES]
        if self.scenario.trajectories == "all":
            out.update(zip(_STATES, states))
        elif self.every is not None:
            # At most ceil(size / K) multiples of K among ≤ size consecutive indices: a
            # fixed number of rows, so the gather compiles once.
            pos = np.flatnonzero(idx % self.every == 0)
            pos = np.concatenate([pos, np.zeros(-(-self.size // self.every) - pos.size,
                                                pos.dtype)]).astype(_index_dtype())
            out.update(zip(_STATES, _take(states, pos)))
        return out

    def collect(self, out: dict, idx: np.ndarray) -> dict[str, np.ndarray]:
        """The outputs of `launch` for its trajectories `idx` (waits for them)."""
        sampled = idx.size if self.every is None else int(np.sum(idx % self.every == 0))
        return {k: np.asarray(v)[:sampled if k in _STATES else idx.size]
                for k, v in out.items()}


_RUNNERS: dict[tuple, _Runner] = {}


def _runner(sc: Scenario, lanes: int, devices: tuple, chunk: int) -> _Runner:
    """A compiled runner, reused by later runs of the same scenario and layout (a resumed
    or repeated run in the same process compiles nothing)."""
    quantum = _quantum(devices[0].platform, lanes) * len(devices)  # the compiled shape
    key = (json.dumps(sc.source, sort_keys=True), lanes, devices, -(-chunk // quantum))
    if key not in _RUNNERS:
        _RUNNERS.clear()  # keep one
        _RUNNERS[key] = _Runner(sc, lanes, list(devices), chunk)
    return _RUNNERS[key]


# ----------------------------------------------------------------------------------------
# Chunk size and lanes
# ----------------------------------------------------------------------------------------

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


def chunking(n: int, *, platform: str, devices: int, memory: int | None,
             trajectory_bytes: tuple[int, int], chunk: int | None = None,
             lanes: int | None = None, every: int | None = None) -> tuple[int, int]:
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
            fits = min(MAX_SHARE, int(MEMORY_SHARE * (memory or FALLBACK_MEMORY)) // device,
                       MAX_STORED_CHUNK // (stored * devices))
            share = min(_power_of_two(max(1, fits)), _power_of_two(-(-n // devices), up=True))
            chunk = share * devices
    if every is not None and every < chunk:
        chunk -= chunk % every
    if lanes is None:
        lanes = CPU_LANES if platform == "cpu" else default_lanes(-(-chunk // devices), 1,
                                                                   platform)
    return chunk, lanes


def _devices_info(devices: int | None) -> tuple[str, int, int | None]:
    """`(platform, count, memory)` of the first `devices` (default all) of this process's
    `jax.local_devices()`: a Dask worker's, asked before the store is made."""
    local = jax.local_devices()
    return local[0].platform, len(local) if devices is None else devices, device_memory(local[0])


# ----------------------------------------------------------------------------------------
# The store
# ----------------------------------------------------------------------------------------

# name: (dims, units, long_name, description); the summaries add theirs from SUMMARIES.
_VARIABLES = {
    "omega": (("trajectory", "time", "axis"), "rad/s", "body angular velocity",
              "angular velocity in body axes (relative to the transport frame O1 for "
              "relative_rigid_body); NaN where the trajectory failed"),
    "quat": (("trajectory", "time", "quat_component"), "1", "attitude quaternion",
             "unit quaternion [w, x, y, z] rotating body components into the parent frame; "
             "NaN where the trajectory failed"),
    "inertia": (("trajectory", "row", "col"), "kg m2", "inertia tensor",
                "the sampled inertia tensor in body axes"),
    "status": (("trajectory",), "1", "solver status",
               "result of the solve: 0 successful, -1 not run yet, otherwise the failure "
               "named by flag_meanings"),
    "num_steps": (("trajectory",), "1", "solver steps",
                  "steps the solver took (accepted and rejected)"),
}
_COORDS = {
    "time": ("s", "time", "output time"),
    "trajectory": ("1", "trajectory index",
                   "index i of the trajectory, drawn from fold_in(key(seed), i)"),
    "sampled_trajectory": ("1", "sampled trajectory index",
                           "index i of a trajectory whose states are stored (every K-th: i = "
                           "0, K, 2K, ...); its other variables are at trajectory = i"),
}
_LABELS = {
    "axis": (["x", "y", "z"], "body axis", "component along a body axis"),
    "quat_component": (["w", "x", "y", "z"], "quaternion component",
                       "component of the quaternion, scalar first"),
    "row": (["x", "y", "z"], "inertia tensor row", "row of the inertia tensor (body axis)"),
    "col": (["x", "y", "z"], "inertia tensor column",
            "column of the inertia tensor (body axis)"),
}
_NOT_RUN = -1


def status_meanings() -> dict[int, str]:
    """`{code: name}` of every value of a store's `status` (−1 `not_run`, then the
    `RESULTS` codes); the store carries them as `flag_values` / `flag_meanings`."""
    return {_NOT_RUN: "not_run", **result_names()}


@dataclasses.dataclass(frozen=True)
class _Location:
    """Where a store is: a local path (made absolute, for workers started elsewhere), or a
    URL fsspec opens (`s3://…`, `gs://…`, `file://…`) with its `storage_options`."""

    url: str
    options: dict

    @classmethod
    def of(cls, out: str | pathlib.Path, storage_options: dict | None = None) -> _Location:
        if "://" not in str(out):
            return cls(str(pathlib.Path(out).absolute()), {})
        options = dict(storage_options or {})
        if str(out).startswith("file://"):
            options.setdefault("auto_mkdir", True)  # object stores need no directories
        return cls(str(out), options)

    @property
    def is_url(self) -> bool:
        return "://" in self.url

    def group(self, mode: str):
        import zarr

        return zarr.open_group(self.url, mode=mode, zarr_format=3,
                               storage_options=self.options if self.is_url else None)

    def fs(self):
        """(fsspec filesystem, root path in it)."""
        import fsspec

        return fsspec.core.url_to_fs(self.url, **self.options)

    def is_store(self) -> bool:
        """Whether a sweep store is here: its group's metadata holds the consolidated
        metadata of its arrays, written last when a store is made."""
        fs, root = self.fs()
        try:
            meta = json.loads(fs.cat_file(f"{root}/zarr.json"))
        except (OSError, ValueError):
            return False
        return meta.get("node_type") == "group" and bool(meta.get("consolidated_metadata"))

    def is_empty(self) -> bool:
        fs, root = self.fs()
        return not fs.exists(root) or (fs.isdir(root) and not fs.ls(root))

    def remove(self) -> None:
        fs, root = self.fs()
        if fs.exists(root):
            fs.rm(root, recursive=True)


def _create_store(loc: _Location, sc: Scenario, n: int, chunk: int, seed: int, lanes: int):
    """A new store for `n` trajectories of `sc` in chunks of `chunk`: every variable and
    coordinate with its metadata, `status` −1 everywhere, the global attributes."""
    from ._version import __version__

    g = loc.group("w")
    every = sc.trajectories if isinstance(sc.trajectories, int) else None
    sampled = n if every is None else -(-n // every)  # rows of the states
    rows = {"omega": sampled, "quat": sampled}
    shapes = {"omega": (sc.n_times, 3), "quat": (sc.n_times, 4), "inertia": (3, 3)}
    dtypes = {"status": "int32", "num_steps": "int64"}
    meanings = status_meanings()
    names = [v for v in _VARIABLES if v not in _STATES or sc.trajectories != "none"]
    for name in [*names, *sc.summaries]:
        if name in _VARIABLES:
            dims, units, long_name, description = _VARIABLES[name]
        else:
            summary = SUMMARIES[name]
            dims, units, long_name, description = (("trajectory",), summary.units, name,
                                                   summary.description)
        length, chunk_rows = rows.get(name, n), chunk
        if every is not None and name in _STATES:
            # A chunk of trajectories holds chunk / K sampled ones (`chunking` makes the
            # chunk a multiple of K, or K is larger and it holds at most one).
            dims, chunk_rows = ("sampled_trajectory", *dims[1:]), max(1, chunk // every)
            description += (f"; stored for one trajectory in {every}: trajectories 0, "
                            f"{every}, {2 * every}, ... (the coordinate sampled_trajectory)")
        shape = (length, *shapes.get(name, ()))
        dtype = dtypes.get(name, sc.dtype)
        a = _create_array(g, name, shape, (min(chunk_rows, length),) + shape[1:], dtype,
                          np.nan if dtype == sc.dtype else _NOT_RUN, dims)
        a.attrs.update({"units": units, "long_name": long_name, "description": description})
    g["status"].attrs.update({"flag_values": list(meanings),
                              "flag_meanings": " ".join(meanings.values())})
    # The indices (their lengths here) are written a block at a time below.
    indices = {"trajectory": n, **({"sampled_trajectory": sampled} if every else {})}
    labels = {k: v for k, v in _LABELS.items()  # those of the variables it holds
              if sc.trajectories != "none" or k not in ("axis", "quat_component")}
    coords = {"time": sc.ts, **{k: None for k in indices},
              **{k: np.asarray(v[0]) for k, v in labels.items()}}
    for name, values in coords.items():
        if values is None:
            shape, dtype, fill = (indices[name],), np.int64, _NOT_RUN
        else:
            shape, dtype = values.shape, (str if values.dtype.kind == "U" else values.dtype)
            fill = "" if dtype is str else np.nan
        a = _create_array(g, name, shape, (min(shape[0], _COORD_CHUNK),), dtype, fill, (name,))
        units, long_name, description = (_COORDS[name] if name in _COORDS
                                         else (None, *_LABELS[name][1:]))
        a.attrs.update({"long_name": long_name, "description": description,
                        **({"units": units} if units else {})})
    _write_coordinates(g, sc)
    # status −1 (not run) written, so that every status chunk is in the store.
    for start in range(0, n, _COORD_CHUNK):
        _filled(g, "status")[start:start + _COORD_CHUNK] = _NOT_RUN
    # Attribute values are strings and numbers only, so that netCDF can hold them too.
    g.attrs.update({
        "title": f"rbdyn_jax Monte Carlo sweep: {sc.name}",
        "Conventions": "CF-1.11",
        "source": f"rbdyn_jax {__version__} (jax {jax.__version__})",
        "scenario_name": sc.name,
        "scenario": json.dumps(sc.source),
        "model_kind": sc.kind,
        "seed": seed,
        "n_trajectories": n,
        "chunk": chunk,
        "lanes": lanes,
        "trajectories": sc.trajectories,
        "dtype": sc.dtype,
        "summaries": " ".join(sc.summaries),
        "rbdyn_jax_conventions": CONVENTIONS,
        "rbdyn_jax_version": __version__,
        "jax_version": jax.__version__,
        "complete": 0,
    })
    _consolidate(g)
    return g


_COORD_CHUNK = 1 << 20  # the chunk of the index coordinates; rows written at a time


def _create_array(g, name: str, shape: tuple, chunks: tuple, dtype, fill, dims: tuple):
    """An array of the store: `fill` (NaN, −1 or "") wherever nothing is written, every
    chunk checksummed (CRC32C after compression), so that a chunk whose bytes changed is
    found by `verify` and fails when read."""
    from zarr.codecs import BloscCodec, Crc32cCodec

    return g.create_array(name, shape=shape, chunks=chunks, dtype=dtype, fill_value=fill,
                          dimension_names=list(dims),
                          compressors=[BloscCodec(cname="zstd", clevel=5), Crc32cCodec()])


def _filled(g, name: str):
    """The store's array `name` to write to: a chunk is written even when it holds only the
    fill value (NaN, −1), so that a chunk the store lacks is one it lost."""
    return g[name].with_config({"write_empty_chunks": True})


def _write_coordinates(g, sc: Scenario) -> None:
    """Write the store's coordinates: the output times, the axis labels and the trajectory
    indices (a block at a time)."""
    for name, (labels, *_) in _LABELS.items():
        if name in g:
            _filled(g, name)[:] = np.asarray(labels, dtype=object)
    _filled(g, "time")[:] = sc.ts
    n = g["trajectory"].shape[0]
    for start in range(0, n, _COORD_CHUNK):
        stop = min(start + _COORD_CHUNK, n)
        _filled(g, "trajectory")[start:stop] = np.arange(start, stop)
    if "sampled_trajectory" in g:
        every, sampled = sc.trajectories, g["sampled_trajectory"].shape[0]
        for start in range(0, sampled, _COORD_CHUNK):
            stop = min(start + _COORD_CHUNK, sampled)
            _filled(g, "sampled_trajectory")[start:stop] = every * np.arange(start, stop)


def _consolidate(g) -> None:
    """Consolidate the store's metadata into its group's (what `xarray.open_zarr` reads
    first, and what marks a made store). Zarr warns that format 3 does not specify it yet;
    zarr-python and xarray read it."""
    import zarr

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Consolidated metadata is currently not",
                                category=UserWarning)
        zarr.consolidate_metadata(g.store)


def _check_resumable(loc: _Location, sc: Scenario, n: int, seed: int,
                     lanes: int | None) -> int:
    """Refuse a store this run cannot continue; the lanes to continue it with: the store's,
    which `lanes` must equal when given."""
    attrs = loc.group("r").attrs
    lanes = attrs.get("lanes") if lanes is None else lanes
    want = {"trajectories": sc.trajectories, "dtype": sc.dtype, "n_trajectories": n,
            "seed": seed, "lanes": lanes, "scenario": sc.source}
    for k, v in want.items():
        have = attrs.get(k)
        if k == "scenario":  # compared as data (the order of its keys does not matter)
            same, v = json.loads(have or "null") == v, json.dumps(v)
        else:
            same = have == v
        if not same:
            raise ValueError(f"cannot resume {loc.url}: its {k} is {have!r}, this run's is "
                             f"{v!r}; use a new --out or drop --resume.")
    return lanes


def _prepare_store(loc: _Location, sc: Scenario, n: int, seed: int, resume: bool,
                   overwrite: bool, layout: Callable[[], tuple[int, int]],
                   lanes: int | None) -> int:
    """Check a store to resume, or make a new one with the `(chunk, lanes)` of `layout()`;
    the lanes the run solves with. An existing store is replaced only when asked. A local
    store is built beside its path and renamed into place, so a store at the path is always
    initialised (every status −1) and a kill at any moment leaves something `resume` can
    finish; at a URL it is built in place, its consolidated metadata last (a kill before
    that leaves no store `resume` would take)."""
    if resume and overwrite:
        raise ValueError("give at most one of `resume` and `overwrite`.")
    if resume and not loc.is_store():
        raise FileNotFoundError(f"there is no sweep store at {loc.url} to resume: drop "
                                "--resume (resume=False) to start one.")
    if loc.is_store():
        if resume:
            return _check_resumable(loc, sc, n, seed, lanes)
        if not overwrite:
            raise FileExistsError(
                f"{loc.url} already holds a sweep store: pass --overwrite (overwrite=True) "
                f"to replace it and its plots, or --resume (resume=True) to finish it.")
    elif not loc.is_empty():
        raise ValueError(f"{loc.url} exists and is not a sweep store; choose another --out.")
    chunk, lanes = layout()
    if loc.is_url:
        loc.remove()
        _create_store(loc, sc, n, chunk, seed, lanes)
        return lanes
    path = pathlib.Path(loc.url)
    tmp = path.with_name(path.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    _create_store(_Location.of(tmp), sc, n, chunk, seed, lanes)
    if overwrite:
        shutil.rmtree(plots_dir(path), ignore_errors=True)
    shutil.rmtree(path, ignore_errors=True)
    os.replace(tmp, path)
    return lanes


def _write(g, idx: np.ndarray, out: dict[str, np.ndarray], every: int | None) -> None:
    """Write the solved trajectories `idx` (ascending) into the store, one write per
    contiguous run of rows (a partly finished chunk has several); `status` last, which
    marks them done. With `every` = K, the states are those of the multiples of K in `idx`,
    at rows i / K."""
    for name in [*(k for k in out if k != "status"), "status"]:
        rows = idx[idx % every == 0] // every if every and name in _STATES else idx
        if not rows.size:
            continue
        for r in np.split(np.arange(rows.size), np.nonzero(np.diff(rows) != 1)[0] + 1):
            _filled(g, name)[int(rows[r[0]]):int(rows[r[-1]]) + 1] = out[name][r[0]:r[-1] + 1]


# ----------------------------------------------------------------------------------------
# Verifying and repairing
# ----------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Damage:
    """A chunk of a store's `variable` that is `"missing"` (not in the store though it was
    written) or `"damaged"` (its bytes fail their checksum or do not decode; `error` says
    how): the `chunk`-th along the variable's first dimension, holding the results of
    `trajectories` (empty for the time and label coordinates)."""

    variable: str
    chunk: int
    problem: str
    trajectories: range
    error: str = ""

    def __str__(self) -> str:
        t = self.trajectories
        held = (f"trajectories {t.start}..{t[-1]}" + (f" every {t.step}" if t.step > 1 else "")
                if len(t) else "no trajectory's results")
        return (f"{self.variable} chunk {self.chunk}: {self.problem} ({held})"
                + (f": {self.error}" if self.error else ""))


@dataclasses.dataclass(frozen=True)
class Verification:
    """What `verify` found in a store: its `missing` and `damaged` chunks (`Damage`), how
    many of its `n` trajectories are not solved yet (`not_run`, counting those whose
    status chunk is missing or damaged), and whether its metadata say it `complete`."""

    store: str
    n: int
    missing: tuple[Damage, ...]
    damaged: tuple[Damage, ...]
    not_run: int

    @property
    def whole(self) -> bool:
        """No chunk missing or damaged (trajectories may remain to be solved)."""
        return not self.missing and not self.damaged

    @property
    def complete(self) -> bool:
        """Whole, and every trajectory solved."""
        return self.whole and self.not_run == 0

    @property
    def trajectories(self) -> np.ndarray:
        """The indices of the trajectories whose results a missing or damaged chunk held,
        ascending: those `run(..., resume=True)` solves again."""
        held = [np.asarray(d.trajectories) for d in (*self.missing, *self.damaged)]
        return np.unique(np.concatenate([np.zeros(0, np.int64), *held]).astype(np.int64))

    def __str__(self) -> str:
        lines = [f"{self.store}: {self.n} trajectories"]
        for d in (*self.missing, *self.damaged):
            lines.append(f"  {d}")
        if not self.whole:
            lines.append(f"damaged: {len(self.missing)} missing and {len(self.damaged)} "
                         f"damaged chunk(s), holding the results of "
                         f"{self.trajectories.size} trajectories; `rbdyn sweep ... --resume` "
                         "(run(..., resume=True)) solves those again and rewrites the "
                         "chunks")
        elif self.not_run:
            lines.append(f"whole, incomplete: {self.not_run} of {self.n} trajectories not "
                         "solved yet; finish with `rbdyn sweep ... --resume`")
        else:
            lines.append("whole and complete: every chunk present and intact")
        return "\n".join(lines)


class StoreDamagedError(ValueError):
    """A sweep store has missing or damaged chunks (`verify` lists them)."""


def _held(a, name: str, chunk: int, n: int, every: int | None) -> range:
    """The trajectories whose results chunk `chunk` of the store's array `a` holds."""
    rows = a.chunks[0]
    start, stop = chunk * rows, min((chunk + 1) * rows, a.shape[0])
    dim = a.metadata.dimension_names[0]
    if dim == "trajectory" and name != "trajectory":
        return range(start, stop)
    if dim == "sampled_trajectory" and name != "sampled_trajectory":
        return range(start * every, min((stop - 1) * every + 1, n), every)
    return range(0)


def _inspect(loc: _Location, g, read: bool = True) -> Verification:
    """`verify`'s findings for the store `g` at `loc`; with `read=False` only whether each
    chunk is there (a listing and `status`), without reading the others."""
    fs, root = loc.fs()
    prefix = root.rstrip("/") + "/"
    present = {f[len(prefix):] if f.startswith(prefix) else f for f in fs.find(root)}
    status_array = g["status"]
    n, every = status_array.shape[0], g.attrs.get("trajectories")
    every = every if isinstance(every, int) else None
    status = np.full(n, _NOT_RUN, np.int64)  # not solved where unknown
    missing, damaged = [], []
    names = ["status", *sorted(k for k in g.array_keys() if k != "status")]
    for name in names:
        a = g[name]
        if f"{name}/zarr.json" not in present:
            missing.append(Damage(name, -1, "missing metadata", range(0)))
            continue
        rows = a.chunks[0]
        for i in range(-(-a.shape[0] // rows)):
            held = _held(a, name, i, n, every)
            key = f"{name}/{a.metadata.encode_chunk_key((i,) + (0,) * (a.ndim - 1))}"
            per_trajectory = len(held) > 0
            if key not in present:
                # Data are written only where solved: missing where a trajectory it holds
                # is marked solved. Status and coordinates are written when a store is made.
                if not per_trajectory or name == "status" or np.any(status[held] >= 0):
                    missing.append(Damage(name, i, "missing", held))
                continue
            if read or name == "status":
                try:
                    block = a.blocks[i]
                except Exception as e:  # a failed checksum, a truncated or garbled chunk
                    damaged.append(Damage(name, i, "damaged", held,
                                          f"{type(e).__name__}: {e}"))
                    continue
                if name == "status":
                    status[held] = block
    return Verification(loc.url, n, tuple(missing), tuple(damaged),
                        int(np.sum(status < 0)))


def verify(store: str | pathlib.Path, *, storage_options: dict | None = None) -> Verification:
    """Check every chunk of the sweep store `store` (a path or a URL): that it is there and
    that its bytes pass their checksum (CRC32C) and decode.

    A store's `status` chunks and coordinates are written when it is made; a data
    variable's chunk is written when the trajectories it holds are solved, so it is
    missing when one of them is marked solved and the chunk is not there. Reads the whole
    store once.

    **Returns:** a `Verification`: its `missing` and `damaged` chunks with the
    trajectories each holds, `not_run`, and `whole` / `complete`. `run(..., resume=True)`
    solves again exactly `Verification.trajectories` and those not run, after which the
    store is bitwise equal to an uninterrupted run's.

    **Raises:** `ValueError` if `store` is not a sweep store.
    """
    loc = _Location.of(store, storage_options)
    if not loc.is_store():
        raise ValueError(f"{store} is not a sweep store.")
    return _inspect(loc, loc.group("r"))


def _refuse_damaged(found: Verification) -> None:
    """Raise `StoreDamagedError` for a store that is not whole."""
    if not found.whole:
        raise StoreDamagedError(
            f"{found.store} is damaged: {len(found.missing)} missing and {len(found.damaged)} "
            f"damaged chunk(s), holding the results of {found.trajectories.size} "
            f"trajectories (first: {(*found.missing, *found.damaged)[0]}). List them with "
            f"`rbdyn verify {found.store}`; `rbdyn sweep ... --resume` repairs the store.")


def _warn_incomplete(found: Verification) -> None:
    if found.not_run:
        warnings.warn(f"{found.store} is incomplete: {found.not_run} of {found.n} trajectories "
                      "not solved yet (NaN, status -1); finish with `rbdyn sweep ... "
                      "--resume`.", IncompleteStoreWarning, stacklevel=3)


class IncompleteStoreWarning(UserWarning):
    """A sweep store read before all its trajectories were solved."""


def check(store: str | pathlib.Path, *, storage_options: dict | None = None) -> Verification:
    """Refuse a sweep store with missing chunks or damaged `status` chunks
    (`StoreDamagedError`, naming `rbdyn verify` and `--resume`) and warn
    (`IncompleteStoreWarning`) when trajectories remain to be solved; what `summarize`,
    `to_netcdf` and `rbdyn plot` do before reading. Lists the store and reads `status`
    only: a changed byte elsewhere is found when its chunk is read (its checksum fails),
    and by `verify`."""
    loc = _Location.of(store, storage_options)
    if not loc.is_store():
        raise ValueError(f"{store} is not a sweep store.")
    found = _inspect(loc, loc.group("r"), read=False)
    _refuse_damaged(found)
    _warn_incomplete(found)
    return found


@contextlib.contextmanager
def _reading(store, storage_options):
    """Turn an error reading the store into `StoreDamagedError` when `verify` finds the
    store damaged (a chunk whose checksum fails, say)."""
    try:
        yield
    except Exception as e:
        try:
            found = verify(store, storage_options=storage_options)
        except Exception:
            raise e from None
        if found.whole:
            raise
        try:
            _refuse_damaged(found)
        except StoreDamagedError as damaged:
            raise damaged from e


def _repair(loc: _Location, g, sc: Scenario) -> Verification:
    """Make a store `resume` can finish: delete its damaged chunks (they then read as not
    solved: NaN, status −1), mark the trajectories of every missing or damaged chunk not
    run, and rewrite a damaged coordinate. The store is marked incomplete first, so a kill
    at any moment leaves a store `verify` and `resume` take again."""
    found = _inspect(loc, g)
    if found.whole:
        return found
    if any(d.chunk < 0 for d in found.missing):
        names = ", ".join(d.variable for d in found.missing if d.chunk < 0)
        raise StoreDamagedError(f"cannot resume {loc.url}: the metadata of {names} are "
                                "missing; run the sweep again with --overwrite.")
    g.attrs["complete"] = 0
    _consolidate(g)
    fs, root = loc.fs()
    for d in found.damaged:
        a = g[d.variable]
        fs.rm(f"{root}/{d.variable}/"
              f"{a.metadata.encode_chunk_key((d.chunk,) + (0,) * (a.ndim - 1))}")
    if any(not len(d.trajectories) or d.variable in ("trajectory", "sampled_trajectory")
           for d in (*found.missing, *found.damaged)):
        _write_coordinates(g, sc)
    idx = found.trajectories
    if idx.size:
        _filled(g, "status").oindex[idx] = _NOT_RUN
    return found


# ----------------------------------------------------------------------------------------
# Running
# ----------------------------------------------------------------------------------------


@dataclasses.dataclass
class Progress:
    """What `run` reports after each chunk (to an optional `progress` callback)."""

    done: int
    total: int
    failed: int
    elapsed: float
    solved_now: int


def _scan(g, chunk: int, block: int = 1 << 22) -> tuple[int, int, list[tuple[int, ...]]]:
    """(done, failed, `(start, stop, done, failed)` of every store chunk still holding an
    unrun trajectory), reading `status` a block of whole chunks at a time."""
    n = g["status"].shape[0]
    block = chunk * max(1, block // chunk)
    done = failed = 0
    todo = []
    for b in range(0, n, block):
        status = g["status"][b:b + block]
        done += int(np.sum(status >= 0))
        failed += int(np.sum(status > 0))
        for start in range(0, status.size, chunk):
            s = status[start:start + chunk]
            if np.any(s < 0):
                todo.append((b + start, b + start + s.size, int(np.sum(s >= 0)),
                             int(np.sum(s > 0))))
    return done, failed, todo


def _launch_region(g, runner: _Runner, key, start: int, stop: int) -> tuple:
    """Start solving the trajectories of `start:stop` still marked not run
    (`_finish_region` waits for them and writes them)."""
    status = g["status"][start:stop]
    idx = start + np.nonzero(status < 0)[0]
    return runner, start, status, idx, runner.launch(idx, key) if idx.size else None


def _finish_region(g, launched: tuple) -> tuple[int, int]:
    """Write what `_launch_region` solved; the region's counts of done and of failed
    trajectories afterwards."""
    runner, start, status, idx, out = launched
    if idx.size:
        res = runner.collect(out, idx)
        _write(g, idx, res, runner.every)
        status[idx - start] = res["status"]
    return int(np.sum(status >= 0)), int(np.sum(status > 0))


def _solve_region(g, runner: _Runner, key, start: int, stop: int) -> tuple[int, int]:
    """Solve and write the trajectories of `start:stop` still marked not run; the region's
    counts of done and of failed trajectories afterwards."""
    return _finish_region(g, _launch_region(g, runner, key, start, stop))


def _x64() -> bool:
    return bool(jax.config.jax_enable_x64)


def _check_types(dtype: str, n: int, where: str, x64: bool | None = None) -> None:
    """`ValueError` unless a process with (`x64`; default: this one's setting) or without
    64-bit types can run a sweep of `n` trajectories in `dtype` (float64 values; indices
    past int32). rbdyn_jax never switches them on itself: `where` says how."""
    if _x64() if x64 is None else x64:
        return
    if dtype == "float64":
        raise ValueError(f"a float64 sweep needs 64-bit types (`jax_enable_x64`) {where}.")
    if n > np.iinfo(np.int32).max:
        raise ValueError(f"`n` = {n} trajectories need 64-bit indices (`jax_enable_x64`) "
                         f"{where}.")


def _check_workers(client, dtype: str, n: int) -> None:
    """`_check_types` on every worker of `client`, before any task is sent."""
    on = client.run(_x64)  # {worker address: whether it has 64-bit types}
    off = sorted(w for w, x64 in on.items() if not x64)
    if off:
        shown = ", ".join(off[:3]) + (", …" if len(off) > 3 else "")
        _check_types(dtype, n, f"on every worker ({len(off)} of {len(on)} lack them: "
                     f"{shown}): start the workers with JAX_ENABLE_X64=1 in their environment "
                     "(`LocalCluster(..., env={'JAX_ENABLE_X64': '1'})`, or exported before "
                     "`dask worker`)", x64=False)


def solve_chunk(store: str, source: dict, name: str, start: int, stop: int, *, seed: int,
                lanes: int, chunk: int, devices: int | None = None,
                storage_options: dict | None = None) -> tuple[int, int]:
    """Solve the trajectories `start:stop` of a sweep still marked not run, and write them
    into its `store` (`status` last): the task `run(..., client=...)` sends to a Dask worker
    for each store chunk.

    `store` is a local path or a URL fsspec opens with `storage_options`. The task runs on
    the first `devices` of the process's `jax.local_devices()` (default all). The scenario
    travels as its `source` dict (with the `dtype` and `trajectories` of the run) and is
    rebuilt here: a float64 scenario needs 64-bit types in the worker's process (start it
    with `JAX_ENABLE_X64=1` in its environment, as `rbdyn sweep --workers` does for the
    cluster it starts), and a float32 one computes in float32 either way (its arrays are
    float32 explicitly). The task changes no setting of the process. `lanes` and `chunk`
    are the store's. The compiled solver is kept
    for the process's next chunk. A task run again (its worker lost after it wrote) finds its
    trajectories done and solves nothing; one lost before it wrote `status` solves them again
    into the same region, with the same bits.

    **Returns:** `(done, failed)`: how many trajectories of `start:stop` are done and how
    many of them failed, once it has finished (the same for a task run again).
    """
    sc = Scenario.from_dict(source, default_name=name)
    _check_types(sc.dtype, stop, "on this worker: start its process with JAX_ENABLE_X64=1 "
                 "in its environment")
    local = jax.local_devices()
    devices = len(local) if devices is None else devices
    if not 1 <= devices <= len(local):
        raise ValueError(f"`devices` must be in 1..{len(local)} on this worker, "
                         f"got {devices!r}.")
    runner = _runner(sc, lanes, tuple(local[:devices]), chunk)
    g = _Location.of(store, storage_options).group("r+")
    return _solve_region(g, runner, jax.random.key(seed), start, stop)


def run(
    scenario: Scenario | str | pathlib.Path,
    n: int,
    out: str | pathlib.Path,
    *,
    chunk: int | None = None,
    seed: int = 0,
    devices: int | None = None,
    lanes: int | None = None,
    trajectories: str | int | None = None,
    dtype: str | None = None,
    resume: bool = False,
    overwrite: bool = False,
    client=None,
    storage_options: dict | None = None,
    progress: Callable[[Progress], None] | None = None,
) -> pathlib.Path | str:
    """Run `n` trajectories of `scenario` and stream them to the zarr store `out`.

    **Arguments:**

    - `scenario`: a `Scenario`, a shipped scenario name or a TOML path.
    - `n`: number of trajectories; `seed`: the random seed.
    - `chunk`: trajectories solved and written at a time, and the store's chunk along
      `trajectory` (memory ∝ chunk). `None` (default): 1024 on a CPU; on a GPU the largest
      power of two whose footprint fits the device's memory, at most 2²⁰ per device
      (`chunking`, which also rounds a chunk down to a multiple of K for `trajectories` =
      K). On a CPU each device solves its share in blocks of 8 × `lanes`, so a chunk is
      padded to a multiple of 8 × `lanes` × devices (1024 at the defaults on two devices):
      a smaller chunk solves padding, and is slower per trajectory.
    - `devices`: how many devices to shard each chunk over (default all): of this process's
      `jax.devices()`, or with `client` of each worker's.
    - `lanes`: lanes of each device's solver loop (the lane solver of `simulate_batch`; a
      lane takes the next trajectory as soon as its own has finished). `None` (default): 64
      on a CPU; on a GPU those `simulate_batch` takes for a device's share of the chunk,
      solved in one block (`chunking`). On a CPU results are bitwise identical for any
      `chunk`, `devices` and `client` at the same `lanes`. On a GPU backend a scenario
      whose model the Pallas kernel runs is solved by it (`Kernel`, as `simulate_batch`'s
      default), which has no lanes to set: `lanes` is then recorded but unused, and the
      results are bitwise identical for any `chunk`.
    - `trajectories`: which trajectories' states (`omega`, `quat`) the store keeps: `"all"`,
      `"none"` (only the summaries, `status`, `num_steps` and `inertia`), or an integer K
      (those of trajectories 0, K, 2K, …, over the dimension `sampled_trajectory`); `None`
      (default): the scenario's `[outputs] trajectories`. The other variables are kept for
      every trajectory, and hold the same bits whatever is chosen.
    - `dtype`: `"float64"` or `"float32"`, what the sweep samples, solves, summarises and
      stores in; `None` (default): the scenario's `[solver] dtype`. A float64 sweep needs
      `jax_enable_x64` in this process, or with `client` on every worker (checked before
      any task is sent); a float32 one runs with it on or off.
    - `resume`: continue an interrupted run in `out` (same scenario, n, seed, lanes,
      trajectories and dtype; `lanes=None` takes the store's), solving only the
      trajectories not yet written, in the store's own chunks.
    - `overwrite`: replace a sweep store already at `out`, and its plots folder
      (`plots_dir(out)`). Without `resume` or `overwrite` an existing store is refused.
    - `client`: a `dask.distributed.Client`: each chunk is then a task (`solve_chunk`) that
      a worker solves and writes into the store itself, so the store must be where every
      worker reaches it (a shared filesystem, or object storage by URL). A chunk lost with
      its worker is rerun by Dask. The chunk and lanes are chosen for a worker's devices.
      Default: solve in this process.
    - `storage_options`: for a URL `out` (`s3://bucket/sweep.zarr`, `gs://…`; any fsspec
      protocol whose package is installed), the options of its fsspec filesystem
      (credentials, endpoint), given to every worker too.
    - `progress`: called with a `Progress` after every chunk.

    **Returns:** the store: a `pathlib.Path` (absolute), or the URL as given; open it with
    `open_dataset(store)`. Its attributes record the chunk, lanes, trajectories and dtype
    the sweep ran with.

    **Raises:** `FileExistsError` if `out` holds a sweep store and neither `resume` nor
    `overwrite` is set (the store is left untouched); `ValueError` for invalid arguments,
    a non-store at `out`, or a store `resume` cannot continue; `ScenarioError` (a
    `ValueError`) for a `trajectories` or `dtype` the scenario cannot take, naming its key
    (`solver.rtol` finer than float32 resolves, say).
    """
    sc = scenario if isinstance(scenario, Scenario) else Scenario.load(scenario)
    sc = sc.with_settings(dtype=dtype, trajectories=trajectories)
    for name, v in (("n", n), ("chunk", chunk), ("lanes", lanes)):
        if v is None and name != "n":
            continue
        if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 1:
            raise ValueError(f"`{name}` must be a positive integer, got {v!r}.")
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"`seed` must be a non-negative integer, got {seed!r}.")
    if client is None:
        _check_types(sc.dtype, n, "in this process: call "
                     "`jax.config.update('jax_enable_x64', True)` first")
        all_devices = jax.devices()
        devices = len(all_devices) if devices is None else devices
        if isinstance(devices, bool) or not 1 <= devices <= len(all_devices):
            raise ValueError(f"`devices` must be in 1..{len(all_devices)} (jax.devices()), "
                             f"got {devices!r}.")
    else:
        if devices is not None and (isinstance(devices, bool) or devices < 1):
            raise ValueError(f"`devices` must be a positive integer, got {devices!r}.")
        _check_workers(client, sc.dtype, n)

    def layout() -> tuple[int, int]:
        """The chunk and lanes of a new store, for this process's devices or a worker's."""
        if client is None:
            info = (all_devices[0].platform, devices, device_memory(all_devices[0]))
        elif chunk is None or lanes is None:
            info = client.submit(_devices_info, devices, pure=False).result()
        else:
            info = ("cpu", devices or 1, None)  # both given: only a K rounds the chunk
        platform, count, memory = info
        return chunking(n, platform=platform, devices=count, memory=memory,
                        trajectory_bytes=trajectory_bytes(sc), chunk=chunk, lanes=lanes,
                        every=sc.trajectories if isinstance(sc.trajectories, int) else None)

    loc = _Location.of(out, storage_options)
    lanes = _prepare_store(loc, sc, n, seed, resume, overwrite, layout, lanes)
    g = loc.group("r+")
    if resume:  # missing and damaged chunks marked not run, to be solved again
        _repair(loc, g, sc)
    # One task per zarr chunk of the store (a resumed run keeps the store's chunking, so no
    # two tasks write one zarr chunk).
    chunk = g["status"].chunks[0]
    done, failed, todo = _scan(g, chunk)
    t_start = time.perf_counter()

    def report(region: tuple[int, ...], counts: tuple[int, int]) -> None:
        """A region finished: the trajectories it solved are its done count now less then
        (a rerun task that found them written counts them once)."""
        nonlocal done, failed
        solved = counts[0] - region[2]
        done += solved
        failed += counts[1] - region[3]
        if progress is not None and solved:
            progress(Progress(done, n, failed, time.perf_counter() - t_start, solved))

    if client is None:
        runner = _runner(sc, lanes, tuple(all_devices[:devices]), chunk)
        key = jax.random.key(seed)
        # The devices solve a region while this thread writes the one before.
        solving = None
        for region in todo:
            launched = (region, _launch_region(g, runner, key, *region[:2]))
            if solving is not None:
                report(solving[0], _finish_region(g, solving[1]))
            solving = launched
        if solving is not None:
            report(solving[0], _finish_region(g, solving[1]))
    else:
        _run_on_dask(client, todo, report, loc.url, sc, seed=seed, lanes=lanes, chunk=chunk,
                     devices=devices, storage_options=loc.options or None)
    g.attrs["complete"] = 1
    _consolidate(g)
    return loc.url if loc.is_url else pathlib.Path(loc.url)


def _run_on_dask(client, todo, report, store, sc, **kw) -> None:
    """Each chunk a task writing its own region; progress as the tasks complete."""
    from distributed import as_completed

    token = uuid.uuid4().hex[:8]
    futures = {client.submit(solve_chunk, store, sc.source, sc.name, *region[:2], **kw,
                             key=f"rbdyn_jax-sweep-{token}-{region[0]}", pure=False): region
               for region in todo}
    try:
        for future in as_completed(futures):
            report(futures[future], future.result())
            future.release()
    finally:
        client.cancel(futures)


# ----------------------------------------------------------------------------------------
# Reading
# ----------------------------------------------------------------------------------------


def open_dataset(store: str | pathlib.Path, *, storage_options: dict | None = None, **kwargs):
    """The sweep store at `store` (a path or a URL) as an `xarray.Dataset` (lazy: Dask
    arrays, nothing is loaded); `kwargs` go to `xarray.open_zarr` (e.g. `chunks`)."""
    import xarray as xr

    loc = _Location.of(store, storage_options)
    return xr.open_zarr(loc.url, storage_options=loc.options or None, **kwargs)


_EXACT_ROWS = 1 << 25  # quantiles exact (in memory, 8 bytes a row) up to this many values


def summarize(store: str | pathlib.Path, quantiles=(0.05, 0.5, 0.95), *,
              rows: int = 1 << 20, storage_options: dict | None = None) -> dict:
    """Counts per status and, for every summary, count/mean/std/min/quantiles/max over the
    successful trajectories (finite values).

    The store (a path or a URL) is read through `xarray.open_zarr` and Dask, `rows` trajectories at
    a time (rounded to whole store chunks), reading only the `(trajectory,)` columns: a store of any
    size is summarised without loading it whole, on the active Dask scheduler (a
    `distributed.Client` if one is set up). Quantiles are exact while a summary has at most 2²⁵
    successful values (they are then gathered, 8 bytes each); beyond, they are Dask's approximation
    merged from per-block quantiles (`dask.array.percentile`).

    **Returns:** `{"n", "status": {name: count}, "summaries": {name: {count, mean, std,
    min, qNN…, max}}, "scenario", "complete"}`.
    """
    found = check(store, storage_options=storage_options)
    with _reading(store, storage_options):
        stats = _summarize(store, quantiles, rows, storage_options)
    return {**stats, "complete": stats["complete"] and found.complete}


def _summarize(store, quantiles, rows, storage_options) -> dict:
    import dask
    import dask.array as da

    ds = open_dataset(store, storage_options=storage_options, chunks={})
    stored = ds.status.chunks[0][0]
    ds = ds.chunk({"trajectory": stored * max(1, rows // stored)})
    status = ds.status.data
    meanings = dict(zip(ds.status.attrs["flag_values"], ds.status.attrs["flag_meanings"].split()))
    names = ds.attrs["summaries"].split()
    ok = status == 0
    lazy = {"status": [da.sum(status == c) for c in meanings]}
    good = {}
    for name in names:
        x = ds[name].data
        good[name] = ok & da.isfinite(x)
        xs = da.where(good[name], x, np.nan)
        lazy[name] = [da.sum(good[name]), da.nanmean(xs), da.nanstd(xs, ddof=1),
                      da.nanmin(xs), da.nanmax(xs)]
    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns: handled below
        (computed,) = dask.compute(lazy)
    counts = {meanings[c]: int(k) for c, k in zip(meanings, computed["status"]) if k}
    stats = {}
    for name in names:
        count, mean, std, lo, hi = computed[name]
        row = {"count": int(count)}
        if count:
            x = ds[name].data[good[name]]
            if count <= _EXACT_ROWS:
                qs = np.quantile(x.compute(), quantiles)
            else:
                qs = da.percentile(x.compute_chunk_sizes(), 100 * np.asarray(quantiles)).compute()
            row.update(mean=float(mean), std=float(std) if count > 1 else 0.0,
                       min=float(lo), max=float(hi))
            row.update({f"q{round(100 * q):02d}": float(v) for q, v in zip(quantiles, qs)})
        stats[name] = row
    return {"n": int(status.size), "status": counts, "summaries": stats,
            "scenario": ds.attrs["scenario_name"], "complete": bool(ds.attrs["complete"])}


def to_netcdf(store: str | pathlib.Path, path: str | pathlib.Path, *,
              overwrite: bool = False, storage_options: dict | None = None) -> pathlib.Path:
    """Write the sweep `store` (a path or a URL) to the local netCDF-4 file `path` (engine netCDF4,
    zlib-compressed), streamed chunk by chunk through Dask; `xarray.open_dataset(path)` reads it
    back equal to `open_dataset(store)`, attributes included.

    The file is written beside `path` and renamed into place, so a failed export leaves no
    broken file. An existing `path` is refused unless `overwrite`.

    **Returns:** `path`. **Raises:** `FileExistsError` if `path` exists and not
    `overwrite`; `ValueError` if `store` is not a sweep store.
    """
    path = pathlib.Path(path)
    check(store, storage_options=storage_options)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists: pass --overwrite (overwrite=True) to replace it.")
    ds = open_dataset(store, storage_options=storage_options, chunks={})
    for v in ds.variables.values():
        keep = {k: v.encoding[k] for k in ("dtype", "_FillValue") if k in v.encoding}
        if v.dtype.kind in "fiu" and v.ndim:
            keep.update(zlib=True, complevel=4)
        v.encoding = keep
    # CF: flag_values has the type of its variable.
    status = ds.variables["status"]
    status.attrs["flag_values"] = np.asarray(status.attrs["flag_values"], status.dtype)
    tmp = path.with_name(path.name + ".partial")
    try:
        with _reading(store, storage_options):
            ds.to_netcdf(tmp, engine="netcdf4", format="NETCDF4")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


__all__ = [
    "Damage",
    "IncompleteStoreWarning",
    "Progress",
    "StoreDamagedError",
    "Verification",
    "check",
    "chunking",
    "open_dataset",
    "plots_dir",
    "run",
    "solve_chunk",
    "status_meanings",
    "summarize",
    "to_netcdf",
    "trajectory_bytes",
    "verify",
]
