"""The commands on a sweep store: `rbdyn export` (to netCDF), `rbdyn plot` (PNGs) and
`rbdyn verify` (every chunk there and intact)."""

import shlex
import sys
import warnings

from ._common import EXIT_DAMAGED, EXIT_INCOMPLETE, EXIT_USAGE, error_text


def export_command(args) -> int:
    """`rbdyn export STORE OUT`: the store as a netCDF-4 file."""
    from .. import sweep

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
        print(f"rbdyn export: {error_text(e, args.out)}", file=sys.stderr)
        return EXIT_USAGE
    print(f"wrote {path} (open with xarray.open_dataset({str(path)!r}))")
    return 0


def plot_command(args) -> int:
    """`rbdyn plot PATH`: PNGs of the store, and a note on each plot it cannot draw."""
    from .. import sweep
    from .._plots import plot_sweep

    if (code := _store_problem(sweep, "plot", args.path)) is not None:
        return code
    try:
        with sweep.reading(args.path):
            files = plot_sweep(args.path, args.out)
    except sweep.StoreDamagedError as e:
        print(f"rbdyn plot: {e}", file=sys.stderr)
        return EXIT_DAMAGED
    except OSError as e:
        print(f"rbdyn plot: {error_text(e, args.out or args.path)}", file=sys.stderr)
        return EXIT_USAGE
    for f in files:
        print(f"wrote {f}")
    import xarray as xr

    with xr.open_zarr(args.path) as ds:
        if "omega" not in ds:
            print(
                "note: no trajectories.png or polhodes.png: the store keeps no states (a "
                'sweep with trajectories = "none"); sweep with --trajectories all or K '
                "to plot them"
            )
        elif not any(str(f).endswith("trajectories.png") for f in files):
            print(
                "note: no trajectories.png or polhodes.png: no trajectory whose states the "
                "store keeps succeeded (status.png counts the outcomes)"
            )
        elif not any(str(f).endswith("polhodes.png") for f in files):
            print(
                "note: no polhodes.png: this scenario's torque does not conserve the "
                "kinetic energy, so ω leaves the energy ellipsoid; trajectories.png shows "
                "|ω| and the nutation against time"
            )
    return 0


def verify_command(args) -> int:
    """`rbdyn verify STORE`: every chunk there and intact (0), or what is missing or damaged
    and the command that finishes the sweep."""
    from .. import sweep

    try:
        found = sweep.verify(args.store)
    except (ValueError, OSError) as e:
        print(f"rbdyn verify: {error_text(e, args.store)}", file=sys.stderr)
        return EXIT_USAGE
    print(found)
    if found.complete:
        return 0
    from .._catalogue import catalogue

    attrs = sweep.open_dataset(args.store).attrs
    name = attrs["scenario_name"]
    scenario = name if name in catalogue() else "SCENARIO.toml"  # the file it was run from
    seed = [] if attrs["seed"] == 0 else ["--seed", str(attrs["seed"])]
    print(
        "finish it with: "
        + shlex.join(
            [
                "rbdyn",
                "sweep",
                scenario,
                "--n",
                str(attrs["n_trajectories"]),
                *seed,
                "--trajectories",
                str(attrs["trajectories"]),
                "--dtype",
                attrs["dtype"],
                "--out",
                str(args.store),
                "--resume",
            ]
        )
    )
    return EXIT_DAMAGED if not found.whole else EXIT_INCOMPLETE


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
        print(f"rbdyn {command}: {error_text(e, store)}", file=sys.stderr)
        return EXIT_USAGE
    for w in caught:
        print(f"rbdyn {command}: warning: {w.message}", file=sys.stderr)
    return None
