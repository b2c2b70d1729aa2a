"""Monte Carlo sweeps of a scenario: chunks solved in this process or as tasks on a Dask
cluster, each written straight into a zarr store; resume; summaries; netCDF export.

The scenario (model, distributions, output times, solver settings, summaries; TOML) is
`rbdyn_jax.scenario.Scenario`. `run(scenario, n, out)` draws trajectory `i` from
`fold_in(key(seed), i)` (and every random quantity from a further `fold_in` with a hash of
its key path), so a trajectory's sample does not depend on the chunking, the devices, the
workers or the other random quantities. A chunk is solved by one compiled program: each
device takes its part with `jax.shard_map` (no collectives inside the solver loop) and
runs it through the lane solver (`simulate_batch(..., batching=Lanes(lanes, devices=1))`)
in fixed blocks of 8 × `lanes` trajectories: `lanes` trajectories step together, and a
lane whose trajectory has finished takes the next one of its block at once. Because the
block shape is fixed and every drawn quantity enters as a runtime argument (the output
times and tolerances, the same for every trajectory, are constants of the program), the
results are **bitwise identical for any chunk size, any number of devices and any number
of Dask workers** at a given `lanes` (tested at 4, 16 and 64 lanes; at 8, with XLA's while
loops compiled whole, a trajectory's last bits can depend on its lane within the block).

In this process (the default) the chunks are solved one after the other. With
`client=dask.distributed.Client(...)` every chunk is a task (`solve_chunk`): a worker
solves it and writes its own region of the store, so nothing but two counts per chunk
passes through the scheduler; a chunk lost with its worker is run again by Dask.

The store is zarr (format 2, consolidated metadata; `xarray.open_zarr(path)` reads it),
with dimensions `trajectory × time × axis|quat_component` and CF-style metadata (`units`,
`long_name`, `description` on every variable, labelled coordinates, `status` meanings as
`flag_values`/`flag_meanings`): `omega`, `quat`, `inertia` (`trajectory × row × col`),
`status` (a `RESULTS` code per trajectory; −1 = not run yet), `num_steps`, and one
variable per summary. `status` is written last in a chunk, so a run that is killed keeps
every finished chunk and `run(..., resume=True)` solves exactly the trajectories still
marked −1. An existing store is replaced only with `overwrite=True`. `to_netcdf` exports a
store to a netCDF-4 file.
"""

from __future__ import annotations

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

from . import _traces
from ._checks import checks_as_nan
from ._plots import plots_dir
from .integrate import (
    MODE_DEPENDENT_JITS,
    RESULTS,
    Lanes,
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
                          max_steps=scenario.max_steps, batching=Lanes(lanes, devices=1))
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
        "num_steps": traj.stats["num_steps"].astype(jnp.int64),
        **{k: jnp.where(good, v, jnp.nan) for k, v in summ.items()},
    }


_PER_LANE = 8  # trajectories per lane in one lane-solver block (a block: 8 × lanes)


# The scenarios of this process's runners by their source's JSON text (`_Runner`).
_SCENARIOS: dict[str, Scenario] = {}


def _chunk_program(source: str, lanes: int, mesh, idx, dists, key) -> dict:
    """Sample and solve the trajectories `idx` (sharded over `mesh`'s devices) of the
    scenario whose `source` is the JSON text `source`, with `dists` its distributions.

    The scenario enters as its source text, which the trace cache can describe exactly
    (`_traces`): a later process with the cache configured loads this program instead of
    tracing it. Traced with the solves' checks as NaN (`checks_as_nan`: the scenario was
    validated, and a failing trajectory is reported in `status`), so the program holds no
    host callback and can be stored."""
    sc = _SCENARIOS[source]

    def per_device(idx, dists, key):
        # Fixed blocks of _PER_LANE × lanes trajectories, one after the other: the
        # block's program is then the same for every chunk size and device count, so
        # the results are bitwise identical across them (a lane-solver loop over the
        # whole share compiles differently for each share size and rounds differently).
        # Fixed blocks also avoid a hang in the XLA runtime (all threads asleep) that
        # one loop over a large share (2048 on 2 XLA:CPU host devices) runs into.
        out = jax.lax.map(lambda b: _solve_block(sc, dists, key, b, lanes),
                          idx.reshape(-1, _PER_LANE * lanes))
        return jax.tree_util.tree_map(lambda x: x.reshape((-1,) + x.shape[2:]), out)

    # No collectives inside the solver loop: each device runs its own while loops.
    sharded = jax.shard_map(per_device, mesh=mesh, in_specs=(P("batch"), P(), P()),
                            out_specs=P("batch"), check_vma=False)
    with checks_as_nan(jitted=MODE_DEPENDENT_JITS):
        return sharded(idx, dists, key)


_solve_chunk = _traces.cached(_chunk_program)


@dataclasses.dataclass
class _Runner:
    """The compiled chunk solver: every call has the same padded size (one compilation)."""

    scenario: Scenario
    lanes: int
    devices: list
    chunk: int
    source: str  # the scenario's source as JSON text (`_chunk_program`)
    mesh: Any = dataclasses.field(init=False)

    def __post_init__(self):
        self.mesh = jax.sharding.Mesh(np.asarray(self.devices), ("batch",))
        _SCENARIOS.clear()  # as `_RUNNERS`, keep one
        _SCENARIOS[self.source] = self.scenario

    @property
    def size(self) -> int:
        """The padded chunk: a multiple of _PER_LANE × lanes × devices."""
        quantum = _PER_LANE * self.lanes * len(self.devices)
        return -(-self.chunk // quantum) * quantum

    def launch(self, idx: np.ndarray, key) -> dict:
        """Start solving the trajectories `idx` (≤ chunk of them) and return at once: JAX
        dispatches the program and hands back its outputs before they are computed."""
        n = len(idx)  # padded with copies of the last index (solved, then dropped)
        full = np.concatenate([idx, np.full(self.size - n, idx[-1], idx.dtype)])
        arr = jax.make_array_from_callback(
            (self.size,), NamedSharding(self.mesh, P("batch")), lambda i: full[i])
        return _solve_chunk(self.source, self.lanes, self.mesh, arr, self.scenario.dists, key)

    @staticmethod
    def collect(out: dict, n: int) -> dict[str, np.ndarray]:
        """The outputs of `launch` for its `n` trajectories (waits for them)."""
        return {k: np.asarray(v)[:n] for k, v in out.items()}


_RUNNERS: dict[tuple, _Runner] = {}


def _runner(sc: Scenario, lanes: int, devices: tuple, chunk: int) -> _Runner:
    """A compiled runner, reused by later runs of the same scenario and layout (a resumed
    or repeated run in the same process compiles nothing)."""
    quantum = _PER_LANE * lanes * len(devices)  # the compiled shape: the padded chunk
    source = json.dumps(sc.source, sort_keys=True)
    key = (source, lanes, devices, -(-chunk // quantum))
    if key not in _RUNNERS:
        _RUNNERS.clear()  # keep one
        _RUNNERS[key] = _Runner(sc, lanes, list(devices), chunk, source)
    return _RUNNERS[key]


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

        return zarr.open_group(self.url, mode=mode, zarr_format=2,
                               storage_options=self.options if self.is_url else None)

    def fs(self):
        """(fsspec filesystem, root path in it)."""
        import fsspec

        return fsspec.core.url_to_fs(self.url, **self.options)

    def is_store(self) -> bool:
        """Whether a whole sweep store is here (its consolidated metadata, written last
        when a store is made, is there)."""
        fs, root = self.fs()
        return fs.isfile(f"{root}/.zgroup") and fs.isfile(f"{root}/.zmetadata")

    def is_empty(self) -> bool:
        fs, root = self.fs()
        return not fs.exists(root) or (fs.isdir(root) and not fs.ls(root))

    def remove(self) -> None:
        fs, root = self.fs()
        if fs.exists(root):
            fs.rm(root, recursive=True)


def _create_store(loc: _Location, sc: Scenario, n: int, chunk: int, seed: int, lanes: int):
    import zarr

    from ._version import __version__

    g = loc.group("w")
    shapes = {"omega": (n, sc.n_times, 3), "quat": (n, sc.n_times, 4), "inertia": (n, 3, 3),
              "status": (n,), "num_steps": (n,)}
    dtypes = {"status": "int32", "num_steps": "int64"}
    meanings = status_meanings()
    for name in [*_VARIABLES, *sc.summaries]:
        if name in _VARIABLES:
            dims, units, long_name, description = _VARIABLES[name]
        else:
            summary = SUMMARIES[name]
            dims, units, long_name, description = (("trajectory",), summary.units, name,
                                                   summary.description)
        shape = shapes.get(name, (n,))
        dtype = dtypes.get(name, "float64")
        a = g.create_array(name, shape=shape, chunks=(min(chunk, n),) + shape[1:], dtype=dtype,
                           fill_value=None if dtype != "float64" else np.nan)
        a.attrs.update({"_ARRAY_DIMENSIONS": list(dims), "units": units,
                        "long_name": long_name, "description": description})
    g["status"].attrs.update({"flag_values": list(meanings),
                              "flag_meanings": " ".join(meanings.values())})
    coords = {"time": sc.ts, "trajectory": None,  # the index: written a block at a time
              **{k: np.asarray(v[0]) for k, v in _LABELS.items()}}
    for name, values in coords.items():
        shape, dtype = ((n,), np.int64) if values is None else (values.shape, values.dtype)
        a = g.create_array(name, shape=shape, chunks=(min(shape[0], 1 << 20),), dtype=dtype,
                           fill_value=None)
        if values is not None:
            a[:] = values
        units, long_name, description = (_COORDS[name] if name in _COORDS
                                         else (None, *_LABELS[name][1:]))
        a.attrs.update({"_ARRAY_DIMENSIONS": [name], "long_name": long_name,
                        "description": description,
                        **({"units": units} if units else {})})
    for start in range(0, n, 1 << 20):  # a block at a time: status −1 (not run: written,
        stop = min(start + (1 << 20), n)  # not a fill value) and the trajectory index
        g["status"][start:stop] = _NOT_RUN
        g["trajectory"][start:stop] = np.arange(start, stop)
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
        "summaries": " ".join(sc.summaries),
        "rbdyn_jax_conventions": CONVENTIONS,
        "rbdyn_jax_version": __version__,
        "jax_version": jax.__version__,
        "complete": 0,
    })
    zarr.consolidate_metadata(g.store)
    return g


def _check_resumable(loc: _Location, sc: Scenario, n: int, seed: int, lanes: int):
    g = loc.group("r")
    want = {"scenario": json.dumps(sc.source), "n_trajectories": n, "seed": seed,
            "lanes": lanes}
    for k, v in want.items():
        if g.attrs.get(k) != v:
            raise ValueError(f"cannot resume {loc.url}: its {k} is {g.attrs.get(k)!r}, this run's "
                             f"is {v!r}; use a new --out or drop --resume.")


def _prepare_store(loc: _Location, sc: Scenario, n, chunk, seed, lanes, resume,
                   overwrite) -> None:
    """Check a store to resume, or make a new one. An existing store is replaced only when
    asked. A local store is built beside its path and renamed into place, so a store at the
    path is always initialised (every status −1) and a kill at any moment leaves something
    `resume` can finish; at a URL it is built in place, its consolidated metadata last (a
    kill before that leaves no store `resume` would take)."""
    if resume and overwrite:
        raise ValueError("give at most one of `resume` and `overwrite`.")
    if loc.is_store():
        if resume:
            _check_resumable(loc, sc, n, seed, lanes)
            return
        if not overwrite:
            raise FileExistsError(
                f"{loc.url} already holds a sweep store: pass --overwrite (overwrite=True) "
                f"to replace it and its plots, or --resume (resume=True) to finish it.")
    elif not loc.is_empty():
        raise ValueError(f"{loc.url} exists and is not a sweep store; choose another --out.")
    if loc.is_url:
        loc.remove()
        _create_store(loc, sc, n, chunk, seed, lanes)
        return
    path = pathlib.Path(loc.url)
    tmp = path.with_name(path.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    _create_store(_Location.of(tmp), sc, n, chunk, seed, lanes)
    if overwrite:
        shutil.rmtree(plots_dir(path), ignore_errors=True)
    shutil.rmtree(path, ignore_errors=True)
    os.replace(tmp, path)


def _write(g, idx: np.ndarray, out: dict[str, np.ndarray]) -> None:
    """Write the solved trajectories `idx` (ascending) into the store, one write per
    contiguous run (a partly finished chunk has several); `status` last, which marks them
    done."""
    runs = np.split(np.arange(idx.size), np.nonzero(np.diff(idx) != 1)[0] + 1)
    for name in [*(k for k in out if k != "status"), "status"]:
        for r in runs:
            g[name][int(idx[r[0]]):int(idx[r[-1]]) + 1] = out[name][r[0]:r[-1] + 1]


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
    return start, status, idx, runner.launch(idx, key) if idx.size else None


def _finish_region(g, launched: tuple) -> tuple[int, int]:
    """Write what `_launch_region` solved; the region's counts of done and of failed
    trajectories afterwards."""
    start, status, idx, out = launched
    if idx.size:
        res = _Runner.collect(out, idx.size)
        _write(g, idx, res)
        status[idx - start] = res["status"]
    return int(np.sum(status >= 0)), int(np.sum(status > 0))


def _solve_region(g, runner: _Runner, key, start: int, stop: int) -> tuple[int, int]:
    """Solve and write the trajectories of `start:stop` still marked not run; the region's
    counts of done and of failed trajectories afterwards."""
    return _finish_region(g, _launch_region(g, runner, key, start, stop))


def solve_chunk(store: str, source: dict, name: str, start: int, stop: int, *, seed: int,
                lanes: int, chunk: int, devices: int | None = None,
                storage_options: dict | None = None) -> tuple[int, int]:
    """Solve the trajectories `start:stop` of a sweep still marked not run, and write them
    into its `store` (`status` last): the task `run(..., client=...)` sends to a Dask worker
    for each store chunk.

    `store` is a local path or a URL fsspec opens with `storage_options`. The task runs in float64
    (it sets `jax_enable_x64` in its process) on the first `devices` of the process's
    `jax.local_devices()` (default all). The scenario travels as its `source` dict and is rebuilt
    here, after float64 is on; the compiled solver is kept for the process's next chunk. A task run
    again (its worker lost after it wrote) finds its trajectories done and solves nothing; one lost
    before it wrote `status` solves them again into the same region, with the same bits.

    **Returns:** `(done, failed)`: how many trajectories of `start:stop` are done and how
    many of them failed, once it has finished (the same for a task run again).
    """
    jax.config.update("jax_enable_x64", True)
    sc = Scenario.from_dict(source, default_name=name)
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
    chunk: int = 1024,
    seed: int = 0,
    devices: int | None = None,
    lanes: int = 64,
    resume: bool = False,
    overwrite: bool = False,
    client=None,
    storage_options: dict | None = None,
    progress: Callable[[Progress], None] | None = None,
) -> pathlib.Path | str:
    """Run `n` trajectories of `scenario` and stream them to the zarr store `out`.

    **Arguments:**

    - `scenario`: a `Scenario`, a shipped scenario name or a TOML path.
    - `n`: number of trajectories; `chunk`: trajectories solved and written at a time, and
      the store's chunk along `trajectory` (memory ∝ chunk); `seed`: the random seed. Each
      device solves its share in blocks of 8 × `lanes`, so a chunk is padded to a multiple
      of 8 × `lanes` × devices (1024 at the defaults on two devices): a smaller chunk
      solves padding, and is slower per trajectory.
    - `devices`: how many devices to shard each chunk over (default all): of this process's
      `jax.devices()`, or with `client` of each worker's.
    - `lanes`: lanes of each device's solver loop (the lane solver of `simulate_batch`; a
      lane takes the next trajectory as soon as its own has finished). Results are bitwise
      identical for any `chunk`, `devices` and `client` at the same `lanes`.
    - `resume`: continue an interrupted run in `out` (same scenario, n, seed, lanes),
      solving only the trajectories not yet written, in the store's own chunks.
    - `overwrite`: replace a sweep store already at `out`, and its plots folder
      (`plots_dir(out)`). Without `resume` or `overwrite` an existing store is refused.
    - `client`: a `dask.distributed.Client`: each chunk is then a task (`solve_chunk`) that
      a worker solves and writes into the store itself, so the store must be where every
      worker reaches it (a shared filesystem, or object storage by URL). A chunk lost with
      its worker is rerun by Dask. Default: solve in this process.
    - `storage_options`: for a URL `out` (`s3://bucket/sweep.zarr`, `gs://…`; any fsspec
      protocol whose package is installed), the options of its fsspec filesystem
      (credentials, endpoint), given to every worker too.
    - `progress`: called with a `Progress` after every chunk.

    **Returns:** the store: a `pathlib.Path` (absolute), or the URL as given; open it with
    `open_dataset(store)`.

    **Raises:** `FileExistsError` if `out` holds a sweep store and neither `resume` nor
    `overwrite` is set (the store is left untouched); `ValueError` for invalid arguments,
    a non-store at `out`, or a store `resume` cannot continue.
    """
    sc = scenario if isinstance(scenario, Scenario) else Scenario.load(scenario)
    for name, v in (("n", n), ("chunk", chunk), ("lanes", lanes)):
        if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 1:
            raise ValueError(f"`{name}` must be a positive integer, got {v!r}.")
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"`seed` must be a non-negative integer, got {seed!r}.")
    if client is None:
        if not jax.config.jax_enable_x64:
            raise ValueError("sweeps run in float64: call "
                             "`jax.config.update('jax_enable_x64', True)` first.")
        all_devices = jax.devices()
        devices = len(all_devices) if devices is None else devices
        if isinstance(devices, bool) or not 1 <= devices <= len(all_devices):
            raise ValueError(f"`devices` must be in 1..{len(all_devices)} (jax.devices()), "
                             f"got {devices!r}.")
    elif devices is not None and (isinstance(devices, bool) or devices < 1):
        raise ValueError(f"`devices` must be a positive integer, got {devices!r}.")
    import zarr

    loc = _Location.of(out, storage_options)
    _prepare_store(loc, sc, n, chunk, seed, lanes, resume, overwrite)
    g = loc.group("r+")
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
    zarr.consolidate_metadata(g.store)
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
    if not _Location.of(store, storage_options).is_store():
        raise ValueError(f"{store} is not a sweep store.")
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
        ds.to_netcdf(tmp, engine="netcdf4", format="NETCDF4")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


__all__ = [
    "Progress",
    "open_dataset",
    "plots_dir",
    "run",
    "solve_chunk",
    "status_meanings",
    "summarize",
    "to_netcdf",
]
