"""The zarr store: its layout, CF metadata, creation, resumption checks and writing."""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import shutil
import warnings
from collections.abc import Callable

import jax
import numpy as np

from .._plots import plots_dir
from ..integrate import (
    result_names,
)
from ..scenario import SUMMARIES, Scenario
from ._chunk import _STATES

CONVENTIONS = (
    "Conventions of the rbdyn_jax physics guide (docs/physics.md#conventions): "
    "quat = [w, x, y, z] (scalar first), unit, rotating body "
    "components into the parent frame (O0 for rigid_body, the transport frame O1 for "
    "relative_rigid_body); omega in body components, rad/s (the rate relative to O1 for "
    "relative_rigid_body); inertia in body axes; times in s; angles in rad."
)

# name: (dims, units, long_name, description); the summaries add theirs from SUMMARIES.
_VARIABLES = {
    "omega": (
        ("trajectory", "time", "axis"),
        "rad/s",
        "body angular velocity",
        "angular velocity in body axes (relative to the transport frame O1 for "
        "relative_rigid_body); NaN where the trajectory failed",
    ),
    "quat": (
        ("trajectory", "time", "quat_component"),
        "1",
        "attitude quaternion",
        "unit quaternion [w, x, y, z] rotating body components into the parent frame; "
        "NaN where the trajectory failed",
    ),
    "inertia": (
        ("trajectory", "row", "col"),
        "kg m2",
        "inertia tensor",
        "the sampled inertia tensor in body axes",
    ),
    "status": (
        ("trajectory",),
        "1",
        "solver status",
        "result of the solve: 0 successful, -1 not run yet, otherwise the failure "
        "named by flag_meanings",
    ),
    "num_steps": (
        ("trajectory",),
        "1",
        "solver steps",
        "steps the solver took (accepted and rejected)",
    ),
}
_COORDS = {
    "time": ("s", "time", "output time"),
    "trajectory": (
        "1",
        "trajectory index",
        "index i of the trajectory, drawn from fold_in(key(seed), i)",
    ),
    "sampled_trajectory": (
        "1",
        "sampled trajectory index",
        "index i of a trajectory whose states are stored (every K-th: i = "
        "0, K, 2K, ...); its other variables are at trajectory = i",
    ),
}
_LABELS = {
    "axis": (["x", "y", "z"], "body axis", "component along a body axis"),
    "quat_component": (
        ["w", "x", "y", "z"],
        "quaternion component",
        "component of the quaternion, scalar first",
    ),
    "row": (["x", "y", "z"], "inertia tensor row", "row of the inertia tensor (body axis)"),
    "col": (["x", "y", "z"], "inertia tensor column", "column of the inertia tensor (body axis)"),
}
_NOT_RUN = -1


def status_meanings() -> dict[int, str]:
    """`{code: name}` of every value of a store's `status` (−1 `not_run`, then the
    `RESULTS` codes); the store carries them as `flag_values` / `flag_meanings`."""
    return {_NOT_RUN: "not_run", **result_names()}


@dataclasses.dataclass(frozen=True)
class _Location:
    """Where a store is: a local path (made absolute, for workers started elsewhere), or a
    URL fsspec opens (`s3://…`, `gs://…`, `file://…`) with its `storage_options`."""

    url: str
    options: dict

    @classmethod
    def of(cls, out: str | pathlib.Path, storage_options: dict | None = None) -> _Location:
        if "://" not in str(out):
            return cls(str(pathlib.Path(out).absolute()), {})
        options = dict(storage_options or {})
        if str(out).startswith("file://"):
            options.setdefault("auto_mkdir", True)  # object stores need no directories
        return cls(str(out), options)

    @property
    def is_url(self) -> bool:
        return "://" in self.url

    def group(self, mode: str):
        import zarr

        return zarr.open_group(
            self.url,
            mode=mode,
            zarr_format=3,
            storage_options=self.options if self.is_url else None,
        )

    def fs(self):
        """(fsspec filesystem, root path in it)."""
        import fsspec

        return fsspec.core.url_to_fs(self.url, **self.options)

    def is_store(self) -> bool:
        """Whether a sweep store is here: its group's metadata holds the consolidated
        metadata of its arrays, written last when a store is made."""
        fs, root = self.fs()
        try:
            meta = json.loads(fs.cat_file(f"{root}/zarr.json"))
        except (OSError, ValueError):
            return False
        return meta.get("node_type") == "group" and bool(meta.get("consolidated_metadata"))

    def is_empty(self) -> bool:
        fs, root = self.fs()
        return not fs.exists(root) or (fs.isdir(root) and not fs.ls(root))

    def remove(self) -> None:
        fs, root = self.fs()
        if fs.exists(root):
            fs.rm(root, recursive=True)


def _create_store(loc: _Location, sc: Scenario, n: int, chunk: int, seed: int, lanes: int):
    """A new store for `n` trajectories of `sc` in chunks of `chunk`: every variable and
    coordinate with its metadata, `status` −1 everywhere, the global attributes."""
    from .._version import __version__

    g = loc.group("w")
    every = sc.trajectories if isinstance(sc.trajectories, int) else None
    sampled = n if every is None else -(-n // every)  # rows of the states
    rows = {"omega": sampled, "quat": sampled}
    shapes = {"omega": (sc.n_times, 3), "quat": (sc.n_times, 4), "inertia": (3, 3)}
    dtypes = {"status": "int32", "num_steps": "int64"}
    meanings = status_meanings()
    names = [v for v in _VARIABLES if v not in _STATES or sc.trajectories != "none"]
    for name in [*names, *sc.summaries]:
        if name in _VARIABLES:
            dims, units, long_name, description = _VARIABLES[name]
        else:
            summary = SUMMARIES[name]
            dims, units, long_name, description = (
                ("trajectory",),
                summary.units,
                name,
                summary.description,
            )
        length, chunk_rows = rows.get(name, n), chunk
        if every is not None and name in _STATES:
            # A chunk of trajectories holds chunk / K sampled ones (`chunking` makes the
            # chunk a multiple of K, or K is larger and it holds at most one).
            dims, chunk_rows = ("sampled_trajectory", *dims[1:]), max(1, chunk // every)
            description += (
                f"; stored for one trajectory in {every}: trajectories 0, "
                f"{every}, {2 * every}, ... (the coordinate sampled_trajectory)"
            )
        shape = (length, *shapes.get(name, ()))
        dtype = dtypes.get(name, sc.dtype)
        a = _create_array(
            g,
            name,
            shape,
            (min(chunk_rows, length),) + shape[1:],
            dtype,
            np.nan if dtype == sc.dtype else _NOT_RUN,
            dims,
        )
        a.attrs.update({"units": units, "long_name": long_name, "description": description})
    g["status"].attrs.update(
        {"flag_values": list(meanings), "flag_meanings": " ".join(meanings.values())}
    )
    # The indices (their lengths here) are written a block at a time below.
    indices = {"trajectory": n, **({"sampled_trajectory": sampled} if every else {})}
    labels = {
        k: v
        for k, v in _LABELS.items()  # those of the variables it holds
        if sc.trajectories != "none" or k not in ("axis", "quat_component")
    }
    coords = {
        "time": sc.ts,
        **{k: None for k in indices},
        **{k: np.asarray(v[0]) for k, v in labels.items()},
    }
    for name, values in coords.items():
        if values is None:
            shape, dtype, fill = (indices[name],), np.int64, _NOT_RUN
        else:
            shape, dtype = values.shape, (str if values.dtype.kind == "U" else values.dtype)
            fill = "" if dtype is str else np.nan
        a = _create_array(g, name, shape, (min(shape[0], _COORD_CHUNK),), dtype, fill, (name,))
        units, long_name, description = (
            _COORDS[name] if name in _COORDS else (None, *_LABELS[name][1:])
        )
        a.attrs.update(
            {
                "long_name": long_name,
                "description": description,
                **({"units": units} if units else {}),
            }
        )
    _write_coordinates(g, sc)
    # status −1 (not run) written, so that every status chunk is in the store.
    for start in range(0, n, _COORD_CHUNK):
        _filled(g, "status")[start : start + _COORD_CHUNK] = _NOT_RUN
    # Attribute values are strings and numbers only, so that netCDF can hold them too.
    g.attrs.update(
        {
            "title": f"rbdyn_jax Monte Carlo sweep: {sc.name}",
            "Conventions": "CF-1.11",
            "source": f"rbdyn_jax {__version__} (jax {jax.__version__})",
            "scenario_name": sc.name,
            "scenario": json.dumps(sc.source),
            "model_kind": sc.kind,
            "seed": seed,
            "n_trajectories": n,
            "chunk": chunk,
            "lanes": lanes,
            "trajectories": sc.trajectories,
            "dtype": sc.dtype,
            "summaries": " ".join(sc.summaries),
            "rbdyn_jax_conventions": CONVENTIONS,
            "rbdyn_jax_version": __version__,
            "jax_version": jax.__version__,
            "complete": 0,
        }
    )
    _consolidate(g)
    return g


_COORD_CHUNK = 1 << 20  # the chunk of the index coordinates; rows written at a time

# Blosc's compressor and level (its byte shuffle for multi-byte types, zarr's default).
# A sweep's floating-point values barely compress (their low bits are noise), so a fast
# compressor stores nearly as much: with LZ4 a store is 3–4 % larger than with Zstandard
# at level 5 and is written 2–3 times faster (benchmarks/store_write.py), which matters
# where a GPU solves a chunk faster than the calling process writes the one before.
COMPRESSION = {"cname": "lz4", "clevel": 5}


def _create_array(g, name: str, shape: tuple, chunks: tuple, dtype, fill, dims: tuple):
    """An array of the store: `fill` (NaN, −1 or "") wherever nothing is written, every
    chunk compressed (`COMPRESSION`) and checksummed (CRC32C after compression), so that a
    chunk whose bytes changed is found by `verify` and fails when read."""
    from zarr.codecs import BloscCodec, Crc32cCodec

    return g.create_array(
        name,
        shape=shape,
        chunks=chunks,
        dtype=dtype,
        fill_value=fill,
        dimension_names=list(dims),
        compressors=[BloscCodec(**COMPRESSION), Crc32cCodec()],
    )


def _filled(g, name: str):
    """The store's array `name` to write to: a chunk is written even when it holds only the
    fill value (NaN, −1), so that a chunk the store lacks is one it lost."""
    return g[name].with_config({"write_empty_chunks": True})


def _write_coordinates(g, sc: Scenario) -> None:
    """Write the store's coordinates: the output times, the axis labels and the trajectory
    indices (a block at a time)."""
    for name, (labels, *_) in _LABELS.items():
        if name in g:
            _filled(g, name)[:] = np.asarray(labels, dtype=object)
    _filled(g, "time")[:] = sc.ts
    n = g["trajectory"].shape[0]
    for start in range(0, n, _COORD_CHUNK):
        stop = min(start + _COORD_CHUNK, n)
        _filled(g, "trajectory")[start:stop] = np.arange(start, stop)
    if "sampled_trajectory" in g:
        every, sampled = sc.trajectories, g["sampled_trajectory"].shape[0]
        for start in range(0, sampled, _COORD_CHUNK):
            stop = min(start + _COORD_CHUNK, sampled)
            _filled(g, "sampled_trajectory")[start:stop] = every * np.arange(start, stop)


def _consolidate(g) -> None:
    """Consolidate the store's metadata into its group's (what `xarray.open_zarr` reads
    first, and what marks a made store). Zarr warns that format 3 does not specify it yet;
    zarr-python and xarray read it."""
    import zarr

    with warnings.catch_warnings():
        warnings.filterwarnings(
            "ignore", message="Consolidated metadata is currently not", category=UserWarning
        )
        zarr.consolidate_metadata(g.store)


def _check_resumable(loc: _Location, sc: Scenario, n: int, seed: int, lanes: int | None) -> int:
    """Refuse a store this run cannot continue; the lanes to continue it with: the store's,
    which `lanes` must equal when given."""
    attrs = loc.group("r").attrs
    lanes = attrs.get("lanes") if lanes is None else lanes
    want = {
        "trajectories": sc.trajectories,
        "dtype": sc.dtype,
        "n_trajectories": n,
        "seed": seed,
        "lanes": lanes,
        "scenario": sc.source,
    }
    for k, v in want.items():
        have = attrs.get(k)
        if k == "scenario":  # compared as data (the order of its keys does not matter)
            same, v = json.loads(have or "null") == v, json.dumps(v)
        else:
            same = have == v
        if not same:
            raise ValueError(
                f"cannot resume {loc.url}: its {k} is {have!r}, this run's is "
                f"{v!r}; use a new --out or drop --resume."
            )
    return lanes


def _prepare_store(
    loc: _Location,
    sc: Scenario,
    n: int,
    seed: int,
    resume: bool,
    overwrite: bool,
    layout: Callable[[], tuple[int, int]],
    lanes: int | None,
) -> int:
    """Check a store to resume, or make a new one with the `(chunk, lanes)` of `layout()`;
    the lanes the run solves with. An existing store is replaced only when asked. A local
    store is built beside its path and renamed into place, so a store at the path is always
    initialised (every status −1) and a kill at any moment leaves something `resume` can
    finish; at a URL it is built in place, its consolidated metadata last (a kill before
    that leaves no store `resume` would take)."""
    if resume and overwrite:
        raise ValueError("give at most one of `resume` and `overwrite`.")
    if resume and not loc.is_store():
        raise FileNotFoundError(
            f"there is no sweep store at {loc.url} to resume: drop "
            "--resume (resume=False) to start one."
        )
    if loc.is_store():
        if resume:
            return _check_resumable(loc, sc, n, seed, lanes)
        if not overwrite:
            raise FileExistsError(
                f"{loc.url} already holds a sweep store: pass --overwrite (overwrite=True) "
                f"to replace it and its plots, or --resume (resume=True) to finish it."
            )
    elif not loc.is_empty():
        raise ValueError(f"{loc.url} exists and is not a sweep store; choose another --out.")
    chunk, lanes = layout()
    if loc.is_url:
        loc.remove()
        _create_store(loc, sc, n, chunk, seed, lanes)
        return lanes
    path = pathlib.Path(loc.url).resolve()  # a link to a store: the store it names
    tmp = path.with_name(path.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        _create_store(_Location.of(tmp), sc, n, chunk, seed, lanes)
    except BaseException:  # a full disk, an interrupt: nothing left behind
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if overwrite:
        shutil.rmtree(plots_dir(path), ignore_errors=True)
    shutil.rmtree(path, ignore_errors=True)
    os.replace(tmp, path)
    return lanes


def _write(g, idx: np.ndarray, out: dict[str, np.ndarray], every: int | None) -> None:
    """Write the solved trajectories `idx` (ascending) into the store, one write per
    contiguous run of rows (a partly finished chunk has several); `status` last, which
    marks them done. With `every` = K, the states are those of the multiples of K in `idx`,
    at rows i / K."""
    for name in [*(k for k in out if k != "status"), "status"]:
        rows = idx[idx % every == 0] // every if every and name in _STATES else idx
        if not rows.size:
            continue
        for r in np.split(np.arange(rows.size), np.nonzero(np.diff(rows) != 1)[0] + 1):
            _filled(g, name)[int(rows[r[0]]) : int(rows[r[-1]]) + 1] = out[name][r[0] : r[-1] + 1]
