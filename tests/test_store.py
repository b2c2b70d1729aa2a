"""A sweep store that knows when it is damaged: fault injection on real stores.

Each fault (a deleted `status` chunk, a deleted data chunk, a flipped byte, a truncated
chunk, a lost coordinate) is made in a copy of a finished store; `sweep.verify` must name
the chunk and the trajectories it holds, the readers must refuse the store, and
`run(..., resume=True)` must leave it bitwise equal to the uninterrupted run. Equality is
bitwise because a resumed trajectory is solved by the same compiled block program from the
same drawn values (`rbdyn_jax.sweep`'s docstring), whichever other trajectories share its block.
"""

import os
import shutil

import numpy as np
import pytest
import zarr
from helpers import assert_same_arrays as assert_same, load_store as load, small_scenario as small

from rbdyn_jax import sweep
from rbdyn_jax.scenario import Scenario

N, CHUNK, LANES, SEED = 20, 8, 16, 3  # chunks of trajectories 0..7, 8..15, 16..19


def _run(out, **kw):
    return sweep.run(Scenario.from_dict(small()), N, out, chunk=CHUNK, seed=SEED, lanes=LANES, **kw)


# The tests reading the reference store share one worker (`--dist loadgroup`): it is
# solved once.
SHARES_THE_REFERENCE = pytest.mark.xdist_group("store_reference")


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    return _run(tmp_path_factory.mktemp("store") / "ref.zarr")


@pytest.fixture
def copy(reference, tmp_path):
    out = tmp_path / "copy.zarr"
    shutil.copytree(reference, out)
    return out


def _chunk(store, name, i) -> str:
    """The file of chunk `i` (along the first dimension) of the store's array `name`."""
    a = zarr.open_group(str(store), mode="r")[name]
    return os.path.join(store, name, a.metadata.encode_chunk_key((i,) + (0,) * (a.ndim - 1)))


def _flip_byte(path):
    with open(path, "r+b") as f:
        data = bytearray(f.read())
        data[len(data) // 2] ^= 0x01
        f.seek(0)
        f.write(data)


def _truncate(path):
    with open(path, "r+b") as f:
        f.truncate(os.path.getsize(path) // 2)


def _all(store) -> dict:
    """Every array of the store, coordinates included."""
    g = zarr.open_group(str(store), mode="r")
    return load(store, tuple(g.array_keys()))


FAULTS = {
    # name: (variable, chunk, what is done to it, trajectories it holds)
    "status deleted": ("status", 1, os.remove, range(8, 16)),
    "data deleted": ("omega", 2, os.remove, range(16, 20)),
    "byte flipped": ("quat", 0, _flip_byte, range(0, 8)),
    "truncated": ("energy_drift", 1, _truncate, range(8, 16)),
    "status byte flipped": ("status", 0, _flip_byte, range(0, 8)),
    "coordinate deleted": ("time", 0, os.remove, range(0)),
}


@pytest.mark.parametrize("fault", FAULTS)
@SHARES_THE_REFERENCE
def test_each_fault_is_found_and_resume_restores_the_bits(reference, copy, fault):
    name, i, damage, held = FAULTS[fault]
    assert sweep.verify(copy).complete
    damage(_chunk(copy, name, i))
    found = sweep.verify(copy)
    assert not found.whole and not found.complete
    (d,) = (*found.missing, *found.damaged)
    assert (d.variable, d.chunk, d.trajectories) == (name, i, held)
    assert d.problem == ("missing" if damage is os.remove else "damaged")
    assert np.array_equal(found.trajectories, np.asarray(held))
    assert f"{name} chunk {i}" in str(found)
    solved = []
    _run(copy, resume=True, progress=lambda p: solved.append(p.solved_now))
    assert sum(solved) == len(held)  # exactly the trajectories the chunk held
    assert sweep.verify(copy).complete
    assert_same(_all(copy), _all(reference))
    assert zarr.open_group(str(copy), mode="r").attrs["complete"]


def test_readers_refuse_a_damaged_store(copy, tmp_path):
    """A missing chunk is refused before anything is read; a changed byte when its chunk is
    read (its checksum fails). The message names `rbdyn verify` and `--resume`."""
    os.remove(_chunk(copy, "omega", 1))
    for read in (sweep.summarize, lambda s: sweep.to_netcdf(s, tmp_path / "x.nc"), sweep.check):
        with pytest.raises(sweep.StoreDamagedError, match=r"rbdyn verify .*--resume"):
            read(copy)
    assert not (tmp_path / "x.nc").exists()
    _run(copy, resume=True)
    _flip_byte(_chunk(copy, "max_abs_omega", 0))
    sweep.check(copy)  # lists the chunks and reads `status` only
    with pytest.raises(sweep.StoreDamagedError, match="max_abs_omega chunk 0: damaged"):
        sweep.summarize(copy)


def test_a_store_partly_solved_reads_as_not_solved_and_warns(tmp_path):
    """Where nothing is written the store reads as not solved (status −1, data NaN); an
    interrupted store is whole but incomplete, and the readers warn about it."""
    out = _run(tmp_path / "s.zarr")
    g = zarr.open_group(str(out), mode="r+")
    for name in g.array_keys():  # forget the last chunk, as a run killed before it
        if g[name].metadata.dimension_names[0] == "trajectory" and name != "trajectory":
            os.remove(_chunk(out, name, 2))
    assert np.all(zarr.open_group(str(out), mode="r")["status"][16:] == -1)
    assert np.all(np.isnan(zarr.open_group(str(out), mode="r")["omega"][16:]))
    # The status chunk is gone too: its trajectories count as missing (and as not run).
    found = sweep.verify(out)
    assert [d.variable for d in found.missing] == ["status"]
    _filled = zarr.open_group(str(out), mode="r+")["status"].with_config(
        {"write_empty_chunks": True}
    )
    _filled[16:] = -1  # as a store made and not yet solved there
    found = sweep.verify(out)
    assert found.whole and not found.complete and found.not_run == 4
    assert "incomplete: 4 of 20" in str(found)
    with pytest.warns(sweep.IncompleteStoreWarning, match="4 of 20 trajectories not solved"):
        stats = sweep.summarize(out)
    assert stats["status"] == {"not_run": 4, "successful": 16}


def test_every_chunk_is_written_even_when_it_holds_only_fill_values(tmp_path):
    """A chunk of trajectories that all failed (NaN data) is still in the store, so that a
    missing chunk means a lost one."""
    d = small(solver={"rtol": 1e-9, "atol": 1e-9, "max_steps": 2})  # every solve fails
    out = sweep.run(Scenario.from_dict(d), 8, tmp_path / "f.zarr", chunk=4, lanes=LANES)
    g = zarr.open_group(str(out), mode="r")
    assert np.all(g["status"][:] > 0) and np.all(np.isnan(g["omega"][:]))
    for name in ("omega", "quat", "energy_drift", "status"):
        assert all(os.path.isfile(_chunk(out, name, i)) for i in range(2)), name
    assert sweep.verify(out).complete


def test_states_of_every_kth_trajectory(tmp_path):
    """A store keeping every K-th trajectory's states: a lost chunk of them holds
    trajectories 0, K, 2K, …; resume solves those and restores the bits."""
    kw = dict(chunk=CHUNK, seed=SEED, lanes=LANES, trajectories=4)
    ref = sweep.run(Scenario.from_dict(small()), N, tmp_path / "ref.zarr", **kw)
    out = tmp_path / "k.zarr"
    shutil.copytree(ref, out)
    os.remove(_chunk(out, "quat", 1))  # sampled rows 2, 3: trajectories 8 and 12
    (d,) = sweep.verify(out).missing
    assert d.trajectories == range(8, 13, 4)
    assert "trajectories 8..12 every 4" in str(d)
    sweep.run(Scenario.from_dict(small()), N, out, resume=True, **kw)
    assert_same(_all(out), _all(ref))


def test_resume_needs_a_store(tmp_path):
    with pytest.raises(FileNotFoundError, match="no sweep store .* drop --resume"):
        _run(tmp_path / "none.zarr", resume=True)
    assert not (tmp_path / "none.zarr").exists()
    with pytest.raises(ValueError, match="not a sweep store"):
        sweep.verify(tmp_path)


def test_a_store_creation_that_fails_leaves_nothing_and_keeps_the_old_store(
    reference, copy, monkeypatch
):
    """A creation that fails midway (here a full disk at the third array) removes what it
    had made, and a store it was to replace (`overwrite=True`) is still whole."""
    from rbdyn_jax.sweep import _store

    made, create = [], _store._create_array

    def full_disk(*args, **kw):
        made.append(args[1])
        if len(made) == 3:
            raise OSError(28, "No space left on device")
        return create(*args, **kw)

    monkeypatch.setattr(_store, "_create_array", full_disk)
    for out, kw in ((copy.with_name("new.zarr"), {}), (copy, {"overwrite": True})):
        made.clear()
        with pytest.raises(OSError, match="No space left"):
            _run(out, **kw)
        assert len(made) == 3
        assert sorted(p.name for p in out.parent.iterdir()) == ["copy.zarr"]
    assert sweep.verify(copy).complete
    assert_same(_all(copy), _all(reference))


def test_overwrite_through_a_link_replaces_the_store_it_names(copy):
    """`out` a symbolic link to a store: `overwrite=True` replaces that store, and the link
    stays (the new store could not take the link's place: 'Not a directory')."""
    link = copy.with_name("link.zarr")
    link.symlink_to(copy)
    _run(link, overwrite=True)
    assert link.is_symlink() and sweep.verify(link).complete
    assert sorted(p.name for p in copy.parent.iterdir()) == ["copy.zarr", "link.zarr"]


@SHARES_THE_REFERENCE
def test_store_metadata_say_what_is_not_solved(reference):
    """The fill values are what a reader of the store sees where nothing was written."""
    g = zarr.open_group(str(reference), mode="r")
    assert g["status"].fill_value == -1 and g["num_steps"].fill_value == -1
    assert np.isnan(g["omega"].fill_value) and np.isnan(g["energy_drift"].fill_value)
    assert "crc32c" in [c.to_dict()["name"] for c in g["omega"].metadata.codecs]
    assert g["omega"].metadata.dimension_names == ("trajectory", "time", "axis")
