"""Running a sweep: in this process, or as Dask tasks that each solve and write a chunk."""

from __future__ import annotations

import contextlib
import dataclasses
import pathlib
import signal
import threading
import time
import uuid
from collections.abc import Callable

import jax
import numpy as np

from ..integrate import (
    device_memory,
)
from ..scenario import Scenario
from ._chunk import _Runner, _runner
from ._chunking import _devices_info, chunking, trajectory_bytes
from ._store import _consolidate, _Location, _prepare_store, _write
from ._verify import _repair


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
        status = g["status"][b : b + block]
        done += int(np.sum(status >= 0))
        failed += int(np.sum(status > 0))
        for start in range(0, status.size, chunk):
            s = status[start : start + chunk]
            if np.any(s < 0):
                todo.append(
                    (b + start, b + start + s.size, int(np.sum(s >= 0)), int(np.sum(s > 0)))
                )
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
        with _interrupt_held():
            _write(g, idx, res, runner.every)
        status[idx - start] = res["status"]
    return int(np.sum(status >= 0)), int(np.sum(status > 0))


@contextlib.contextmanager
def _interrupt_held():
    """Ctrl-C (SIGINT) held while a region is written, then delivered: an interrupted sweep
    leaves no write in flight (zarr writes from its own thread, which an interrupt of this
    one does not stop), so its store says what was solved when the call returns. Only in
    the main thread, with a handler Python installed; elsewhere as it is."""
    main = threading.current_thread() is threading.main_thread()
    if not main or signal.getsignal(signal.SIGINT) is None:
        yield
        return
    held = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if held:
            signal.raise_signal(signal.SIGINT)


@contextlib.contextmanager
def _interrupts_kept():
    """Ctrl-C (SIGINT) raises `KeyboardInterrupt` as Python's own handler does, and is also
    kept: where Python ignored the exception (raised inside a garbage-collector callback,
    which JAX registers, Python prints "Exception ignored" and goes on), `check()` raises
    it again between regions. Only in the main thread, with a handler Python installed."""
    main = threading.current_thread() is threading.main_thread()
    if not main or signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield lambda: None
        return
    kept = []

    def handler(signum, frame):
        kept.append(signum)
        raise KeyboardInterrupt

    def check():
        if kept:
            raise KeyboardInterrupt

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield check
    finally:
        signal.signal(signal.SIGINT, previous)


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
        raise ValueError(f"`n` = {n} trajectories need 64-bit indices (`jax_enable_x64`) {where}.")


def _check_workers(client, dtype: str, n: int) -> None:
    """`_check_types` on every worker of `client`, before any task is sent."""
    on = client.run(_x64)  # {worker address: whether it has 64-bit types}
    off = sorted(w for w, x64 in on.items() if not x64)
    if off:
        shown = ", ".join(off[:3]) + (", …" if len(off) > 3 else "")
        _check_types(
            dtype,
            n,
            f"on every worker ({len(off)} of {len(on)} lack them: "
            f"{shown}): start the workers with JAX_ENABLE_X64=1 in their environment "
            "(`LocalCluster(..., env={'JAX_ENABLE_X64': '1'})`, or exported before "
            "`dask worker`)",
            x64=False,
        )


def solve_chunk(
    store: str,
    source: dict,
    name: str,
    start: int,
    stop: int,
    *,
    seed: int,
    lanes: int,
    chunk: int,
    devices: int | None = None,
    storage_options: dict | None = None,
) -> tuple[int, int]:
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
    _check_types(
        sc.dtype, stop, "on this worker: start its process with JAX_ENABLE_X64=1 in its environment"
    )
    local = jax.local_devices()
    devices = len(local) if devices is None else devices
    if not 1 <= devices <= len(local):
        raise ValueError(f"`devices` must be in 1..{len(local)} on this worker, got {devices!r}.")
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
    - `n`: number of trajectories; `seed`: the random seed, 0 ≤ seed < 2³².
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
      `chunk`, `devices` and `client` at the same `lanes` of 16 or more (with fewer,
      XLA may compile the lanes unrolled and a trajectory's last bits depend on its
      lane: the module's docstring). On a GPU backend a scenario
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
    if isinstance(trajectories, np.integer):  # the scenario's source is JSON: a Python int
        trajectories = int(trajectories)
    sc = sc.with_settings(dtype=dtype, trajectories=trajectories)
    for name, v in (("n", n), ("chunk", chunk), ("lanes", lanes)):
        if v is None and name != "n":
            continue
        if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 1:
            raise ValueError(f"`{name}` must be a positive integer, got {v!r}.")
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or not 0 <= seed < 2**32:
        # `jax.random.key` keeps a larger seed's low 32 bits where 64-bit types are off
        # (seed 2³² would draw seed 0's trajectories) and overflows at 2⁶³ where they are on.
        raise ValueError(f"`seed` must be an integer in 0..2**32 - 1, got {seed!r}.")
    # Python ints from here: they are written into the store's attributes (JSON)
    n, seed = int(n), int(seed)
    chunk, lanes = (None if v is None else int(v) for v in (chunk, lanes))
    if client is None:
        _check_types(
            sc.dtype, n, "in this process: call `jax.config.update('jax_enable_x64', True)` first"
        )
        all_devices = jax.devices()
        devices = len(all_devices) if devices is None else devices
        if (
            isinstance(devices, bool)
            or not isinstance(devices, int | np.integer)
            or not 1 <= devices <= len(all_devices)
        ):
            raise ValueError(
                f"`devices` must be in 1..{len(all_devices)} (jax.devices()), got {devices!r}."
            )
    else:
        if devices is not None and (
            isinstance(devices, bool) or not isinstance(devices, int | np.integer) or devices < 1
        ):
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
        return chunking(
            n,
            platform=platform,
            devices=count,
            memory=memory,
            trajectory_bytes=trajectory_bytes(sc),
            chunk=chunk,
            lanes=lanes,
            every=sc.trajectories if isinstance(sc.trajectories, int) else None,
        )

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
        with _interrupts_kept() as interrupted:
            for region in todo:
                launched = (region, _launch_region(g, runner, key, *region[:2]))
                if solving is not None:
                    report(solving[0], _finish_region(g, solving[1]))
                    interrupted()
                solving = launched
            if solving is not None:
                report(solving[0], _finish_region(g, solving[1]))
                interrupted()
    else:
        _run_on_dask(
            client,
            todo,
            report,
            loc.url,
            sc,
            seed=seed,
            lanes=lanes,
            chunk=chunk,
            devices=devices,
            storage_options=loc.options or None,
        )
    g.attrs["complete"] = 1
    _consolidate(g)
    return loc.url if loc.is_url else pathlib.Path(loc.url)


def _run_on_dask(client, todo, report, store, sc, **kw) -> None:
    """Each chunk a task writing its own region; progress as the tasks complete."""
    from distributed import as_completed

    token = uuid.uuid4().hex[:8]
    futures = {
        client.submit(
            solve_chunk,
            store,
            sc.source,
            sc.name,
            *region[:2],
            **kw,
            key=f"rbdyn_jax-sweep-{token}-{region[0]}",
            pure=False,
        ): region
        for region in todo
    }
    try:
        for future in as_completed(futures):
            report(futures[future], future.result())
            future.release()
    finally:
        client.cancel(futures)
