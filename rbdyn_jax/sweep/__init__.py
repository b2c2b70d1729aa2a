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
of Dask workers** at a given `lanes` of 16 or more (tested at 16). With fewer lanes XLA may
compile a loop over the lanes unrolled (every while loop is compiled whole:
`configure_xla`), and one lane's arithmetic can then differ from another's in its last bits
(seen at 3, 4, 6 and 8 lanes on an AVX-512 CPU): a trajectory's results depend on its lane
within the block, so on the chunking, and a repaired store agrees with an uninterrupted run
to round-off, not bitwise.
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

The modules, one idea each:

- `_chunk`: the compiled chunk solver (a chunk sampled and solved in one program, sharded
  over the local devices) and the runner that keeps it for the next chunk;
- `_chunking`: the chunk size and lanes for the devices at hand;
- `_store`: the zarr store (layout, CF metadata, creation, resumption checks, writing);
- `_verify`: verifying and repairing a store, and the readers' refusal of a damaged one;
- `_run`: `run` in this process or as Dask tasks (`solve_chunk`);
- `_read`: the dataset, summaries and netCDF export.
"""

from .._plots import plots_dir as plots_dir
from ._chunking import chunking as chunking, trajectory_bytes as trajectory_bytes
from ._read import (
    open_dataset as open_dataset,
    summarize as summarize,
    to_netcdf as to_netcdf,
)
from ._run import Progress as Progress, run as run, solve_chunk as solve_chunk
from ._store import status_meanings as status_meanings
from ._verify import (
    Damage as Damage,
    IncompleteStoreWarning as IncompleteStoreWarning,
    StoreDamagedError as StoreDamagedError,
    Verification as Verification,
    check as check,
    reading as reading,
    verify as verify,
)

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
    "reading",
    "run",
    "solve_chunk",
    "status_meanings",
    "summarize",
    "to_netcdf",
    "trajectory_bytes",
    "verify",
]
