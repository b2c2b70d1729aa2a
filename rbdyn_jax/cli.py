"""The `rbdyn` command (the only layer that prints; DESIGN.md).

- `rbdyn sweep SCENARIO --n N --out PATH [--chunk C] [--seed S] [--devices D] [--resume]`:
  a Monte Carlo sweep of a scenario (a TOML file or a shipped name, `rbdyn scenarios`)
  streamed to a zarr store, with a progress bar and a summary table (`rbdyn_jax.sweep`).
- `rbdyn plot PATH [--out DIR]`: PNGs of a sweep (summary histograms, sample
  trajectories, polhodes on their energy ellipsoids, status counts).
- `rbdyn scenarios`: the shipped scenarios.
- `rbdyn demo`: the shipped default body, one trajectory, printed.

On a CPU-only machine `rbdyn sweep` splits the host into `--devices` XLA devices (default:
one per core), since one XLA CPU device uses about one core for these solves.
"""

import argparse
import os
import sys
import time


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
    print("  inertia tensor J [kg m²] (PHYSICS.md §3):")
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
    # which flips again and again (Euler–Poinsot, PHYSICS.md §4), solved with diffrax.
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


def _host_devices(n: int | None) -> None:
    """Ask XLA for `n` CPU devices (default: one per core) unless XLA_FLAGS already says;
    must run before JAX initialises its backend. No effect on GPU/TPU devices."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_force_host_platform_device_count" in flags:
        return
    count = n if n is not None else (os.cpu_count() or 1)
    os.environ["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={count}".strip()


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


def sweep_command(args) -> int:
    _host_devices(args.devices)
    import jax

    jax.config.update("jax_enable_x64", True)
    from tqdm import tqdm

    from . import sweep

    try:
        scenario = sweep.Scenario.load(args.scenario)
    except sweep.ScenarioError as e:
        print(f"rbdyn sweep: invalid scenario: {e}", file=sys.stderr)
        return 2
    devices = jax.devices()
    n_dev = args.devices if args.devices is not None else len(devices)
    print(f"rbdyn sweep: {scenario.name} — {scenario.description}")
    print(f"  {args.n} trajectories in chunks of {args.chunk} on {n_dev} "
          f"{devices[0].platform} device(s), {args.lanes} lanes per solver loop, "
          f"seed {args.seed}, → {args.out}")
    bar = tqdm(total=args.n, unit="traj", unit_scale=True, dynamic_ncols=True,
               desc="solving (first chunk compiles)", file=sys.stderr)

    def progress(p: "sweep.Progress") -> None:
        if bar.n == 0 and p.done > p.solved_now:  # resumed: count the finished ones
            bar.update(p.done - p.solved_now)
        bar.set_description("solving")
        bar.set_postfix(failed=p.failed)
        bar.update(p.solved_now)

    t0 = time.perf_counter()
    try:
        path = sweep.run(scenario, args.n, args.out, chunk=args.chunk, seed=args.seed,
                         devices=n_dev, lanes=args.lanes, resume=args.resume,
                         progress=progress)
    except ValueError as e:
        bar.close()
        print(f"rbdyn sweep: {e}", file=sys.stderr)
        return 2
    bar.close()
    elapsed = time.perf_counter() - t0
    print_summary(sweep.summarize(path))
    print(f"\nwrote {path} in {elapsed:.1f} s (open with xarray.open_zarr({str(path)!r}));"
          f" plots: rbdyn plot {path}")
    return 0


def plot_command(args) -> int:
    from ._plots import plot_sweep

    files = plot_sweep(args.path, args.out)
    for f in files:
        print(f"wrote {f}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="rbdyn", description="Rotational dynamics of rigid bodies in JAX."
    )
    sub = parser.add_subparsers(dest="command", required=True)
    p_sweep = sub.add_parser("sweep", help="Monte Carlo sweep of a scenario, streamed to zarr")
    p_sweep.add_argument("scenario", help="scenario TOML file or shipped name (rbdyn scenarios)")
    p_sweep.add_argument("--n", type=int, required=True, help="number of trajectories")
    p_sweep.add_argument("--out", required=True, help="output zarr store (a directory)")
    p_sweep.add_argument("--chunk", type=int, default=1024,
                         help="trajectories solved and written at a time (default 1024)")
    p_sweep.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p_sweep.add_argument("--devices", type=int, default=None,
                         help="devices to shard over (default all; on CPU, one per core)")
    p_sweep.add_argument("--lanes", type=int, default=64,
                         help="trajectories per vmapped solver loop (default 64)")
    p_sweep.add_argument("--resume", action="store_true",
                         help="finish an interrupted run in --out")
    p_plot = sub.add_parser("plot", help="PNGs of a sweep store")
    p_plot.add_argument("path", help="a store written by rbdyn sweep")
    p_plot.add_argument("--out", default=None, help="folder for the PNGs (default PATH_plots)")
    sub.add_parser("scenarios", help="list the shipped scenarios")
    p_demo = sub.add_parser("demo", help="summarise and simulate the shipped default body")
    p_demo.add_argument("--steps", type=int, default=5, help="output steps (default 5)")
    p_demo.add_argument("--duration", type=float, default=100.0, help="seconds (default 100)")
    args = parser.parse_args(argv)
    if args.command == "sweep":
        for name in ("n", "chunk", "lanes", "devices"):
            v = getattr(args, name)
            if v is not None and v < 1:
                parser.error(f"--{name} must be ≥ 1")
        if args.seed < 0:
            parser.error("--seed must be ≥ 0")
        return sweep_command(args)
    if args.command == "plot":
        return plot_command(args)
    if args.command == "scenarios":
        from . import sweep

        for name in sweep.list_scenarios():
            sc = sweep.Scenario.load(name)
            print(f"{name:28s} {sc.description}")
        return 0
    if args.command == "demo":
        if args.steps < 1:
            parser.error("--steps must be ≥ 1")
        return demo(args.steps, args.duration)
    return 2  # unreachable: argparse rejects unknown commands


if __name__ == "__main__":
    sys.exit(main())
