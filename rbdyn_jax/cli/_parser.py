"""The `rbdyn` command's argument parser, every subcommand and option (the CLI reference of
the documentation is generated from it)."""

import argparse

from .._version import __version__


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
    p_sweep.add_argument(
        "--chunk",
        type=int,
        default=None,
        help="trajectories solved and written at a time (default: 1024 on "
        "CPU; on a GPU the largest power of two its memory holds, at "
        "most 2^20 per device)",
    )
    p_sweep.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p_sweep.add_argument(
        "--devices",
        type=int,
        default=None,
        help="devices to shard over (default all; on CPU, one per core); "
        "with --workers/--scheduler, per worker",
    )
    p_sweep.add_argument(
        "--lanes",
        type=int,
        default=None,
        help="lanes per device in the solver loop (default: 64 on CPU; on a "
        "GPU those simulate_batch takes for a device's share of a chunk: "
        "all of a share up to 16384, else a third, at most 131072)",
    )
    p_sweep.add_argument(
        "--trajectories",
        type=_trajectories_arg,
        default=None,
        metavar="{all,none,K}",
        help="whose states the store keeps: all, none (the summaries, status, "
        "num_steps and inertia only) or every K-th trajectory (default: "
        "the scenario's [outputs] trajectories, else all)",
    )
    p_sweep.add_argument(
        "--dtype",
        choices=("float64", "float32"),
        default=None,
        help="the precision the sweep computes and stores in (default: the "
        "scenario's [solver] dtype, else float64)",
    )
    store = p_sweep.add_mutually_exclusive_group()
    store.add_argument("--resume", action="store_true", help="finish an interrupted run in --out")
    store.add_argument(
        "--overwrite",
        action="store_true",
        help="replace a sweep store already at --out (and its plots folder)",
    )
    engine = p_sweep.add_mutually_exclusive_group()
    engine.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="run the chunks as tasks on the Dask cluster at ADDRESS "
        "(tcp://HOST:8786); --out must be where its workers reach it: "
        "a shared filesystem or an object-storage URL",
    )
    engine.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="K",
        help="run the chunks as tasks on a new Dask LocalCluster of K "
        "worker processes on this machine",
    )
    p_export = sub.add_parser("export", help="write a sweep store to a netCDF file")
    p_export.add_argument("store", help="a store written by rbdyn sweep")
    p_export.add_argument("out", help="the netCDF-4 file to write (e.g. sweep.nc)")
    p_export.add_argument("--overwrite", action="store_true", help="replace an existing file")
    p_plot = sub.add_parser("plot", help="PNGs of a sweep store")
    p_plot.add_argument("path", help="a store written by rbdyn sweep")
    p_plot.add_argument("--out", default=None, help="folder for the PNGs (default PATH_plots)")
    p_verify = sub.add_parser(
        "verify", help="check that every chunk of a sweep store is there and intact"
    )
    p_verify.add_argument("store", help="a store written by rbdyn sweep")
    p_fit = sub.add_parser("fit", help="identify inertia / torque parameters from observations")
    p_fit.add_argument("data", help="observations: .npz, .csv, or a store/netCDF xarray opens")
    p_fit.add_argument(
        "--model",
        required=True,
        help="scenario TOML (or shipped name) giving "
        "the model and the initial guess (its nominal values)",
    )
    p_fit.add_argument(
        "--free",
        default="inertia,ic",
        help="free parameters: inertia, k, torque, ic (default inertia,ic)",
    )
    p_fit.add_argument("--out", default="results/fit", help="folder for fit.json, fit.png")
    p_fit.add_argument(
        "--overwrite", action="store_true", help="replace a fit.json or fit.png already in --out"
    )
    p_fit.add_argument(
        "--steps",
        type=int,
        default=30,
        help="Levenberg–Marquardt steps, at most, per horizon (default 30)",
    )
    p_fit.add_argument(
        "--scale",
        default=None,
        help="fix the scale of J: trace=V or moment=AXIS:V (torque-free data)",
    )
    p_fit.add_argument("--sigma-omega", type=float, default=None, help="ω noise [rad/s]")
    p_fit.add_argument("--sigma-quat", type=float, default=None, help="attitude noise [rad]")
    p_fit.add_argument("--trajectories", type=int, default=None, help="use the first K")
    p_fit.add_argument(
        "--horizons",
        default="0.25,0.5,1",
        help="fit growing fractions of every record, each stage starting from "
        "the last (default 0.25,0.5,1); 1: the whole record at once",
    )
    p_fit.add_argument("--seq", default="ZXZ", help="Euler sequence of `euler` data")
    p_fit.add_argument(
        "--normalize-quat",
        action="store_true",
        help="renormalise the observed quaternions (data written to a few decimals)",
    )
    sub.add_parser("scenarios", help="list the shipped scenarios")
    p_demo = sub.add_parser("demo", help="summarise and simulate the shipped default body")
    p_demo.add_argument("--steps", type=int, default=5, help="output steps (default 5)")
    p_demo.add_argument("--duration", type=float, default=100.0, help="seconds (default 100)")
    return parser
