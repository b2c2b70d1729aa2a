"""Monte Carlo sweeps of a scenario: chunked runs sharded over devices, streaming to disk,
resume.

The scenario (model, distributions, output times, solver settings, summaries; TOML) is
`rbdyn_jax.scenario.Scenario`. `run(scenario, n, out)` draws trajectory `i` from
`fold_in(key(seed), i)` (and every random quantity from a further `fold_in` with a hash of
its key path), so a trajectory's sample does not depend on the chunking, the devices or the
other random quantities. The solves run through one compiled program: each device takes its
part of a chunk with `jax.shard_map` (no collectives inside the solver loop) and runs it
through the lane solver (`simulate_batch(..., batching=Lanes(lanes, devices=1))`), in
fixed blocks of 8 × `lanes` trajectories: `lanes` trajectories step together, and a lane
whose trajectory has finished takes the next one of its block at once. Because the block
shape is fixed and every drawn quantity enters as a runtime argument (the output times and
tolerances, the same for every trajectory, are constants of the program), the results are
**bitwise identical for any chunk size and any number of devices** at a given `lanes`.
Each finished chunk is written to a zarr store (format 2 with consolidated metadata:
`xarray.open_zarr(path)` reads it) and dropped, so memory does not grow with `n`.

The store holds, with dims `trajectory × time × axis|quat_component`: `omega`, `quat`,
`inertia` (`trajectory × row × col`), `status` (a `RESULTS` code per trajectory; −1 = not
run yet), `num_steps`, and one variable per summary. `status` is written last in a chunk,
so a run that is killed keeps every finished chunk and `run(..., resume=True)` solves
exactly the trajectories still marked −1.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import shutil
import time
from collections.abc import Callable, Iterator
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding, PartitionSpec as P

from ._checks import checks_as_nan
from ._xla import jit
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
        return {name: SUMMARIES[name][1](m, tr) for name in scenario.summaries}

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


@dataclasses.dataclass
class _Runner:
    """The compiled chunk solver: every call has the same padded size (one compilation)."""

    scenario: Scenario
    lanes: int
    devices: list
    chunk: int
    fn: Callable = dataclasses.field(init=False)
    mesh: Any = dataclasses.field(init=False)

    def __post_init__(self):
        sc, lanes = self.scenario, self.lanes
        self.mesh = jax.sharding.Mesh(np.asarray(self.devices), ("batch",))

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
        sharded = jax.shard_map(per_device, mesh=self.mesh,
                                in_specs=(P("batch"), P(), P()), out_specs=P("batch"),
                                check_vma=False)
        self.fn = jit(sharded)

    @property
    def size(self) -> int:
        """The padded chunk: a multiple of _PER_LANE × lanes × devices."""
        quantum = _PER_LANE * self.lanes * len(self.devices)
        return -(-self.chunk // quantum) * quantum

    def __call__(self, idx: np.ndarray, key) -> dict[str, np.ndarray]:
        n = len(idx)  # ≤ chunk; padded with copies of the last index (solved, then dropped)
        full = np.concatenate([idx, np.full(self.size - n, idx[-1], idx.dtype)])
        arr = jax.make_array_from_callback(
            (self.size,), NamedSharding(self.mesh, P("batch")), lambda i: full[i])
        with checks_as_nan(jitted=MODE_DEPENDENT_JITS):  # traced on the first call only
            out = self.fn(arr, self.scenario.dists, key)
        if jax.process_count() > 1:  # multi-host: every process gets the whole chunk
            from jax.experimental import multihost_utils

            out = multihost_utils.process_allgather(out, tiled=True)
        return {k: np.asarray(v)[:n] for k, v in out.items()}


_RUNNERS: dict[tuple, _Runner] = {}


def _runner(sc: Scenario, lanes: int, devices: tuple, chunk: int) -> _Runner:
    """A compiled runner, reused by later runs of the same scenario and layout (a resumed
    or repeated run in the same process compiles nothing)."""
    quantum = _PER_LANE * lanes * len(devices)  # the compiled shape: the padded chunk
    key = (json.dumps(sc.source, sort_keys=True), lanes, devices, -(-chunk // quantum))
    if key not in _RUNNERS:
        _RUNNERS.clear()  # keep one: a compiled solver holds memory
        _RUNNERS[key] = _Runner(sc, lanes, list(devices), chunk)
    return _RUNNERS[key]


# ----------------------------------------------------------------------------------------
# The store
# ----------------------------------------------------------------------------------------

_DIMS = {
    "omega": ("trajectory", "time", "axis"),
    "quat": ("trajectory", "time", "quat_component"),
    "inertia": ("trajectory", "row", "col"),
    "status": ("trajectory",),
    "num_steps": ("trajectory",),
}


def _status_codes() -> dict[str, str]:
    codes = {"-1": "not_run"}
    codes.update({str(c): name for c, name in result_names().items()})
    return codes


def _create_store(path: pathlib.Path, sc: Scenario, n: int, chunk: int, seed: int, lanes: int):
    import zarr

    from ._version import __version__

    g = zarr.open_group(str(path), mode="w", zarr_format=2)
    T = sc.n_times
    shapes = {"omega": (n, T, 3), "quat": (n, T, 4), "inertia": (n, 3, 3), "status": (n,),
              "num_steps": (n,)}
    dtypes = {"status": "int32", "num_steps": "int64"}
    for name in [*shapes, *sc.summaries]:
        shape = shapes.get(name, (n,))
        dims = _DIMS.get(name, ("trajectory",))
        fill = None if name in ("status", "num_steps") else np.nan
        a = g.create_array(name, shape=shape, chunks=(min(chunk, n),) + shape[1:],
                           dtype=dtypes.get(name, "float64"), fill_value=fill)
        attrs = {"_ARRAY_DIMENSIONS": list(dims)}
        if name in SUMMARIES:
            attrs["description"] = SUMMARIES[name][0]
        a.attrs.update(attrs)
    for start in range(0, n, 1 << 20):  # status −1 = not run (written, not a fill value)
        g["status"][start:start + (1 << 20)] = -1
    for name, values, dims in (("time", sc.ts, ["time"]),
                               ("trajectory", np.arange(n, dtype=np.int64), ["trajectory"])):
        a = g.create_array(name, shape=values.shape, chunks=(min(len(values), 1 << 20),),
                           dtype=values.dtype, fill_value=None)
        a[:] = values
        a.attrs["_ARRAY_DIMENSIONS"] = dims
    g["omega"].attrs["description"] = "body angular velocity (relative to O1 in relative models)"
    g["quat"].attrs["description"] = "attitude quaternion [w, x, y, z], body → parent"
    g.attrs.update({
        "title": f"rbdyn_jax Monte Carlo sweep: {sc.name}",
        "scenario_name": sc.name,
        "scenario": json.dumps(sc.source),
        "model_kind": sc.kind,
        "seed": seed,
        "n_trajectories": n,
        "chunk": chunk,
        "lanes": lanes,
        "summaries": list(sc.summaries),
        "status_codes": json.dumps(_status_codes()),
        "conventions": CONVENTIONS,
        "rbdyn_jax_version": __version__,
        "jax_version": jax.__version__,
        "complete": False,
    })
    zarr.consolidate_metadata(str(path))
    return g


def _open_store(path: pathlib.Path, sc: Scenario, n: int, seed: int, lanes: int):
    import zarr

    g = zarr.open_group(str(path), mode="r+", zarr_format=2)
    want = {"scenario": json.dumps(sc.source), "n_trajectories": n, "seed": seed,
            "lanes": lanes}
    for k, v in want.items():
        if g.attrs.get(k) != v:
            raise ValueError(f"cannot resume {path}: its {k} is {g.attrs.get(k)!r}, this run's "
                             f"is {v!r}; use a new --out or drop --resume.")
    return g


def _write_chunk(g, start: int, out: dict[str, np.ndarray]):
    stop = start + len(out["status"])
    for name, values in out.items():
        if name != "status":
            g[name][start:stop] = values
    g["status"][start:stop] = out["status"]  # last: marks the chunk done


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


def _todo_chunks(status: np.ndarray, chunk: int) -> Iterator[tuple[int, np.ndarray]]:
    """(start, indices) of the chunks that still hold unrun trajectories."""
    for start in range(0, len(status), chunk):
        idx = np.nonzero(status[start:start + chunk] < 0)[0]
        if idx.size:
            yield start, start + idx


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
    progress: Callable[[Progress], None] | None = None,
) -> pathlib.Path:
    """Run `n` trajectories of `scenario` and stream them to the zarr store `out`.

    **Arguments:**

    - `scenario`: a `Scenario`, a shipped scenario name or a TOML path.
    - `n`: number of trajectories; `chunk`: trajectories solved and written at a time
      (memory ∝ chunk); `seed`: the random seed. Each device solves its share in blocks
      of 8 × `lanes`, so a chunk is padded to a multiple of 8 × `lanes` × devices (1024
      at the defaults on two devices): a smaller chunk solves padding, and is slower per
      trajectory.
    - `devices`: how many of `jax.devices()` to shard each chunk over (default all).
    - `lanes`: lanes of each device's solver loop (the lane solver of `simulate_batch`; a
      lane takes the next trajectory as soon as its own has finished). Results are bitwise
      identical for any `chunk` and `devices` at the same `lanes`.
    - `resume`: continue an interrupted run in `out` (same scenario, n, seed, lanes),
      solving only the trajectories not yet written.
    - `progress`: called with a `Progress` after every chunk.

    **Returns:** the path of the store; open it with `open_dataset(path)`.
    """
    sc = scenario if isinstance(scenario, Scenario) else Scenario.load(scenario)
    for name, v in (("n", n), ("chunk", chunk), ("lanes", lanes)):
        if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 1:
            raise ValueError(f"`{name}` must be a positive integer, got {v!r}.")
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"`seed` must be a non-negative integer, got {seed!r}.")
    if not jax.config.jax_enable_x64:
        raise ValueError("sweeps run in float64: call "
                         "`jax.config.update('jax_enable_x64', True)` first.")
    import zarr

    all_devices = jax.devices()
    devices = len(all_devices) if devices is None else devices
    if isinstance(devices, bool) or not 1 <= devices <= len(all_devices):
        raise ValueError(f"`devices` must be in 1..{len(all_devices)} (jax.devices()), "
                         f"got {devices!r}.")
    path = pathlib.Path(out)
    # Multi-host (after `jax.distributed.initialize()`): every process runs this function
    # on the same arguments, the chunks are sharded over all hosts' devices, and process 0
    # alone writes the store (a filesystem all hosts see).
    writer = jax.process_index() == 0
    if writer:
        _prepare_store(path, sc, n, chunk, seed, lanes, resume)
    _barrier("rbdyn_jax.sweep: store ready")
    g = zarr.open_group(str(path), mode="r+" if writer else "r", zarr_format=2)

    runner = _runner(sc, lanes, tuple(all_devices[:devices]), chunk)
    key = jax.random.key(seed)
    status = g["status"][:]
    done = int(np.sum(status >= 0))
    failed = int(np.sum(status > 0))
    t_start = time.perf_counter()
    for _, idx in _todo_chunks(status, chunk):
        res = runner(idx, key)
        if writer:  # one write per contiguous run (a partly finished chunk has several)
            runs = np.split(np.arange(idx.size), np.nonzero(np.diff(idx) != 1)[0] + 1)
            for r in runs:
                _write_chunk(g, int(idx[r[0]]), {k: v[r[0]:r[-1] + 1] for k, v in res.items()})
        done += idx.size
        failed += int(np.sum(res["status"] != 0))
        if progress is not None:
            progress(Progress(done, n, failed, time.perf_counter() - t_start, idx.size))
    if writer:
        g.attrs["complete"] = True
        zarr.consolidate_metadata(str(path))
    _barrier("rbdyn_jax.sweep: done")
    return path


def _barrier(name: str) -> None:
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices(name)


def _prepare_store(path: pathlib.Path, sc: Scenario, n, chunk, seed, lanes, resume) -> None:
    """Check a store to resume, or build a new one beside `path` and rename it into place,
    so a store at `path` is always initialised (every status −1) and a kill at any moment
    leaves something `resume` can finish."""
    if resume and (path / ".zgroup").exists():
        _open_store(path, sc, n, seed, lanes)
        return
    if path.exists() and not (path / ".zgroup").exists() and any(path.iterdir()):
        raise ValueError(f"{path} exists and is not a sweep store; choose another --out.")
    tmp = path.with_name(path.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    _create_store(tmp, sc, n, chunk, seed, lanes)
    shutil.rmtree(path, ignore_errors=True)
    os.replace(tmp, path)


def open_dataset(path: str | pathlib.Path):
    """The sweep store at `path` as an `xarray.Dataset` (lazy; nothing is loaded)."""
    import xarray as xr

    return xr.open_zarr(str(path))


def summarize(path: str | pathlib.Path, quantiles=(0.05, 0.5, 0.95)) -> dict:
    """Counts per status and, for every summary, count/mean/std/min/quantiles/max over the
    successful trajectories (finite values). Reads only the `(trajectory,)` columns (8 bytes
    per trajectory per summary), never the trajectories themselves."""
    import zarr

    g = zarr.open_group(str(path), mode="r")
    status = g["status"][:]
    codes = json.loads(g.attrs["status_codes"])
    counts = {codes.get(str(c), str(c)): int(k) for c, k in zip(*np.unique(status,
                                                                          return_counts=True))}
    stats = {}
    ok = status == 0
    for name in g.attrs["summaries"]:
        x = g[name][:][ok]
        x = x[np.isfinite(x)]
        row = {"count": int(x.size)}
        if x.size:
            row.update(mean=float(x.mean()), std=float(x.std(ddof=1)) if x.size > 1 else 0.0,
                       min=float(x.min()), max=float(x.max()))
            row.update({f"q{round(100 * q):02d}": float(v)
                        for q, v in zip(quantiles, np.quantile(x, quantiles))})
        stats[name] = row
    return {"n": int(status.size), "status": counts, "summaries": stats,
            "scenario": g.attrs["scenario_name"], "complete": bool(g.attrs["complete"])}


__all__ = [
    "Progress",
    "open_dataset",
    "run",
    "summarize",
]
