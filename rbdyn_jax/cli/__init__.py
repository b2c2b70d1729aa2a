"""The `rbdyn` command (`rbdyn_jax.cli:main`, also `python -m rbdyn_jax.cli`): the only layer
that prints. The library below it returns values, and reads files only through its own
loaders (`identify.Observations.from_file`).

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

The modules, one idea each (none imports JAX or NumPy at its top: `--help`, `--version` and
`rbdyn scenarios` need neither, and each command imports what it computes with):

- `_main`: `main`, the entry point, which runs a command;
- `_parser`: `build_parser`, every subcommand and option;
- `_common`: the exit statuses, JAX's persistent compilation cache, error messages;
- `_sweep`: `rbdyn sweep`, its progress and summary;
- `_store`: `rbdyn export`, `rbdyn plot` and `rbdyn verify`, on a sweep store;
- `_fit`: `rbdyn fit`, its report, plot and advice (the observations read by
  `identify.Observations.from_file`);
- `_demo`: `rbdyn demo` and `rbdyn scenarios`.
"""

from ._common import (
    EXIT_ALL_FAILED as EXIT_ALL_FAILED,
    EXIT_DAMAGED as EXIT_DAMAGED,
    EXIT_INCOMPLETE as EXIT_INCOMPLETE,
    EXIT_INTERRUPTED as EXIT_INTERRUPTED,
    EXIT_NOT_CONVERGED as EXIT_NOT_CONVERGED,
    EXIT_SOME_FAILED as EXIT_SOME_FAILED,
    EXIT_USAGE as EXIT_USAGE,
)
from ._main import main as main
from ._parser import build_parser as build_parser

__all__ = [
    "EXIT_ALL_FAILED",
    "EXIT_DAMAGED",
    "EXIT_INCOMPLETE",
    "EXIT_INTERRUPTED",
    "EXIT_NOT_CONVERGED",
    "EXIT_SOME_FAILED",
    "EXIT_USAGE",
    "build_parser",
    "main",
]
