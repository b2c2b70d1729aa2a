"""Verifying and repairing a store: missing and damaged chunks, the readers' refusals, and the
trajectories `resume` solves again.
"""

from __future__ import annotations

import contextlib
import dataclasses
import pathlib
import warnings

import numpy as np

from ..scenario import Scenario
from ._store import _NOT_RUN, _consolidate, _filled, _Location, _write_coordinates


@dataclasses.dataclass(frozen=True)
class Damage:
    """A chunk of a store's `variable` that is `"missing"` (not in the store though it was
    written) or `"damaged"` (its bytes fail their checksum or do not decode; `error` says
    how): the `chunk`-th along the variable's first dimension, holding the results of
    `trajectories` (empty for the time and label coordinates)."""

    variable: str
    chunk: int
    problem: str
    trajectories: range
    error: str = ""

    def __str__(self) -> str:
        t = self.trajectories
        held = (
            f"trajectories {t.start}..{t[-1]}" + (f" every {t.step}" if t.step > 1 else "")
            if len(t)
            else "no trajectory's results"
        )
        return f"{self.variable} chunk {self.chunk}: {self.problem} ({held})" + (
            f": {self.error}" if self.error else ""
        )


@dataclasses.dataclass(frozen=True)
class Verification:
    """What `verify` found in a store: its `missing` and `damaged` chunks (`Damage`), how
    many of its `n` trajectories are not solved yet (`not_run`, counting those whose
    status chunk is missing or damaged), and whether its metadata say it `complete`."""

    store: str
    n: int
    missing: tuple[Damage, ...]
    damaged: tuple[Damage, ...]
    not_run: int

    @property
    def whole(self) -> bool:
        """No chunk missing or damaged (trajectories may remain to be solved)."""
        return not self.missing and not self.damaged

    @property
    def complete(self) -> bool:
        """Whole, and every trajectory solved."""
        return self.whole and self.not_run == 0

    @property
    def trajectories(self) -> np.ndarray:
        """The indices of the trajectories whose results a missing or damaged chunk held,
        ascending: those `run(..., resume=True)` solves again."""
        held = [np.asarray(d.trajectories) for d in (*self.missing, *self.damaged)]
        return np.unique(np.concatenate([np.zeros(0, np.int64), *held]).astype(np.int64))

    def __str__(self) -> str:
        lines = [f"{self.store}: {self.n} trajectories"]
        for d in (*self.missing, *self.damaged):
            lines.append(f"  {d}")
        if not self.whole:
            lines.append(
                f"damaged: {len(self.missing)} missing and {len(self.damaged)} "
                f"damaged chunk(s), holding the results of "
                f"{self.trajectories.size} trajectories; `rbdyn sweep ... --resume` "
                "(run(..., resume=True)) solves those again and rewrites the "
                "chunks"
            )
        elif self.not_run:
            lines.append(
                f"whole, incomplete: {self.not_run} of {self.n} trajectories not "
                "solved yet; finish with `rbdyn sweep ... --resume`"
            )
        else:
            lines.append("whole and complete: every chunk present and intact")
        return "\n".join(lines)


class StoreDamagedError(ValueError):
    """A sweep store has missing or damaged chunks (`verify` lists them)."""


def _held(a, name: str, chunk: int, n: int, every: int | None) -> range:
    """The trajectories whose results chunk `chunk` of the store's array `a` holds."""
    rows = a.chunks[0]
    start, stop = chunk * rows, min((chunk + 1) * rows, a.shape[0])
    dim = a.metadata.dimension_names[0]
    if dim == "trajectory" and name != "trajectory":
        return range(start, stop)
    if dim == "sampled_trajectory" and name != "sampled_trajectory":
        return range(start * every, min((stop - 1) * every + 1, n), every)
    return range(0)


def _inspect(loc: _Location, g, read: bool = True) -> Verification:
    """`verify`'s findings for the store `g` at `loc`; with `read=False` only whether each
    chunk is there (a listing and `status`), without reading the others."""
    fs, root = loc.fs()
    prefix = root.rstrip("/") + "/"
    present = {f[len(prefix) :] if f.startswith(prefix) else f for f in fs.find(root)}
    status_array = g["status"]
    n, every = status_array.shape[0], g.attrs.get("trajectories")
    every = every if isinstance(every, int) else None
    status = np.full(n, _NOT_RUN, np.int64)  # not solved where unknown
    missing, damaged = [], []
    names = ["status", *sorted(k for k in g.array_keys() if k != "status")]
    for name in names:
        a = g[name]
        if f"{name}/zarr.json" not in present:
            missing.append(Damage(name, -1, "missing metadata", range(0)))
            continue
        rows = a.chunks[0]
        for i in range(-(-a.shape[0] // rows)):
            held = _held(a, name, i, n, every)
            key = f"{name}/{a.metadata.encode_chunk_key((i,) + (0,) * (a.ndim - 1))}"
            per_trajectory = len(held) > 0
            if key not in present:
                # Data are written only where solved: missing where a trajectory it holds
                # is marked solved. Status and coordinates are written when a store is made.
                if not per_trajectory or name == "status" or np.any(status[held] >= 0):
                    missing.append(Damage(name, i, "missing", held))
                continue
            if read or name == "status":
                try:
                    block = a.blocks[i]
                except Exception as e:  # a failed checksum, a truncated or garbled chunk
                    damaged.append(Damage(name, i, "damaged", held, f"{type(e).__name__}: {e}"))
                    continue
                if name == "status":
                    status[held] = block
    return Verification(loc.url, n, tuple(missing), tuple(damaged), int(np.sum(status < 0)))


def verify(store: str | pathlib.Path, *, storage_options: dict | None = None) -> Verification:
    """Check every chunk of the sweep store `store` (a path or a URL): that it is there and
    that its bytes pass their checksum (CRC32C) and decode.

    A store's `status` chunks and coordinates are written when it is made; a data
    variable's chunk is written when the trajectories it holds are solved, so it is
    missing when one of them is marked solved and the chunk is not there. Reads the whole
    store once.

    **Returns:** a `Verification`: its `missing` and `damaged` chunks with the
    trajectories each holds, `not_run`, and `whole` / `complete`. `run(..., resume=True)`
    solves again exactly `Verification.trajectories` and those not run, after which the
    store is bitwise equal to an uninterrupted run's.

    **Raises:** `ValueError` if `store` is not a sweep store.
    """
    loc = _Location.of(store, storage_options)
    if not loc.is_store():
        raise ValueError(f"{store} is not a sweep store.")
    return _inspect(loc, loc.group("r"))


def _refuse_damaged(found: Verification) -> None:
    """Raise `StoreDamagedError` for a store that is not whole."""
    if not found.whole:
        raise StoreDamagedError(
            f"{found.store} is damaged: {len(found.missing)} missing and {len(found.damaged)} "
            f"damaged chunk(s), holding the results of {found.trajectories.size} "
            f"trajectories (first: {(*found.missing, *found.damaged)[0]}). List them with "
            f"`rbdyn verify {found.store}`; `rbdyn sweep ... --resume` repairs the store."
        )


def _warn_incomplete(found: Verification) -> None:
    if found.not_run:
        warnings.warn(
            f"{found.store} is incomplete: {found.not_run} of {found.n} trajectories "
            "not solved yet (NaN, status -1); finish with `rbdyn sweep ... "
            "--resume`.",
            IncompleteStoreWarning,
            stacklevel=3,
        )


class IncompleteStoreWarning(UserWarning):
    """A sweep store read before all its trajectories were solved."""


def check(store: str | pathlib.Path, *, storage_options: dict | None = None) -> Verification:
    """Refuse a sweep store with missing chunks or damaged `status` chunks
    (`StoreDamagedError`, naming `rbdyn verify` and `--resume`) and warn
    (`IncompleteStoreWarning`) when trajectories remain to be solved; what `summarize`,
    `to_netcdf` and `rbdyn plot` do before reading. Lists the store and reads `status`
    only: a changed byte elsewhere is found when its chunk is read (its checksum fails),
    and by `verify`."""
    loc = _Location.of(store, storage_options)
    if not loc.is_store():
        raise ValueError(f"{store} is not a sweep store.")
    found = _inspect(loc, loc.group("r"), read=False)
    _refuse_damaged(found)
    _warn_incomplete(found)
    return found


@contextlib.contextmanager
def reading(store: str | pathlib.Path, storage_options: dict | None = None):
    """A context in which an error reading the sweep store `store` becomes a
    `StoreDamagedError` naming the damage, where `verify` finds the store damaged (a chunk
    whose checksum fails, say); any other error is raised as it is."""
    try:
        yield
    except Exception as e:
        try:
            found = verify(store, storage_options=storage_options)
        except Exception:
            raise e from None
        if found.whole:
            raise
        try:
            _refuse_damaged(found)
        except StoreDamagedError as damaged:
            raise damaged from e


def _repair(loc: _Location, g, sc: Scenario) -> Verification:
    """Make a store `resume` can finish: delete its damaged chunks (they then read as not
    solved: NaN, status −1), mark the trajectories of every missing or damaged chunk not
    run, and rewrite a damaged coordinate. The store is marked incomplete first, so a kill
    at any moment leaves a store `verify` and `resume` take again."""
    found = _inspect(loc, g)
    if found.whole:
        return found
    if any(d.chunk < 0 for d in found.missing):
        names = ", ".join(d.variable for d in found.missing if d.chunk < 0)
        raise StoreDamagedError(
            f"cannot resume {loc.url}: the metadata of {names} are "
            "missing; run the sweep again with --overwrite."
        )
    g.attrs["complete"] = 0
    _consolidate(g)
    fs, root = loc.fs()
    for d in found.damaged:
        a = g[d.variable]
        fs.rm(
            f"{root}/{d.variable}/{a.metadata.encode_chunk_key((d.chunk,) + (0,) * (a.ndim - 1))}"
        )
    if any(
        not len(d.trajectories) or d.variable in ("trajectory", "sampled_trajectory")
        for d in (*found.missing, *found.damaged)
    ):
        _write_coordinates(g, sc)
    idx = found.trajectories
    if idx.size:
        _filled(g, "status").oindex[idx] = _NOT_RUN
    return found
