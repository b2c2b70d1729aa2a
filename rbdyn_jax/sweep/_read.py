"""Reading a store: the dataset, summaries through xarray/Dask, netCDF export."""

from __future__ import annotations

import os
import pathlib
import warnings

import numpy as np

from ._store import _Location
from ._verify import check, reading


def open_dataset(store: str | pathlib.Path, *, storage_options: dict | None = None, **kwargs):
    """The sweep store at `store` (a path or a URL) as an `xarray.Dataset` (lazy: Dask
    arrays, nothing is loaded); `kwargs` go to `xarray.open_zarr` (e.g. `chunks`)."""
    import xarray as xr

    loc = _Location.of(store, storage_options)
    return xr.open_zarr(loc.url, storage_options=loc.options or None, **kwargs)


_EXACT_ROWS = 1 << 25  # quantiles exact (in memory, 8 bytes a row) up to this many values


def quantile_key(q: float) -> str:
    """The key of quantile `q` in `summarize`'s rows: its percentile, `q05` for 0.05,
    `q100` for 1, and as many decimals as it has otherwise (`q0.1`, `q99.51`)."""
    p = round(100 * float(q), 10)
    return f"q{round(p):02d}" if p == round(p) else f"q{p:g}"


def summarize(
    store: str | pathlib.Path,
    quantiles=(0.05, 0.5, 0.95),
    *,
    rows: int = 1 << 20,
    storage_options: dict | None = None,
) -> dict:
    """Counts per status and, for every summary, count/mean/std/min/quantiles/max over the
    successful trajectories (finite values).

    The store (a path or a URL) is read through `xarray.open_zarr` and Dask, `rows` trajectories at
    a time (rounded to whole store chunks), reading only the `(trajectory,)` columns: a store of any
    size is summarised without loading it whole, on the active Dask scheduler (a
    `distributed.Client` if one is set up). Quantiles are exact while a summary has at most 2²⁵
    successful values (they are then gathered, 8 bytes each); beyond, they are Dask's approximation
    merged from per-block quantiles (`dask.array.percentile`).

    **Returns:** `{"n", "status": {name: count}, "summaries": {name: {count, mean, std,
    min, qNN…, max}}, "scenario", "complete"}`, each quantile under its percentile
    (`q05` for 0.05; `q0.1` for 0.001).
    """
    qs = np.atleast_1d(np.asarray(quantiles, float))
    if qs.ndim != 1 or not np.all((qs >= 0) & (qs <= 1)):
        raise ValueError(f"`quantiles` must be numbers in [0, 1], got {quantiles!r}.")
    keys = [quantile_key(q) for q in qs]
    if len(set(keys)) != len(keys):
        raise ValueError(f"`quantiles` must be distinct percentiles, got {quantiles!r}.")
    found = check(store, storage_options=storage_options)
    with reading(store, storage_options):
        stats = _summarize(store, quantiles, rows, storage_options)
    return {**stats, "complete": stats["complete"] and found.complete}


def _summarize(store, quantiles, rows, storage_options) -> dict:
    import dask
    import dask.array as da

    ds = open_dataset(store, storage_options=storage_options, chunks={})
    stored = ds.status.chunks[0][0]
    ds = ds.chunk({"trajectory": stored * max(1, rows // stored)})
    status = ds.status.data
    meanings = dict(zip(ds.status.attrs["flag_values"], ds.status.attrs["flag_meanings"].split()))
    names = ds.attrs["summaries"].split()
    ok = status == 0
    lazy = {"status": [da.sum(status == c) for c in meanings]}
    good = {}
    for name in names:
        x = ds[name].data
        good[name] = ok & da.isfinite(x)
        xs = da.where(good[name], x, np.nan)
        lazy[name] = [
            da.sum(good[name]),
            da.nanmean(xs),
            da.nanstd(xs, ddof=1),
            da.nanmin(xs),
            da.nanmax(xs),
        ]
    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns: handled below
        (computed,) = dask.compute(lazy)
    counts = {meanings[c]: int(k) for c, k in zip(meanings, computed["status"]) if k}
    stats = {}
    for name in names:
        count, mean, std, lo, hi = computed[name]
        row = {"count": int(count)}
        if count:
            x = ds[name].data[good[name]]
            if count <= _EXACT_ROWS:
                qs = np.quantile(x.compute(), quantiles)
            else:
                qs = da.percentile(x.compute_chunk_sizes(), 100 * np.asarray(quantiles)).compute()
            row.update(
                mean=float(mean), std=float(std) if count > 1 else 0.0, min=float(lo), max=float(hi)
            )
            row.update({quantile_key(q): float(v) for q, v in zip(quantiles, qs)})
        stats[name] = row
    return {
        "n": int(status.size),
        "status": counts,
        "summaries": stats,
        "scenario": ds.attrs["scenario_name"],
        "complete": bool(ds.attrs["complete"]),
    }


def to_netcdf(
    store: str | pathlib.Path,
    path: str | pathlib.Path,
    *,
    overwrite: bool = False,
    storage_options: dict | None = None,
) -> pathlib.Path:
    """Write the sweep `store` (a path or a URL) to the local netCDF-4 file `path` (engine netCDF4,
    zlib-compressed), streamed chunk by chunk through Dask; `xarray.open_dataset(path)` reads it
    back equal to `open_dataset(store)`, attributes included.

    The file is written beside `path` and renamed into place, so a failed export leaves no
    broken file. An existing `path` is refused unless `overwrite`.

    **Returns:** `path`. **Raises:** `FileExistsError` if `path` exists and not
    `overwrite`; `ValueError` if `store` is not a sweep store.
    """
    path = pathlib.Path(path)
    check(store, storage_options=storage_options)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists: pass --overwrite (overwrite=True) to replace it.")
    ds = open_dataset(store, storage_options=storage_options, chunks={})
    for v in ds.variables.values():
        keep = {k: v.encoding[k] for k in ("dtype", "_FillValue") if k in v.encoding}
        if v.dtype.kind in "fiu" and v.ndim:
            keep.update(zlib=True, complevel=4)
        v.encoding = keep
    # CF: flag_values has the type of its variable.
    status = ds.variables["status"]
    status.attrs["flag_values"] = np.asarray(status.attrs["flag_values"], status.dtype)
    tmp = path.with_name(path.name + ".partial")
    try:
        with reading(store, storage_options):
            ds.to_netcdf(tmp, engine="netcdf4", format="NETCDF4")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path
