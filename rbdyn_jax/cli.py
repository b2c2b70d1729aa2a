"""The `rbdyn` command: the only layer that prints (the library below it returns values).

- `rbdyn sweep SCENARIO --n N --out PATH [--chunk C] [--seed S] [--devices D]
  [--trajectories {all,none,K}] [--dtype {float64,float32}] [--resume | --overwrite]
  [--scheduler ADDRESS | --workers K]`: a Monte Carlo sweep of a scenario (a TOML file or
  a shipped name, `rbdyn scenarios`) streamed to a zarr store, in this process (on its
  devices: CPU cores or GPUs) or as tasks on a Dask cluster, with a progress bar and a
  summary table (`rbdyn_jax.sweep`). Exits 3 if some trajectories failed, 4 if all did.
- `rbdyn export STORE OUT.nc [--overwrite]`: a sweep store as a netCDF-4 file.
- `rbdyn verify STORE`: every chunk of a sweep store there and intact (its checksum), or
  the missing and damaged ones with the trajectories they hold (`--resume` repairs them).
- `rbdyn plot PATH [--out DIR]`: PNGs of a sweep (summary histograms, sample
  trajectories, polhodes on their energy ellipsoids where the model conserves it, status
  counts).
- `rbdyn fit DATA --model SCENARIO [--free inertia,k] [--out PATH]`: identify the
  inertia and/or torque parameters from observed ω / attitudes (`rbdyn_jax.identify`),
  printing them with standard errors and writing fit.json and a PNG of observed vs fitted.
- `rbdyn scenarios`: the shipped scenarios.
- `rbdyn demo`: the shipped default body, one trajectory, printed.
- `rbdyn --version`: the installed version.

A command ends with one message, never a traceback: status 2 for a user's error (a bad
option, scenario or path), 5 for a damaged store, 6 for a fit that did not converge, 7
for `rbdyn verify` of an incomplete store, 130 on Ctrl-C (the `EXIT_*` constants).

XLA starts with the flags `import rbdyn_jax` sets (`rbdyn_jax.configure_xla`: one CPU
device per core, since one XLA CPU device uses about one core for these solves, and while
loops compiled whole; the user's `XLA_FLAGS` win, and `RBDYN_JAX_CONFIGURE_XLA=0` turns them
off). `rbdyn sweep --devices D` asks for D devices instead, and `--workers K` gives each
worker `cores // K`. `rbdyn sweep` and `rbdyn fit` keep their traced and compiled programs
in JAX's persistent cache (`$RBDYN_JAX_CACHE_DIR`, default `~/.cache/rbdyn_jax/xla`; set it
empty to turn this off).
"""

import argparse
import os
import shlex
import sys
import time
import warnings

from ._version import __version__

EXIT_USAGE = 2  # a usage error, an invalid scenario or data, a path that cannot be written
EXIT_DAMAGED = 5  # a store with missing or damaged chunks (`rbdyn verify` lists them)
EXIT_INCOMPLETE = 7  # `rbdyn verify`: a whole store with trajectories not solved yet
EXIT_INTERRUPTED = 130  # Ctrl-C (128 + SIGINT)
LOG_EVERY = 5.0  # seconds between progress lines when stderr is not a terminal


def _default_body():
    """Point masses (kg) and positions (m) of the shipped default body."""
    import numpy as np

    masses = np.array([2.0, 1.5, 1.0, 1.0, 0.5, 0.8])
    positions = np.array(
        [
            [0.30, 0.10, 0.00],
            [-0.20, 0.25, 0.05],
            [0.00, -0.30, 0.10],
            [-0.10, -0.05, -0.25],
            [0.15, 0.05, 0.30],
            [-0.05, 0.20, -0.15],
        ]
    )
    return masses, positions


def demo(n_steps: int = 5, duration: float = 100.0) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    from . import inertia, rotation

    t0 = time.perf_counter()
    masses, positions = _default_body()
    com = (masses[:, None] * positions).sum(0) / masses.sum()
    J = inertia.from_point_masses(masses, positions, about=com)
    moments, axes = inertia.principal_axes(J)
    Jp = inertia.planar(J)
    print("rbdyn demo: the default body (6 point masses, about its centre of mass)")
    print(f"  mass {masses.sum():.3f} kg, centre of mass {np.round(com, 4)} m")
    print("  inertia tensor J [kg m²] (docs/physics.md#inertia-tensor):")
    for row in np.asarray(J):
        print("    " + "  ".join(f"{x:+.5f}" for x in row))
    A, B, C = np.asarray(moments)
    print(f"  principal moments A ≤ B ≤ C: {A:.5f}, {B:.5f}, {C:.5f}")
    print(f"  planar moments A', B', C':    {(B + C - A) / 2:.5f}, {(C + A - B) / 2:.5f}, "
          f"{(A + B - C) / 2:.5f}  (eig J' = {np.round(np.linalg.eigvalsh(Jp), 5)})")
    print(f"  physically consistent: {bool(inertia.is_physical(J))}")
    angles = rotation.dcm_to_euler(axes, "ZXZ")
    print(f"  principal frame as ZXZ angles (ψ, θ, φ) [deg]: {np.round(np.degrees(angles), 3)}")

    # The default scenario: torque-free spin started 1° off the intermediate principal axis,
    # which flips again and again (Euler–Poinsot, docs/physics.md#torque-free-motion),
    # solved with diffrax.
    from . import invariants
    from .integrate import RESULTS, simulate
    from .models import RigidBody
    from .state import State

    tilt = np.radians(1.0)
    omega0 = 2.0 * (np.cos(tilt) * axes[:, 1] + np.sin(tilt) * axes[:, 0])
    body = RigidBody(J)
    y0 = State(omega=jnp.asarray(omega0), quat=rotation.dcm_to_quat(axes))
    ts = jnp.linspace(0.0, duration, n_steps * 100 + 1)
    t1 = time.perf_counter()
    traj = simulate(body, y0, ts, rtol=1e-10, atol=1e-10)
    jax.block_until_ready(traj)
    t_first = time.perf_counter() - t1
    t1 = time.perf_counter()
    jax.block_until_ready(simulate(body, y0, ts, rtol=1e-10, atol=1e-10))
    t_again = time.perf_counter() - t1
    T = np.asarray(invariants.kinetic_energy(body, traj))
    L = np.asarray(invariants.angular_momentum_inertial(body, traj))
    along_b = np.asarray(traj.ys.omega) @ np.asarray(axes[:, 1])
    flips = int(np.sum(np.diff(np.sign(along_b)) != 0))
    print("\n  torque-free spin |ω| = 2 rad/s, 1° off the intermediate axis, "
          f"t ∈ [0, {duration:g}] s")
    print(f"    result: {RESULTS[traj.result] or 'successful'}, "
          f"{int(traj.stats['num_steps'])} steps (Tsit5, rtol = atol = 1e-10)")
    print(f"    intermediate-axis flips: {flips}")
    print(f"    energy drift max|T − T0|/T0:       {np.max(np.abs(T - T[0])) / T[0]:.2e}")
    print(f"    momentum drift max|L − L0|/|L0|:   "
          f"{np.max(np.linalg.norm(L - L[:1], axis=-1)) / np.linalg.norm(L[0]):.2e}")
    print(f"    quaternion norm drift removed:     {float(traj.stats['norm_drift']):.2e}")
    print(f"    time: first call {t_first:.2f} s (with compilation), again {t_again * 1e3:.1f} ms")
    for t, w in zip(np.asarray(ts)[:: 100], np.asarray(traj.ys.omega)[:: 100]):
        print(f"    t = {t:7.2f} s   ω_body = ({w[0]:+.4f}, {w[1]:+.4f}, {w[2]:+.4f}) rad/s")
    print(f"done in {time.perf_counter() - t0:.2f} s")
    return 0


def _configure_xla(devices: int) -> None:
    """`devices` XLA CPU devices (`rbdyn_jax.configure_xla`, in place of the count that
    `import rbdyn_jax` set; a count in the user's `XLA_FLAGS` wins), when this process has
    not started JAX yet (when it has, e.g. a test calling a command in-process, it runs as
    it is). No effect on GPU/TPU."""
    from ._xla_flags import backend_started, configure_xla

    if not backend_started():
        configure_xla(devices)


def _table(rows: list[list[str]], header: list[str]) -> str:
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    line = lambda r: "  ".join(c.rjust(w) if i else c.ljust(w)  # noqa: E731
                               for i, (c, w) in enumerate(zip(r, widths)))
    return "\n".join([line(header), "  ".join("-" * w for w in widths), *map(line, rows)])


def print_summary(stats: dict) -> None:
    """Print `sweep.summarize`'s result as tables."""
    print(f"\nscenario {stats['scenario']}: {stats['n']} trajectories"
          + ("" if stats["complete"] else " (incomplete: run again with --resume)"))
    print(_table([[k, str(v)] for k, v in stats["status"].items()], ["status", "count"]))
    cols = ["count", "mean", "std", "min", "q05", "q50", "q95", "max"]
    rows = []
    for name, row in stats["summaries"].items():
        rows.append([name] + [str(row[c]) if c == "count" else
                              (f"{row[c]:.6g}" if c in row else "-") for c in cols])
    if rows:
        print()
        print(_table(rows, ["summary (successful)"] + cols))


def _cache_dir() -> str:
    """`$RBDYN_JAX_CACHE_DIR`, default `~/.cache/rbdyn_jax/xla`; empty: no cache."""
    return os.environ.get("RBDYN_JAX_CACHE_DIR",
                          os.path.join(os.path.expanduser("~"), ".cache", "rbdyn_jax", "xla"))


def _compilation_cache(jax) -> None:
    """JAX's persistent compilation cache in `_cache_dir()`, so a repeated sweep or fit skips
    tracing and compiling its program (rbdyn_jax stores the traced program beside it)."""
    path = _cache_dir()
    if path:
        jax.config.update("jax_compilation_cache_dir", path)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


EXIT_SOME_FAILED = 3  # `rbdyn sweep`: some trajectories failed (the rest are written)
EXIT_ALL_FAILED = 4  # `rbdyn sweep`: every trajectory failed
EXIT_NOT_CONVERGED = 6  # `rbdyn fit`: the fit did not converge (its files are written)


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
    return [f"{count} {name}: " + hints.get(name, "see the status codes in the sweep "
                                                  "guide (rbdyn_jax.sweep.status_meanings())")
            for name, count in status.items() if name not in ("successful", "not_run")]


def _cluster(args):
    """A Dask client: on the cluster at `--scheduler`, or on a new `LocalCluster` of
    `--workers` processes (one thread each: a task's solve uses the worker's XLA devices,
    `--devices` of them, default all). None: solve in this process."""
    if args.scheduler is None and args.workers is None:
        return None, None
    from distributed import Client, LocalCluster

    if args.scheduler is not None:
        return Client(args.scheduler), None
    # The workers inherit this process's environment (XLA's flags), and get its compilation
    # cache through their own.
    cache = _cache_dir()
    env = ({"JAX_COMPILATION_CACHE_DIR": cache, "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "1"}
           if cache else {})
    cluster = LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True,
                           dashboard_address=":0", env=env)
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


def sweep_command(args) -> int:
    if args.scheduler is not None or args.workers is not None:
        try:
            import distributed  # noqa: F401
        except ImportError:
            print("rbdyn sweep: --scheduler/--workers need Dask's distributed: "
                  "pip install 'rbdyn_jax[dask]'", file=sys.stderr)
            return 2
    # XLA CPU devices: in-process, one per core (set by `import rbdyn_jax`) or --devices;
    # with --workers, cores // workers for each worker (whose environment comes from this
    # process; on GPUs each worker sees its GPUs); with --scheduler, the workers' own.
    if args.workers is not None:
        from ._xla_flags import usable_cores

        _configure_xla(args.devices or max(1, usable_cores() // args.workers))
    elif args.devices is not None:
        _configure_xla(args.devices)
    import jax

    jax.config.update("jax_enable_x64", True)
    _compilation_cache(jax)
    from . import sweep
    from .scenario import Scenario, ScenarioError

    try:
        scenario = Scenario.load(args.scenario)
    except ScenarioError as e:
        print(f"rbdyn sweep: invalid scenario: {e}", file=sys.stderr)
        return 2
    try:
        scenario = scenario.with_settings(dtype=args.dtype, trajectories=args.trajectories)
    except ScenarioError as e:  # a float32 sweep of a scenario whose rtol is finer, say
        given = " ".join(f"--{k} {v}" for k, v in (("dtype", args.dtype),
                                                   ("trajectories", args.trajectories))
                         if v is not None)
        print(f"rbdyn sweep: the scenario cannot run with {given}: {e}", file=sys.stderr)
        return 2
    if scenario.dtype == "float32":
        # Float32 throughout (its arrays are float32 explicitly): no 64-bit types needed,
        # and a float32 sweep gives the same bits with them on or off.
        jax.config.update("jax_enable_x64", False)
    client, cluster = _cluster(args)
    print(f"rbdyn sweep: {scenario.name} — {scenario.description}")
    if client is None:
        devices = jax.devices()
        n_dev = args.devices if args.devices is not None else len(devices)
        where = f"on {_devices_text(devices[:n_dev])}"
    else:
        n_dev = args.devices
        workers = len(client.scheduler_info()["workers"])
        where = (f"as Dask tasks on {workers} worker(s) at {client.scheduler.address}, "
                 + ("each on all its devices" if n_dev is None else f"{n_dev} device(s) each"))
    print(f"  {args.n} trajectories {where}, seed {args.seed}, {scenario.dtype}, "
          f"{_states_text(scenario.trajectories)} → {args.out}")
    progress, close = _progress_reporter(args.n)
    t0 = time.perf_counter()
    try:
        path = sweep.run(scenario, args.n, args.out, chunk=args.chunk, seed=args.seed,
                         devices=n_dev, lanes=args.lanes, resume=args.resume,
                         overwrite=args.overwrite, client=client, progress=progress)
    except KeyboardInterrupt:
        close()
        print(f"\nrbdyn sweep: interrupted: {_solved_text(sweep, args)}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (ValueError, OSError) as e:  # FileExistsError, FileNotFoundError, ...
        close()
        print(f"rbdyn sweep: {_error_text(e, args.out)}", file=sys.stderr)
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
    print(f"\nwrote {path} in {elapsed:.1f} s {where}, in chunks of {attrs['chunk']} with "
          f"{attrs['lanes']} lanes per device (open with xarray.open_zarr({str(path)!r}));"
          f" plots: rbdyn plot {path}")
    failed = stats["n"] - stats["status"].get("successful", 0)
    if failed:
        print(f"\nrbdyn sweep: {failed} of {stats['n']} trajectories failed (their data are "
              "NaN; everything solved is written):", file=sys.stderr)
        for hint in _hints(stats["status"], scenario):
            print(f"  {hint}", file=sys.stderr)
        return EXIT_ALL_FAILED if failed == stats["n"] else EXIT_SOME_FAILED
    return 0


def _progress_reporter(total: int):
    """`(progress, close)` for `sweep.run`: a progress bar on a terminal; elsewhere (a log, a
    pipe) a line every `LOG_EVERY` seconds and one at the end."""
    if sys.stderr.isatty():
        from tqdm import tqdm

        bar = tqdm(total=total, unit="traj", unit_scale=True, dynamic_ncols=True,
                   desc="solving (first chunk compiles)", file=sys.stderr)

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
            print(f"solved {p.done} of {p.total} ({100 * p.done / p.total:.0f} %), "
                  f"{p.failed} failed, {p.elapsed:.1f} s", file=sys.stderr, flush=True)

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


def _error_text(e: Exception, path: str) -> str:
    """The message of a user-caused error: an OS error on `path` as `cannot write PATH:
    reason`, any other as it is."""
    if isinstance(e, OSError) and e.errno is not None:
        return f"cannot write {path}: {e.strerror}"
    return str(e)


def _store_problem(sweep, command: str, store: str) -> int | None:
    """Refuse a store that is not one or is damaged (the exit status), warn on an incomplete
    one (`sweep.check`); `None` when the command may read it."""
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", sweep.IncompleteStoreWarning)
            sweep.check(store)
    except sweep.StoreDamagedError as e:
        print(f"rbdyn {command}: {e}", file=sys.stderr)
        return EXIT_DAMAGED
    except (ValueError, OSError) as e:
        print(f"rbdyn {command}: {_error_text(e, store)}", file=sys.stderr)
        return EXIT_USAGE
    for w in caught:
        print(f"rbdyn {command}: warning: {w.message}", file=sys.stderr)
    return None


def export_command(args) -> int:
    from . import sweep

    if (code := _store_problem(sweep, "export", args.store)) is not None:
        return code
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", sweep.IncompleteStoreWarning)  # said above
            path = sweep.to_netcdf(args.store, args.out, overwrite=args.overwrite)
    except sweep.StoreDamagedError as e:
        print(f"rbdyn export: {e}", file=sys.stderr)
        return EXIT_DAMAGED
    except (ValueError, OSError) as e:
        print(f"rbdyn export: {_error_text(e, args.out)}", file=sys.stderr)
        return EXIT_USAGE
    print(f"wrote {path} (open with xarray.open_dataset({str(path)!r}))")
    return 0


def plot_command(args) -> int:
    from . import sweep
    from ._plots import plot_sweep

    if (code := _store_problem(sweep, "plot", args.path)) is not None:
        return code
    try:
        with sweep._reading(args.path, None):
            files = plot_sweep(args.path, args.out)
    except sweep.StoreDamagedError as e:
        print(f"rbdyn plot: {e}", file=sys.stderr)
        return EXIT_DAMAGED
    except OSError as e:
        print(f"rbdyn plot: {_error_text(e, args.out or args.path)}", file=sys.stderr)
        return EXIT_USAGE
    for f in files:
        print(f"wrote {f}")
    import xarray as xr

    with xr.open_zarr(args.path) as ds:
        if "omega" not in ds:
            print("note: no trajectories.png or polhodes.png: the store keeps no states (a "
                  'sweep with trajectories = "none"); sweep with --trajectories all or K '
                  "to plot them")
        elif not any(str(f).endswith("polhodes.png") for f in files):
            print("note: no polhodes.png: this scenario's torque does not conserve the "
                  "kinetic energy, so ω leaves the energy ellipsoid; trajectories.png shows "
                  "|ω| and the nutation against time")
    return 0


def verify_command(args) -> int:
    from . import sweep

    try:
        found = sweep.verify(args.store)
    except (ValueError, OSError) as e:
        print(f"rbdyn verify: {_error_text(e, args.store)}", file=sys.stderr)
        return EXIT_USAGE
    print(found)
    if found.complete:
        return 0
    from ._catalogue import catalogue

    attrs = sweep.open_dataset(args.store).attrs
    name = attrs["scenario_name"]
    scenario = name if name in catalogue() else "SCENARIO.toml"  # the file it was run from
    seed = [] if attrs["seed"] == 0 else ["--seed", str(attrs["seed"])]
    print("finish it with: " + shlex.join([
        "rbdyn", "sweep", scenario, "--n", str(attrs["n_trajectories"]), *seed,
        "--trajectories", str(attrs["trajectories"]), "--dtype", attrs["dtype"],
        "--out", str(args.store), "--resume"]))
    return EXIT_DAMAGED if not found.whole else EXIT_INCOMPLETE


def _free_params(names: list[str], torque):
    """`--free` names → (`params`, `torque_where`) for `identify.fit`: `inertia`,
    `initial_conditions` (or `ic`), `torque` (every array leaf of the torque), `k` (the
    restoring moments' k, or their K(τ) coefficients)."""
    from .torques import RestoringMoment, SumTorque

    params, where = [], None
    for name in names:
        if name == "inertia":
            params.append("inertia")
        elif name in ("initial_conditions", "ic"):
            params.append("initial_conditions")
        elif name in ("torque", "k"):
            if "torque" not in params:
                params.append("torque")
        else:
            raise ValueError(f"--free: unknown {name!r}; expected inertia, k, torque, ic")
    if "k" in names and "torque" not in names:
        parts = list(torque.torques) if isinstance(torque, SumTorque) else [torque]
        picks = [i for i, t in enumerate(parts) if isinstance(t, RestoringMoment)]
        if not picks:
            raise ValueError("--free k: the scenario's model has no restoring_moment torque")

        def leaf(t):
            return t.k.coeffs if callable(t.k) else t.k

        if isinstance(torque, SumTorque):
            where = lambda tq: tuple(leaf(tq.torques[i]) for i in picks)  # noqa: E731
        else:
            where = leaf
    return tuple(params), where


def _get_path(obj, path):
    for key in path:
        obj = getattr(obj, key.name) if hasattr(key, "name") else obj[key.idx]
    return obj


def _compile_meter(jax):
    """A context in which JAX's own reports are counted: `tracing_s`, the seconds spent
    tracing, lowering and compiling programs in this process (a program loaded from JAX's
    persistent cache is not compiled: its time is not counted), and `loaded`, the programs
    loaded from the caches (JAX's persistent cache, rbdyn_jax's traced programs)."""
    import contextlib

    from . import _traces

    meter = {"tracing_s": 0.0, "loaded": 0, "hit": False}
    work = ("/jax/core/compile/jaxpr_trace_duration",
            "/jax/core/compile/jaxpr_to_mlir_module_duration")

    def event(name, **_):
        if name == "/jax/compilation_cache/cache_hits":  # inside the compile event below
            meter["loaded"] += 1
            meter["hit"] = True

    def duration(name, seconds, **_):
        if name == "/jax/core/compile/backend_compile_duration":
            if not meter["hit"]:
                meter["tracing_s"] += seconds
            meter["hit"] = False
        elif name in work:
            meter["tracing_s"] += seconds

    @contextlib.contextmanager
    def metering():
        hits = _traces.stats["hits"]
        jax.monitoring.register_event_listener(event)
        jax.monitoring.register_event_duration_secs_listener(duration)
        try:
            yield meter
        finally:
            jax.monitoring.unregister_event_listener(event)
            jax.monitoring.unregister_event_duration_listener(duration)
            meter["loaded"] += _traces.stats["hits"] - hits

    return metering()


def _time_text(elapsed: float, meter: dict) -> str:
    """`4.7 s (3.9 s of it tracing and compiling)`, `0.5 s (program loaded from the cache)`:
    what the fit's time held, as `_compile_meter` measured it."""
    parts = []
    if meter["loaded"]:
        parts.append("program loaded from the cache")
    if meter["tracing_s"] >= 0.5:  # not the small programs around a loaded one
        parts.append(f"{meter['tracing_s']:.1f} s of it tracing and compiling")
    return f"{elapsed:.1f} s" + (f" ({', '.join(parts)})" if parts else "")


def _finer(horizons: tuple[float, ...]) -> str:
    """More, shorter stages than `horizons`: half the first, and a stage between each two."""
    h = [horizons[0] / 2, horizons[0]]
    for a, b in zip(horizons, horizons[1:]):
        h += [(a + b) / 2, b]
    return ",".join(f"{x:g}" for x in h)


def _fit_hints(args, res, horizons, params, K) -> list[str]:
    """What to try after a fit that did not converge, for what its result shows."""
    import numpy as np

    loss, decrement = float(res.loss), float(res.decrement)
    hints = []
    if not np.isfinite(loss):
        hints.append("the model could not be solved at the starting point (the loss is not "
                     "finite): start nearer the truth (see the last point)")
    elif decrement >= 1e-2 * loss:  # Gauss–Newton: a step would still lower the loss much
        hints.append(f"the loss ({loss:.4g}) is still falling (a Gauss–Newton step would "
                     f"lower it by up to {decrement:.3g}): more steps, --steps "
                     f"{max(2 * args.steps, 30)}")
    else:
        hints.append(f"the loss stalled at {loss:.4g} (a further step would lower it by at "
                     f"most {decrement:.3g}), a local minimum that more steps do not leave")
    if horizons == (1.0,):
        hints.append("fit growing parts of the records, each stage starting from the last: "
                     "--horizons 0.25,0.5,1 (a long or chaotic record fitted whole stalls in a "
                     "local minimum)")
    else:
        hints.append(f"start from a shorter part of the records, in more stages: --horizons "
                     f"{_finer(horizons)}")
    if "inertia" in params and args.scale is None and not res.scale_identified:
        hints.append("the data fix J only up to scale: fix it with --scale trace=V or --scale "
                     "moment=AXIS:V")
    if res.ill_determined > (0 if res.scale_identified and args.scale is None else 1):
        hints.append(f"{res.ill_determined} direction(s) of the parameters are ill-determined: "
                     "free fewer of them (--free), or fit more data")
    if args.trajectories is not None:
        hints.append(f"fit more records, if the data hold more than the {K} fitted: "
                     f"--trajectories {2 * K}, or leave --trajectories out for all of them")
    hints.append(f"start nearer the truth: the fit starts from the nominal values of the "
                 f"[model] of {args.model} and the first observed states; give --model a "
                 "scenario file whose [model] values are closer (`rbdyn scenarios` names the "
                 "shipped files to copy)")
    return hints


def _fit_verdict(args, res, horizons, params, K) -> int:
    """0 for a converged fit; else `EXIT_NOT_CONVERGED`, with what to try on stderr."""
    if res.converged:
        return 0
    print("rbdyn fit: the fit did not converge: the values above are where it stopped, not a "
          "fit of the data. To try:", file=sys.stderr)
    for hint in _fit_hints(args, res, horizons, params, K):
        print(f"  - {hint}", file=sys.stderr)
    return EXIT_NOT_CONVERGED


def fit_command(args) -> int:
    import json
    import pathlib

    import jax

    jax.config.update("jax_enable_x64", True)
    _compilation_cache(jax)
    import jax.numpy as jnp
    import numpy as np

    from . import identify
    from .integrate import simulate
    from .models import RigidBody
    from .scenario import Scenario, ScenarioError

    try:
        scenario = Scenario.load(args.model)
    except ScenarioError as e:
        print(f"rbdyn fit: invalid scenario: {e}", file=sys.stderr)
        return 2
    model, _ = scenario.build(scenario.nominal())
    if not isinstance(model, RigidBody):
        print("rbdyn fit: only rigid_body scenarios can be fitted (absolute motion).",
              file=sys.stderr)
        return 2
    try:
        data = identify.Observations.from_file(
            args.data, sigma_omega=args.sigma_omega, sigma_quat=args.sigma_quat,
            trajectories=args.trajectories, seq=args.seq)
        params, where = _free_params([s.strip() for s in args.free.split(",") if s.strip()],
                                     model.torque)
    except (ValueError, OSError) as e:
        print(f"rbdyn fit: {e}", file=sys.stderr)
        return 2
    scale = None
    if args.scale:
        kind, _, value = args.scale.partition("=")
        axis, _, v = value.partition(":")
        try:
            if kind == "trace":
                scale = identify.TraceScale(float(value))
            elif kind.startswith("moment"):
                scale = identify.MomentScale(int(axis), float(v))
            else:
                raise ValueError(f"unknown {kind!r}")
        except ValueError as e:  # a bad number, or a scale identify refuses
            print(f"rbdyn fit: --scale is trace=V or moment=AXIS:V ({e})", file=sys.stderr)
            return 2
    K, n = data.ts.shape
    print(f"rbdyn fit: {K} trajectories × {n} samples from {args.data}; model "
          f"{scenario.name} ({', '.join(scenario.torques) or 'no torque'}); free: "
          f"{', '.join(params)}")
    try:
        horizons = tuple(float(x) for x in args.horizons.split(","))
    except ValueError:
        print("rbdyn fit: --horizons is a comma list such as 0.25,0.5,1", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    try:
        with _compile_meter(jax) as meter:
            res = identify.fit(model, data, params=params, torque_where=where, scale=scale,
                               optimizer=identify.LevenbergMarquardt(steps=args.steps),
                               horizons=None if horizons == (1.0,) else horizons)
    except ValueError as e:
        print(f"rbdyn fit: {e}", file=sys.stderr)
        return 2
    elapsed = time.perf_counter() - t0
    lh = np.asarray(res.loss_history)
    if horizons == (1.0,):
        print(f"  loss {lh[0]:.6g} → {lh[-1]:.6g} in at most {args.steps} step"
              f"{'s' if args.steps > 1 else ''}, "
              f"converged: {res.converged}, {_time_text(elapsed, meter)}")
    else:
        print(f"  horizons {', '.join(f'{h:g}' for h in horizons)} of each record, at most "
              f"{args.steps} step{'s' if args.steps > 1 else ''} each: loss {lh[-1]:.6g} over "
              "the whole record, "
              f"converged: {res.converged}, {_time_text(elapsed, meter)}")
    report: dict = {"converged": bool(res.converged), "loss": float(res.loss),
                    "notes": list(res.notes), "time_s": elapsed}
    if "inertia" in params:
        J = np.asarray(res.model.inertia)
        se = np.asarray(res.stderr["inertia"])
        print("  inertia J ± stderr:")
        for i in range(3):
            print("    " + "  ".join(f"{J[i, j]:+.6f} ± {se[i, j]:.2e}" for j in range(3)))
        report.update(inertia=J.tolist(), inertia_stderr=se.tolist())
    if "torque" in params:
        rows = []
        for path, se in jax.tree_util.tree_leaves_with_path(res.stderr["torque"]):
            name = jax.tree_util.keystr(path)
            val = np.atleast_1d(np.asarray(_get_path(res.model.torque, path)))
            se = np.atleast_1d(np.asarray(se))
            for i in range(val.size):
                rows.append((f"{name}[{i}]" if val.size > 1 else name, val.flat[i], se.flat[i]))
        print("  torque parameters ± stderr:")
        for name, v, e in rows:
            print(f"    torque{name:24s} {v:+.6g} ± {e:.2e}")
        report["torque"] = {f"torque{r[0]}": [float(r[1]), float(r[2])] for r in rows}
    for note in res.notes:
        print(f"  note: {note}")
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "fit.json").write_text(json.dumps(report, indent=2))
    try:
        import matplotlib
    except ImportError:
        print(f"wrote {out / 'fit.json'} (no plot: pip install matplotlib)")
        return _fit_verdict(args, res, horizons, params, K)
    from matplotlib.figure import Figure

    del matplotlib
    show = min(K, 4)
    fig = Figure(figsize=(11, 3.0 * show), layout="constrained")
    axes = fig.subplots(show, 2, squeeze=False)
    for k in range(show):
        m = np.asarray(data.mask[k])
        ts = np.asarray(data.ts[k])
        y0 = jax.tree_util.tree_map(lambda x, k=k: x[k], res.y0)
        traj = simulate(res.model, y0, jnp.asarray(ts), throw=False)
        if data.omega is not None:
            ax = axes[k, 0]
            for c in range(3):
                ax.plot(ts[m], np.asarray(data.omega[k])[m, c], ".", ms=3, color=f"C{c}")
                ax.plot(ts, np.asarray(traj.ys.omega)[:, c], "-", color=f"C{c}",
                        label=f"ω_{'xyz'[c]}")
            ax.set(xlabel="t [s]", ylabel="ω [rad/s]", title=f"trajectory {k}: ω observed "
                   "(dots) vs fitted")
            ax.legend(fontsize=7)
        if data.quat is not None:
            ax = axes[k, 1]
            qs, qo = np.asarray(traj.ys.quat), np.asarray(data.quat[k])
            qo = np.where(np.sum(qs * qo, -1, keepdims=True) < 0, -qo, qo)  # same sign
            for c in range(4):
                ax.plot(ts[m], qo[m, c], ".", ms=3, color=f"C{c}")
                ax.plot(ts, qs[:, c], "-", color=f"C{c}", label="q_" + "wxyz"[c])
            ax.set(xlabel="t [s]", ylabel="quaternion", title=f"trajectory {k}: attitude "
                   "observed (dots) vs fitted")
            ax.legend(fontsize=7)
    if not res.converged:
        fig.suptitle("not converged: the fitted curves are where the fit stopped",
                     color="C3")
    fig.savefig(out / "fit.png", dpi=90)
    print(f"wrote {out / 'fit.json'} and {out / 'fit.png'}")
    return _fit_verdict(args, res, horizons, params, K)


def _trajectories_arg(text: str) -> str | int:
    """`--trajectories`: `all`, `none` or a positive integer K."""
    if text in ("all", "none"):
        return text
    if text.isdigit() and int(text) >= 1:
        return int(text)
    raise argparse.ArgumentTypeError(f"expected all, none or a positive integer K, got {text!r}")


def build_parser() -> argparse.ArgumentParser:
    """The `rbdyn` command's argument parser: every subcommand and option (the CLI
    reference of the documentation is generated from it)."""
    parser = argparse.ArgumentParser(
        prog="rbdyn", description="Rotational dynamics of rigid bodies in JAX."
    )
    parser.add_argument("--version", action="version", version=f"rbdyn {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    p_sweep = sub.add_parser("sweep", help="Monte Carlo sweep of a scenario, streamed to zarr")
    p_sweep.add_argument("scenario", help="scenario TOML file or shipped name (rbdyn scenarios)")
    p_sweep.add_argument("--n", type=int, required=True, help="number of trajectories")
    p_sweep.add_argument("--out", required=True, help="output zarr store (a directory)")
    p_sweep.add_argument("--chunk", type=int, default=None,
                         help="trajectories solved and written at a time (default: 1024 on "
                              "CPU; on a GPU the largest power of two its memory holds, at "
                              "most 2^20 per device)")
    p_sweep.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p_sweep.add_argument("--devices", type=int, default=None,
                         help="devices to shard over (default all; on CPU, one per core); "
                              "with --workers/--scheduler, per worker")
    p_sweep.add_argument("--lanes", type=int, default=None,
                         help="lanes per device in the solver loop (default: 64 on CPU; on a "
                              "GPU those simulate_batch takes for a device's share of a chunk: "
                              "all of a share up to 16384, else a third, at most 131072)")
    p_sweep.add_argument("--trajectories", type=_trajectories_arg, default=None,
                         metavar="{all,none,K}",
                         help="whose states the store keeps: all, none (the summaries, status, "
                              "num_steps and inertia only) or every K-th trajectory (default: "
                              "the scenario's [outputs] trajectories, else all)")
    p_sweep.add_argument("--dtype", choices=("float64", "float32"), default=None,
                         help="the precision the sweep computes and stores in (default: the "
                              "scenario's [solver] dtype, else float64)")
    store = p_sweep.add_mutually_exclusive_group()
    store.add_argument("--resume", action="store_true",
                       help="finish an interrupted run in --out")
    store.add_argument("--overwrite", action="store_true",
                       help="replace a sweep store already at --out (and its plots folder)")
    engine = p_sweep.add_mutually_exclusive_group()
    engine.add_argument("--scheduler", default=None, metavar="ADDRESS",
                        help="run the chunks as tasks on the Dask cluster at ADDRESS "
                             "(tcp://HOST:8786); --out must be where its workers reach it: "
                             "a shared filesystem or an object-storage URL")
    engine.add_argument("--workers", type=int, default=None, metavar="K",
                        help="run the chunks as tasks on a new Dask LocalCluster of K "
                             "worker processes on this machine")
    p_export = sub.add_parser("export", help="write a sweep store to a netCDF file")
    p_export.add_argument("store", help="a store written by rbdyn sweep")
    p_export.add_argument("out", help="the netCDF-4 file to write (e.g. sweep.nc)")
    p_export.add_argument("--overwrite", action="store_true", help="replace an existing file")
    p_plot = sub.add_parser("plot", help="PNGs of a sweep store")
    p_plot.add_argument("path", help="a store written by rbdyn sweep")
    p_plot.add_argument("--out", default=None, help="folder for the PNGs (default PATH_plots)")
    p_verify = sub.add_parser("verify", help="check that every chunk of a sweep store is there "
                              "and intact")
    p_verify.add_argument("store", help="a store written by rbdyn sweep")
    p_fit = sub.add_parser("fit", help="identify inertia / torque parameters from observations")
    p_fit.add_argument("data", help="observations: .npz, .csv, or a store/netCDF xarray opens")
    p_fit.add_argument("--model", required=True, help="scenario TOML (or shipped name) giving "
                       "the model and the initial guess (its nominal values)")
    p_fit.add_argument("--free", default="inertia,ic",
                       help="free parameters: inertia, k, torque, ic (default inertia,ic)")
    p_fit.add_argument("--out", default="results/fit", help="folder for fit.json, fit.png")
    p_fit.add_argument("--steps", type=int, default=30,
                       help="Levenberg–Marquardt steps, at most, per horizon (default 30)")
    p_fit.add_argument("--scale", default=None,
                       help="fix the scale of J: trace=V or moment=AXIS:V (torque-free data)")
    p_fit.add_argument("--sigma-omega", type=float, default=None, help="ω noise [rad/s]")
    p_fit.add_argument("--sigma-quat", type=float, default=None, help="attitude noise [rad]")
    p_fit.add_argument("--trajectories", type=int, default=None, help="use the first K")
    p_fit.add_argument("--horizons", default="0.25,0.5,1",
                       help="fit growing fractions of every record, each stage starting from "
                            "the last (default 0.25,0.5,1); 1: the whole record at once")
    p_fit.add_argument("--seq", default="ZXZ", help="Euler sequence of `euler` data")
    sub.add_parser("scenarios", help="list the shipped scenarios")
    p_demo = sub.add_parser("demo", help="summarise and simulate the shipped default body")
    p_demo.add_argument("--steps", type=int, default=5, help="output steps (default 5)")
    p_demo.add_argument("--duration", type=float, default=100.0, help="seconds (default 100)")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    try:
        with warnings.catch_warnings():  # one line each, without the line that warned
            warnings.showwarning = lambda message, *_, **__: print(
                f"rbdyn {args.command}: warning: {message}", file=sys.stderr)
            return _dispatch(parser, args)
    except KeyboardInterrupt:
        print(f"\nrbdyn {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


def _dispatch(parser, args) -> int:
    if args.command == "sweep":
        for name in ("n", "chunk", "lanes", "devices", "workers"):
            v = getattr(args, name)
            if v is not None and v < 1:
                parser.error(f"--{name} must be ≥ 1")
        if args.seed < 0:
            parser.error("--seed must be ≥ 0")
        return sweep_command(args)
    if args.command == "plot":
        return plot_command(args)
    if args.command == "export":
        return export_command(args)
    if args.command == "verify":
        return verify_command(args)
    if args.command == "fit":
        if args.steps < 1:
            parser.error("--steps must be ≥ 1")
        return fit_command(args)
    if args.command == "scenarios":  # read from the files: no JAX
        from ._catalogue import catalogue

        for name, description in catalogue().items():
            print(f"{name:28s} {description}")
        return 0
    if args.command == "demo":
        if args.steps < 1:
            parser.error("--steps must be ≥ 1")
        return demo(args.steps, args.duration)
    return 2  # unreachable: argparse rejects unknown commands


if __name__ == "__main__":
    sys.exit(main())
