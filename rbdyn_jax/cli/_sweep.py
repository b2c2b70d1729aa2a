"""`rbdyn sweep`: a Monte Carlo sweep of a scenario streamed to a zarr store, in this process
or on a Dask cluster, with its progress, its summary tables and what to change where
trajectories failed."""

import shlex
import sys
import time

from ._common import (
    EXIT_ALL_FAILED,
    EXIT_DAMAGED,
    EXIT_INTERRUPTED,
    EXIT_SOME_FAILED,
    EXIT_USAGE,
    cache_dir,
    compilation_cache,
    error_text,
)

LOG_EVERY = 5.0  # seconds between progress lines when stderr is not a terminal


def sweep_command(args) -> int:
    """`rbdyn sweep`: its exit status (0, or `EXIT_SOME_FAILED`, `EXIT_ALL_FAILED`, a user's
    error, a damaged store, Ctrl-C)."""
    if args.scheduler is not None or args.workers is not None:
        try:
            import distributed  # noqa: F401
        except ImportError:
            print(
                "rbdyn sweep: --scheduler/--workers need Dask's distributed: "
                "pip install 'rbdyn_jax[dask]'",
                file=sys.stderr,
            )
            return EXIT_USAGE
    # XLA CPU devices: in-process, one per core (set by `import rbdyn_jax`) or --devices;
    # with --workers, cores // workers for each worker (whose environment comes from this
    # process; on GPUs each worker sees its GPUs); with --scheduler, the workers' own.
    if args.workers is not None:
        from .._program.flags import usable_cores

        _configure_xla(args.devices or max(1, usable_cores() // args.workers))
    elif args.devices is not None:
        _configure_xla(args.devices)
    import jax

    jax.config.update("jax_enable_x64", True)
    compilation_cache(jax)
    from .. import sweep
    from ..scenario import Scenario, ScenarioError

    try:
        scenario = Scenario.load(args.scenario)
    except ScenarioError as e:
        print(f"rbdyn sweep: invalid scenario: {e}", file=sys.stderr)
        return EXIT_USAGE
    try:
        scenario = scenario.with_settings(dtype=args.dtype, trajectories=args.trajectories)
    except ScenarioError as e:  # a float32 sweep of a scenario whose rtol is finer, say
        given = " ".join(
            f"--{k} {v}"
            for k, v in (("dtype", args.dtype), ("trajectories", args.trajectories))
            if v is not None
        )
        print(f"rbdyn sweep: the scenario cannot run with {given}: {e}", file=sys.stderr)
        return EXIT_USAGE
    if scenario.dtype == "float32":
        # Float32 throughout (its arrays are float32 explicitly): no 64-bit types needed,
        # and a float32 sweep gives the same bits with them on or off.
        jax.config.update("jax_enable_x64", False)
    try:
        client, cluster = _cluster(args)
    except (OSError, ValueError, TypeError) as e:  # an address Dask cannot parse or reach
        if args.scheduler is None:
            raise
        print(f"rbdyn sweep: no Dask scheduler at {args.scheduler}: {e}", file=sys.stderr)
        return EXIT_USAGE
    print(f"rbdyn sweep: {scenario.name} — {scenario.description}")
    if client is None:
        devices = jax.devices()
        n_dev = args.devices if args.devices is not None else len(devices)
        where = f"on {_devices_text(devices[:n_dev])}"
    else:
        n_dev = args.devices
        workers = len(client.scheduler_info()["workers"])
        where = f"as Dask tasks on {workers} worker(s) at {client.scheduler.address}, " + (
            "each on all its devices" if n_dev is None else f"{n_dev} device(s) each"
        )
    print(
        f"  {args.n} trajectories {where}, seed {args.seed}, {scenario.dtype}, "
        f"{_states_text(scenario.trajectories)} → {args.out}"
    )
    progress, close = _progress_reporter(args.n)
    t0 = time.perf_counter()
    try:
        path = sweep.run(
            scenario,
            args.n,
            args.out,
            chunk=args.chunk,
            seed=args.seed,
            devices=n_dev,
            lanes=args.lanes,
            resume=args.resume,
            overwrite=args.overwrite,
            client=client,
            progress=progress,
        )
    except KeyboardInterrupt:
        close()
        print(f"\nrbdyn sweep: interrupted: {_solved_text(sweep, args)}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (ValueError, OSError) as e:  # FileExistsError, FileNotFoundError, ...
        close()
        print(f"rbdyn sweep: {error_text(e, args.out)}", file=sys.stderr)
        return EXIT_DAMAGED if isinstance(e, sweep.StoreDamagedError) else EXIT_USAGE
    finally:
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()
    close()
    elapsed = time.perf_counter() - t0
    stats = sweep.summarize(path)
    attrs = sweep.open_dataset(path).attrs
    print_summary(stats)
    print(
        f"\nwrote {path} in {elapsed:.1f} s {where}, in chunks of {attrs['chunk']} with "
        f"{attrs['lanes']} lanes per device (open with xarray.open_zarr({str(path)!r}));"
        f" plots: {shlex.join(['rbdyn', 'plot', str(path)])}"
    )
    failed = stats["n"] - stats["status"].get("successful", 0)
    if failed:
        print(
            f"\nrbdyn sweep: {failed} of {stats['n']} trajectories failed (their data are "
            "NaN; everything solved is written):",
            file=sys.stderr,
        )
        for hint in _hints(stats["status"], scenario):
            print(f"  {hint}", file=sys.stderr)
        return EXIT_ALL_FAILED if failed == stats["n"] else EXIT_SOME_FAILED
    return 0


def _configure_xla(devices: int) -> None:
    """`devices` XLA CPU devices (`rbdyn_jax.configure_xla`, in place of the count that
    `import rbdyn_jax` set; a count in the user's `XLA_FLAGS` wins), when this process has
    not started JAX yet (when it has, e.g. a test calling a command in-process, it runs as
    it is). No effect on GPU/TPU."""
    from .._program.flags import backend_started, configure_xla

    if not backend_started():
        configure_xla(devices)


def _cluster(args):
    """A Dask client: on the cluster at `--scheduler`, or on a new `LocalCluster` of
    `--workers` processes (one thread each: a task's solve uses the worker's XLA devices,
    `--devices` of them, default all). None: solve in this process."""
    if args.scheduler is None and args.workers is None:
        return None, None
    from distributed import Client, LocalCluster

    if args.scheduler is not None:
        return Client(args.scheduler), None
    # The workers inherit this process's environment (XLA's flags); they start with 64-bit
    # types (a float32 scenario still computes in float32 there) and get this process's
    # compilation cache through their own.
    cache = cache_dir()
    env = {"JAX_ENABLE_X64": "1"}
    if cache:
        env.update(JAX_COMPILATION_CACHE_DIR=cache, JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="1")
    cluster = LocalCluster(
        n_workers=args.workers,
        threads_per_worker=1,
        processes=True,
        dashboard_address=":0",
        env=env,
    )
    return Client(cluster), cluster


def _devices_text(devices) -> str:
    """`1 × NVIDIA H100 80GB HBM3 (gpu)`, or `2 × cpu devices`: the devices a sweep runs on."""
    kind, platform = devices[0].device_kind, devices[0].platform
    if kind.lower() == platform:
        return f"{len(devices)} × {platform} device{'s' if len(devices) > 1 else ''}"
    return f"{len(devices)} × {kind} ({platform})"


def _states_text(trajectories) -> str:
    """What a store keeps of the states, for `trajectories` = "all", "none" or K."""
    if trajectories == "all":
        return "states of every trajectory"
    if trajectories == "none":
        return "no states (summaries only)"
    return f"states of one trajectory in {trajectories}"


def _progress_reporter(total: int):
    """`(progress, close)` for `sweep.run`: a progress bar on a terminal; elsewhere (a log, a
    pipe) a line every `LOG_EVERY` seconds and one at the end."""
    if sys.stderr.isatty():
        from tqdm import tqdm

        bar = tqdm(
            total=total,
            unit="traj",
            unit_scale=True,
            dynamic_ncols=True,
            desc="solving (first chunk compiles)",
            file=sys.stderr,
        )

        def progress(p) -> None:
            if bar.n == 0 and p.done > p.solved_now:  # resumed: count the finished ones
                bar.update(p.done - p.solved_now)
            bar.set_description("solving")
            bar.set_postfix(failed=p.failed)
            bar.update(p.solved_now)

        return progress, bar.close
    print("solving (the first chunk compiles)", file=sys.stderr, flush=True)
    last = [time.perf_counter()]

    def line(p) -> None:
        now = time.perf_counter()
        if now - last[0] >= LOG_EVERY or p.done == p.total:
            last[0] = now
            print(
                f"solved {p.done} of {p.total} ({100 * p.done / p.total:.0f} %), "
                f"{p.failed} failed, {p.elapsed:.1f} s",
                file=sys.stderr,
                flush=True,
            )

    return line, lambda: None


def _resume_command(args) -> str:
    """The command that finishes the sweep `args` started: the same, with --resume."""
    argv = [a for a in args.argv if a != "--overwrite"]
    return shlex.join(["rbdyn", *argv, *([] if "--resume" in argv else ["--resume"])])


def _solved_text(sweep, args) -> str:
    """`N of M solved; finish with ...` for an interrupted sweep, N read from its store."""
    import numpy as np
    import zarr

    try:
        done = int(np.sum(zarr.open_group(args.out, mode="r")["status"][:] >= 0))
    except Exception:  # no store made yet
        return "no store was made; run the command again."
    return f"{done} of {args.n} solved; finish with `{_resume_command(args)}`"


def _table(rows: list[list[str]], header: list[str]) -> str:
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]

    def line(r):
        return "  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths)))

    return "\n".join([line(header), "  ".join("-" * w for w in widths), *map(line, rows)])


def print_summary(stats: dict) -> None:
    """Print `sweep.summarize`'s result as tables."""
    print(
        f"\nscenario {stats['scenario']}: {stats['n']} trajectories"
        + ("" if stats["complete"] else " (incomplete: run again with --resume)")
    )
    print(_table([[k, str(v)] for k, v in stats["status"].items()], ["status", "count"]))
    cols = ["count", "mean", "std", "min", "q05", "q50", "q95", "max"]
    rows = []
    for name, row in stats["summaries"].items():
        rows.append(
            [name]
            + [
                str(row[c]) if c == "count" else (f"{row[c]:.6g}" if c in row else "-")
                for c in cols
            ]
        )
    if rows:
        print()
        print(_table(rows, ["summary (successful)"] + cols))


def _hints(status: dict[str, int], scenario) -> list[str]:
    """What to change for each kind of failure in a sweep's status counts."""
    hints = {
        "max_steps_reached": f"raise [solver] max_steps (now {scenario.max_steps}) in the "
        "scenario, or loosen [solver] rtol/atol",
        "nonfinite_state": "a drawn sample or the state became non-finite: narrow the "
        "scenario's distributions (a lognormal's sigma, say) or shorten "
        "[time] t1",
        "dt_min_reached": "the step size reached its minimum: loosen [solver] rtol/atol",
    }
    return [
        f"{count} {name}: "
        + hints.get(
            name, "see the status codes in the sweep guide (rbdyn_jax.sweep.status_meanings())"
        )
        for name, count in status.items()
        if name not in ("successful", "not_run")
    ]
