"""Observation files: the arrays of `Observations.from_file` read from an NPZ archive, a CSV
table, or a dataset xarray opens (a sweep store, a netCDF file)."""

import csv
import pathlib
import warnings

import numpy as np

# The arrays an NPZ file may hold: `Observations`' arguments, and `seq` for `euler`.
NPZ_ARRAYS = ("ts", "omega", "quat", "euler", "seq", "sigma_omega", "sigma_quat", "mask")
# A CSV file's columns of each observed field.
CSV_COLUMNS = {"omega": ("wx", "wy", "wz"), "quat": ("qw", "qx", "qy", "qz")}
# The rank of each array with its leading trajectory axis (K, n, …): one of lower rank
# (shared times, a σ per sample or per component) is broadcast over the trajectories.
WITH_TRAJECTORIES = {
    "ts": 2,
    "omega": 3,
    "quat": 3,
    "euler": 3,
    "mask": 2,
    "sigma_omega": 3,
    "sigma_quat": 2,
}


def read_fields(path, *, trajectories: int | None, seq: str) -> tuple[dict, str]:
    """`({argument: array}, seq)` for `Observations` from the file at `path` (its format by
    its suffix, as `Observations.from_file` describes), the first `trajectories` kept."""
    p = pathlib.Path(path)
    if trajectories is not None and (
        isinstance(trajectories, bool)
        or not isinstance(trajectories, int | np.integer)
        or trajectories < 1
    ):
        raise ValueError(f"`trajectories` must be a positive int or None, got {trajectories!r}.")
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such file")
    if p.suffix == ".npz":
        fields, seq = _npz(p, seq)
    elif p.suffix == ".csv":
        fields = _csv(p)
    else:
        return _dataset(p, trajectories), seq  # sliced as it is read
    if trajectories is not None:
        for k, rank in WITH_TRAJECTORIES.items():
            if k in fields and np.ndim(fields[k]) == rank:
                fields[k] = fields[k][:trajectories]
    return fields, seq


def _npz(p: pathlib.Path, seq: str) -> tuple[dict, str]:
    try:
        z = np.load(p)
    except (ValueError, OSError) as e:  # not a zip archive: NumPy tries it as a pickle
        raise ValueError(f"{p}: not an NPZ archive of arrays ({e})") from e
    if not isinstance(z, np.lib.npyio.NpzFile):  # a single `.npy` array saved as `.npz`
        raise ValueError(f"{p}: not an NPZ archive of arrays")
    with z:
        unknown = set(z.files) - set(NPZ_ARRAYS)
        if unknown:
            raise ValueError(f"{p}: unknown arrays {sorted(unknown)}")
        if "ts" not in z.files:
            raise ValueError(f"{p}: no `ts` array")
        fields = {k: z[k] for k in z.files}
    if "seq" in fields:
        seq = str(fields.pop("seq"))
    return fields, seq


def _csv(p: pathlib.Path) -> dict:
    with open(p, newline="", encoding="utf-8", errors="replace") as f:
        header = next(csv.reader(f), [])
    # A column with no name (the index column `pandas.DataFrame.to_csv` writes first) is
    # read and ignored, as any column that is no field's.
    names = [h.strip() or f"unnamed_{i}" for i, h in enumerate(header)]
    if "t" not in names:
        raise ValueError(f"{p}: the header must name a `t` column, got {tuple(names)}")
    try:
        with warnings.catch_warnings():  # no rows: said below
            warnings.simplefilter("ignore", UserWarning)
            table = np.genfromtxt(p, delimiter=",", skip_header=1, names=names)
    except ValueError as e:  # rows of different lengths, say
        raise ValueError(f"{p}: not a CSV table of numbers ({e})") from e
    names = table.dtype.names
    table = np.atleast_1d(table)  # a single row reads as a 0-d record
    if table.size == 0:
        raise ValueError(f"{p}: no rows under the header")
    fields: dict = {}
    if "trajectory" in names:
        ids = table["trajectory"]
        if not np.all(np.isfinite(ids) & (ids == np.round(ids))):
            raise ValueError(f"{p}: the `trajectory` column must hold integers")
        traj = ids.astype(int)
    else:
        traj = np.zeros(len(table), int)
    ids = np.unique(traj)
    n = max(int(np.sum(traj == i)) for i in ids)
    K = len(ids)
    ts = np.full((K, n), np.nan)
    mask = np.zeros((K, n), bool)
    for name, cols in CSV_COLUMNS.items():
        if all(c in names for c in cols):
            fields[name] = np.full((K, n, len(cols)), np.nan)
        elif any(c in names for c in cols):
            raise ValueError(f"{p}: `{name}` needs all of the columns {cols}")
    if not fields:
        raise ValueError(
            f"{p}: the header names no observed field: columns "
            f"{CSV_COLUMNS['omega']} and/or {CSV_COLUMNS['quat']}, got {names}"
        )
    for k, i in enumerate(ids):
        rows = table[traj == i]
        ts[k, : len(rows)] = rows["t"]
        mask[k, : len(rows)] = True
        for name, cols in CSV_COLUMNS.items():
            if name in fields:
                fields[name][k, : len(rows)] = np.stack([rows[c] for c in cols], -1)
    fields.update(ts=ts, mask=mask)
    return fields


def _dataset(p: pathlib.Path, trajectories: int | None) -> dict:
    import xarray as xr

    try:
        ds = xr.open_zarr(p) if p.is_dir() else xr.open_dataset(p)
    except Exception as e:  # xarray's and its backends' errors have no common type
        raise ValueError(
            f"{p}: not a .npz or .csv file, nor a dataset xarray opens (a sweep "
            f"store, a netCDF file): {e}"
        ) from e
    with ds:
        if "omega" not in ds and "quat" not in ds:
            raise ValueError(
                f"{p} holds no ω or attitude to fit (a sweep store keeping no "
                "states: sweep with --trajectories all or K)"
            )
        if "time" not in ds:
            raise ValueError(f"{p}: no `time` coordinate")
        # A sweep keeping every K-th trajectory's states has them over `sampled_trajectory`.
        dim = "sampled_trajectory" if "sampled_trajectory" in ds.dims else "trajectory"
        if "status" in ds:
            status = ds.status.values
            if dim == "sampled_trajectory":
                status = ds.status.sel(trajectory=ds.sampled_trajectory.values).values
            ds = ds.isel({dim: np.nonzero(status == 0)[0]})
        if trajectories is not None:
            ds = ds.isel({dim: slice(0, trajectories)})
        fields = {"ts": ds["time"].values}
        for name in ("omega", "quat"):
            if name in ds:
                fields[name] = ds[name].values
    return fields
