"""Monte Carlo sweeps (rbdyn_jax.sweep): determinism, streaming, resume, isolation.

The solves are checked against `simulate` run directly on the stored samples, and the
shipped scenarios against their first integrals. The scenarios themselves (schema,
samplers, summaries) are tested in test_scenario.py.
"""

import gc
import os
import signal
import subprocess
import sys
import time

import jax.numpy as jnp
import numpy as np
import pytest
import xarray as xr
import zarr
from helpers import assert_same_arrays as assert_same, load_store as load, small_scenario as small

import rbdyn_jax as rb
from rbdyn_jax import sweep
from rbdyn_jax.scenario import SUMMARIES, Scenario, ScenarioError

# --------------------------------------------------------------------------------------
# Running: determinism, dataset, isolation, resume
# --------------------------------------------------------------------------------------

N = 14


# 16 lanes in the bitwise comparisons: at 8, with XLA's while loops compiled whole (the
# import's setting), a trajectory's last bits can depend on its lane within the block
# (the docstring of `rbdyn_jax.sweep`).
# The tests reading a module fixture's store share a worker (`--dist loadgroup`): each
# store is solved once, and the chunk programs compiled for it are reused.
ON_THE_REFERENCE = pytest.mark.xdist_group("sweep_reference_run")
ON_THE_FAILING_RUN = pytest.mark.xdist_group("sweep_failing_run")


@pytest.fixture(scope="module")
def reference_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("sweep") / "ref.zarr"
    sweep.run(Scenario.from_dict(small()), N, out, chunk=N, seed=3, lanes=16)
    return out


@pytest.mark.parametrize("chunk", [1, 7])
@ON_THE_REFERENCE
def test_same_seed_same_bits_for_any_chunk(reference_run, tmp_path, chunk):
    out = sweep.run(
        Scenario.from_dict(small()), N, tmp_path / "s.zarr", chunk=chunk, seed=3, lanes=16
    )
    assert_same(load(reference_run), load(out))
    other = sweep.run(
        Scenario.from_dict(small()), N, tmp_path / "o.zarr", chunk=chunk, seed=4, lanes=16
    )
    assert not np.array_equal(load(other)["omega"], load(out)["omega"])


@ON_THE_REFERENCE
def test_numpy_integers_are_taken_as_ints(reference_run, tmp_path):
    """`n`, `chunk`, `seed`, `lanes` and `trajectories` as NumPy integers (a value read from
    an array, say): the same store as with Python ints, its attributes plain ints."""
    out = sweep.run(
        Scenario.from_dict(small()),
        np.int64(N),
        tmp_path / "np.zarr",
        chunk=np.int32(N),
        seed=np.int64(3),
        lanes=np.int64(16),
        trajectories=np.int64(1),
    )
    assert_same(load(reference_run), load(out))
    attrs = xr.open_zarr(out).attrs
    assert (attrs["n_trajectories"], attrs["seed"], attrs["trajectories"]) == (N, 3, 1)


@ON_THE_REFERENCE
def test_two_devices_give_the_same_bits(reference_run, tmp_path):
    """A fresh process with two XLA host devices, each taking half of every chunk."""
    code = (
        "import jax; jax.config.update('jax_enable_x64', True)\n"
        "assert len(jax.devices()) == 2, jax.devices()\n"
        "from rbdyn_jax import sweep\n"
        "from rbdyn_jax.scenario import Scenario\n"
        f"sweep.run(Scenario.from_dict({small()!r}), {N}, {str(tmp_path / 'd2.zarr')!r},"
        " chunk=7, seed=3, lanes=16, devices=2)\n"
    )
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    subprocess.run([sys.executable, "-c", code], check=True, env=env, timeout=300)
    assert_same(load(reference_run), load(tmp_path / "d2.zarr"))


@ON_THE_REFERENCE
def test_dataset_opens_with_xarray_and_equals_simulate(reference_run):
    ds = xr.open_zarr(reference_run)
    assert ds.omega.dims == ("trajectory", "time", "axis")
    assert ds.quat.dims == ("trajectory", "time", "quat_component")
    assert ds.sizes == {
        "trajectory": N,
        "time": 9,
        "axis": 3,
        "quat_component": 4,
        "row": 3,
        "col": 3,
    }
    assert ds.attrs["seed"] == 3 and ds.attrs["complete"]
    assert ds.attrs["rbdyn_jax_version"] == rb.__version__
    assert "[w, x, y, z]" in ds.attrs["rbdyn_jax_conventions"]
    assert Scenario.from_dict(__import__("json").loads(ds.attrs["scenario"])).name == "small"
    assert np.all(ds.status.values == 0)
    ts = ds.time.values
    assert np.allclose(ts, np.linspace(0, 4, 9))
    for i in range(N):
        body = rb.RigidBody(jnp.asarray(ds.inertia.values[i]))
        y0 = rb.State(
            omega=jnp.asarray(ds.omega.values[i, 0]), quat=jnp.asarray(ds.quat.values[i, 0])
        )
        traj = rb.simulate(body, y0, jnp.asarray(ts), rtol=1e-9, atol=1e-9)
        # the same solver and tolerances, another compiled program: agreement to a few
        # rounding-amplified steps of rtol 1e-9, far below the solution's own error
        np.testing.assert_allclose(ds.omega.values[i], traj.ys.omega, rtol=0, atol=1e-10)
        np.testing.assert_allclose(ds.quat.values[i], traj.ys.quat, rtol=0, atol=1e-10)
        E = np.asarray(rb.invariants.energy(body, traj))
        assert ds.energy_drift.values[i] == pytest.approx(
            np.max(np.abs(E - E[0])) / E[0], rel=1e-3, abs=1e-15
        )
        assert ds.max_abs_omega.values[i] == pytest.approx(
            np.linalg.norm(traj.ys.omega, axis=-1).max(), rel=1e-10
        )
        assert ds.num_steps.values[i] > 0
    stats = sweep.summarize(reference_run)
    assert stats["status"] == {"successful": N}
    e = ds.energy_drift.values
    assert stats["summaries"]["energy_drift"]["mean"] == pytest.approx(e.mean(), rel=1e-12)
    assert stats["summaries"]["energy_drift"]["q50"] == pytest.approx(np.median(e), rel=1e-12)


def test_nan_and_max_steps_are_isolated(tmp_path):
    """Lognormal rates with a huge spread: some overflow to inf (non-finite state), some are
    so fast the solver runs out of steps; the others equal `simulate` run directly."""
    d = small(
        initial={
            "omega": {"dist": "lognormal", "median": [0.3, 1.0, 0.2], "sigma": [0.0, 300.0, 0.0]}
        }
    )
    d["solver"]["max_steps"] = 400
    out = sweep.run(Scenario.from_dict(d), 40, tmp_path / "f.zarr", chunk=16, seed=0, lanes=16)
    ds = xr.open_zarr(out)
    status = ds.status.values
    nonfinite, maxed = (
        int(rb.RESULTS.nonfinite_state._value),
        int(rb.RESULTS.max_steps_reached._value),
    )
    assert np.sum(status == nonfinite) >= 1 and np.sum(status == maxed) >= 1
    assert np.sum(status == 0) >= 10
    assert set(np.unique(status)) <= {0, nonfinite, maxed}
    bad = status != 0
    assert np.all(np.isnan(ds.omega.values[bad])) and np.all(np.isnan(ds.energy_drift.values[bad]))
    stats = sweep.summarize(out)
    assert stats["status"]["nonfinite_state"] == np.sum(status == nonfinite)
    assert stats["summaries"]["energy_drift"]["count"] == np.sum(status == 0)
    ts = jnp.asarray(ds.time.values)
    for i in np.nonzero(status == 0)[0]:
        body = rb.RigidBody(jnp.asarray(ds.inertia.values[i]))
        y0 = rb.State(jnp.asarray(ds.omega.values[i, 0]), jnp.asarray(ds.quat.values[i, 0]))
        traj = rb.simulate(body, y0, ts, rtol=1e-9, atol=1e-9, max_steps=400)
        scale = np.abs(ds.omega.values[i]).max()
        np.testing.assert_allclose(
            ds.omega.values[i], traj.ys.omega, rtol=0, atol=1e-9 * max(scale, 1.0)
        )


def test_resume_after_kill_equals_uninterrupted(tmp_path):
    """A real `rbdyn sweep` process is killed (SIGKILL) after some chunks are written; the
    run resumed in this process equals an uninterrupted one, nothing lost or duplicated."""
    scenario = tmp_path / "slow.toml"
    scenario.write_text(
        'name = "slow"\n[model]\nkind = "rigid_body"\n[model.inertia]\n'
        "principal = [1.0, 2.0, 2.5]\nlog_cholesky_sigma = 0.05\n"
        '[initial]\nomega = { dist = "normal", mean = [0.1, 1.0, 0.1], std = 0.3 }\n'
        "[time]\nt1 = 150.0\nn = 5\n[solver]\nrtol = 1e-8\natol = 1e-8\n"
        '[outputs]\nsummaries = ["energy_drift"]\n'
    )
    n, chunk = 64, 8
    out = tmp_path / "killed.zarr"
    cmd = [
        sys.executable,
        "-m",
        "rbdyn_jax.cli",
        "sweep",
        str(scenario),
        "--n",
        str(n),
        "--out",
        str(out),
        "--chunk",
        str(chunk),
        "--lanes",
        "16",
        "--seed",
        "5",
    ]
    env = dict(os.environ, RBDYN_JAX_CACHE_DIR="")  # no compilation cache: a cold start
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    done = 0
    deadline = time.time() + 240
    try:
        while time.time() < deadline and proc.poll() is None:
            time.sleep(0.02)
            try:
                done = int(np.sum(zarr.open_group(str(out), mode="r")["status"][:] >= 0))
            except Exception:  # store not created yet
                continue
            if done >= chunk:
                break
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait()
    status = zarr.open_group(str(out), mode="r")["status"][:]
    assert 0 < np.sum(status >= 0) < n, "the kill did not land mid-run"
    assert not zarr.open_group(str(out), mode="r").attrs["complete"]
    seen = []
    sweep.run(
        Scenario.from_toml(scenario),
        n,
        out,
        chunk=chunk,
        seed=5,
        lanes=16,
        resume=True,
        progress=lambda p: seen.append(p.solved_now),
    )
    assert sum(seen) == np.sum(status < 0)  # only the missing ones were solved
    assert np.all(zarr.open_group(str(out), mode="r")["status"][:] == 0)
    ref = sweep.run(
        Scenario.from_toml(scenario), n, tmp_path / "ref.zarr", chunk=chunk, seed=5, lanes=16
    )
    names = ("omega", "quat", "inertia", "status", "energy_drift")
    assert_same(load(out, names), load(ref, names))
    assert zarr.open_group(str(out), mode="r").attrs["complete"]


@ON_THE_REFERENCE
def test_resume_refuses_a_different_run(reference_run, tmp_path):
    with pytest.raises(ValueError, match="cannot resume"):
        sweep.run(
            Scenario.from_dict(small()), N, reference_run, chunk=N, seed=4, lanes=16, resume=True
        )
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "file").write_text("data")
    with pytest.raises(ValueError, match="not a sweep store"):
        sweep.run(Scenario.from_dict(small()), N, tmp_path / "x", chunk=N, lanes=16)


def test_run_argument_errors(tmp_path):
    sc = Scenario.from_dict(small())
    bad = (
        {"chunk": 0},
        {"lanes": -1},
        {"seed": -2},
        {"seed": 2**32},  # jax.random.key would keep its low 32 bits without 64-bit types
        {"devices": 99},
        {"devices": 1.5},
    )
    for kw in bad:
        with pytest.raises(ValueError, match=f"`{next(iter(kw))}`"):
            sweep.run(sc, 4, tmp_path / "e.zarr", **kw)
        assert not (tmp_path / "e.zarr").exists()  # refused before a store is made
    with pytest.raises(ScenarioError, match="no scenario file"):
        sweep.run("no_such_scenario", 4, tmp_path / "e.zarr")


# --------------------------------------------------------------------------------------
# Shipped scenarios: their first integrals hold across the sweep
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name, summary, bound",
    [
        ("rotating_platform", "relative_energy_drift", 1e-7),  # T_r integral, rtol 1e-9
        ("gg_axisymmetric", "energy_drift", 1e-7),  # T + V, rtol 1e-9
    ],
)
def test_shipped_scenario_first_integrals(tmp_path, name, summary, bound):
    out = sweep.run(name, 16, tmp_path / f"{name}.zarr", chunk=16, lanes=16)
    stats = sweep.summarize(out)
    assert stats["status"] == {"successful": 16}
    assert stats["summaries"][summary]["max"] < bound
    if name == "rotating_platform":  # |ω_r| between sqrt(2T_r/C) and sqrt(2T_r/A)
        # (Mukhametzyanov (2009), eq. (18))
        ds = xr.open_zarr(out)
        w = ds.omega.values
        J = ds.inertia.values
        Tr = 0.5 * np.einsum("ni,nij,nj->n", w[:, 0], J, w[:, 0])
        lam = np.linalg.eigvalsh(J)
        speed = np.linalg.norm(w, axis=-1)
        assert np.all(speed.min(1) >= np.sqrt(2 * Tr / lam[:, 2]) * (1 - 1e-7))
        assert np.all(speed.max(1) <= np.sqrt(2 * Tr / lam[:, 0]) * (1 + 1e-7))


@ON_THE_REFERENCE
def test_resume_fills_scattered_gaps(reference_run, tmp_path):
    """Unfinished trajectories scattered inside a chunk (as after a resume with another
    chunk size) are solved and written back in contiguous runs, equal to the full run."""
    import shutil

    out = tmp_path / "gaps.zarr"
    shutil.copytree(reference_run, out)
    g = zarr.open_group(str(out), mode="r+")
    gaps = [1, 2, 5, 9, 13]
    status = g["status"][:]
    status[gaps] = -1
    g["status"][:] = status
    omega = g["omega"][:]
    omega[gaps] = np.nan
    g["omega"][:] = omega
    seen = []
    sweep.run(
        Scenario.from_dict(small()),
        N,
        out,
        chunk=N,
        seed=3,
        lanes=16,
        resume=True,
        progress=lambda p: seen.append(p.solved_now),
    )
    assert seen == [len(gaps)]
    assert_same(load(reference_run), load(out))


# --------------------------------------------------------------------------------------
# The store: refused overwrites, CF metadata other tools read, netCDF export, summaries
# --------------------------------------------------------------------------------------


def snapshot(path) -> dict:
    """Every file under `path` with its bytes."""
    return {p.relative_to(path): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


@ON_THE_REFERENCE
def test_existing_store_is_refused_untouched_and_replaced_only_when_asked(reference_run, tmp_path):
    import shutil

    out = tmp_path / "x.zarr"
    shutil.copytree(reference_run, out)
    plots = sweep.plots_dir(out)
    plots.mkdir()
    (plots / "summaries.png").write_bytes(b"old plot")
    before = snapshot(out)
    other = Scenario.from_dict(small(name="other", time={"t1": 2.0, "n": 5}))
    with pytest.raises(FileExistsError, match="--overwrite") as e:
        sweep.run(other, 6, out, chunk=6, lanes=16)
    assert str(out) in str(e.value) and "--resume" in str(e.value)
    assert snapshot(out) == before and (plots / "summaries.png").exists()
    with pytest.raises(ValueError, match="at most one"):
        sweep.run(other, 6, out, chunk=6, lanes=16, overwrite=True, resume=True)
    assert snapshot(out) == before
    sweep.run(other, 6, out, chunk=6, lanes=16, overwrite=True)
    ds = xr.open_zarr(out)
    assert ds.attrs["scenario_name"] == "other" and ds.sizes["trajectory"] == 6
    assert ds.sizes["time"] == 5 and np.all(ds.status.values == 0)
    assert not plots.exists()  # the plots of the replaced store go with it


@ON_THE_REFERENCE
def test_store_carries_cf_metadata(reference_run):
    ds = xr.open_zarr(reference_run)
    for name, v in ds.variables.items():
        assert v.attrs.get("long_name") and v.attrs.get("description"), name
        if v.dtype.kind not in "UOT":  # the labels (strings) have no units
            assert "units" in v.attrs, name
    units = {
        k: ds[k].attrs["units"]
        for k in (
            "omega",
            "quat",
            "inertia",
            "time",
            "energy_drift",
            "max_abs_omega",
            "first_flip_time",
            "status",
            "num_steps",
        )
    }
    assert units == {
        "omega": "rad/s",
        "quat": "1",
        "inertia": "kg m2",
        "time": "s",
        "energy_drift": "1",
        "max_abs_omega": "rad/s",
        "first_flip_time": "s",
        "status": "1",
        "num_steps": "1",
    }
    assert list(ds.axis.values) == ["x", "y", "z"]
    assert list(ds.quat_component.values) == ["w", "x", "y", "z"]
    np.testing.assert_array_equal(ds.omega.sel(axis="y").values, ds.omega.values[..., 1])
    np.testing.assert_array_equal(ds.quat.sel(quat_component="w").values, ds.quat.values[..., 0])
    np.testing.assert_array_equal(
        ds.inertia.sel(row="x", col="y").values, ds.inertia.values[:, 0, 1]
    )
    flags = dict(zip(ds.status.attrs["flag_values"], ds.status.attrs["flag_meanings"].split()))
    assert flags == sweep.status_meanings()
    assert flags[-1] == "not_run" and flags[0] == "successful"
    assert flags[int(rb.RESULTS.max_steps_reached._value)] == "max_steps_reached"
    # netCDF attribute types only: strings, numbers, 1-D numeric lists
    for attrs in [ds.attrs, *(v.attrs for v in ds.variables.values())]:
        for k, a in attrs.items():
            ok = isinstance(a, str | int | float) and not isinstance(a, bool)
            ok |= isinstance(a, list) and all(isinstance(x, int | float) for x in a)
            assert ok, (k, a)


@ON_THE_REFERENCE
def test_netcdf_export_reads_back_equal(reference_run, tmp_path):
    nc = sweep.to_netcdf(reference_run, tmp_path / "s.nc")
    back = xr.open_dataset(nc, engine="netcdf4").load()
    xr.testing.assert_identical(back, xr.open_zarr(reference_run).load())
    assert back.status.attrs["flag_values"].dtype == np.int32  # CF: the variable's type
    with pytest.raises(FileExistsError, match="--overwrite"):
        sweep.to_netcdf(reference_run, nc)
    sweep.to_netcdf(reference_run, nc, overwrite=True)
    with pytest.raises(ValueError, match="not a sweep store"):
        sweep.to_netcdf(tmp_path, tmp_path / "t.nc")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.nc"]  # nothing half-written


@pytest.fixture(scope="module")
def failing_run(tmp_path_factory):
    """40 trajectories of which some fail (non-finite or out of steps), in chunks of 8."""
    d = small(
        initial={
            "omega": {"dist": "lognormal", "median": [0.3, 1.0, 0.2], "sigma": [0.0, 300.0, 0.0]}
        }
    )
    d["solver"]["max_steps"] = 400
    out = tmp_path_factory.mktemp("failing") / "f.zarr"
    return sweep.run(Scenario.from_dict(d), 40, out, chunk=8, seed=0, lanes=16)


@pytest.mark.parametrize("rows", [8, 1 << 20])  # five Dask blocks, and one
@ON_THE_FAILING_RUN
def test_summarize_through_dask_equals_numpy(failing_run, rows):
    g = zarr.open_group(str(failing_run), mode="r")
    status = g["status"][:]
    stats = sweep.summarize(failing_run, rows=rows)
    assert stats["n"] == 40 and stats["complete"] and stats["scenario"] == "small"
    names = sweep.status_meanings()
    assert stats["status"] == {
        names[c]: int(k) for c, k in zip(*np.unique(status, return_counts=True))
    }
    for name in ("energy_drift", "max_abs_omega", "first_flip_time"):
        x = g[name][:][status == 0]
        x = x[np.isfinite(x)]
        row = stats["summaries"][name]
        assert row["count"] == x.size > 1
        # sums in another order: equal to a few roundings
        assert row["mean"] == pytest.approx(x.mean(), rel=1e-13)
        assert row["std"] == pytest.approx(x.std(ddof=1), rel=1e-12)
        assert (row["min"], row["max"]) == (x.min(), x.max())
        assert [row["q05"], row["q50"], row["q95"]] == list(np.quantile(x, [0.05, 0.5, 0.95]))


@ON_THE_FAILING_RUN
def test_summarize_keys_every_quantile_asked_for(failing_run):
    """Each quantile under its own percentile key, fractional percents with their decimals;
    quantiles outside [0, 1] or sharing a key are refused."""
    g = zarr.open_group(str(failing_run), mode="r")
    x = g["max_abs_omega"][:][g["status"][:] == 0]
    qs = (0.001, 0.5, 0.9951, 1.0)
    row = sweep.summarize(failing_run, quantiles=qs)["summaries"]["max_abs_omega"]
    assert [row[k] for k in ("q0.1", "q50", "q99.51", "q100")] == list(np.quantile(x, qs))
    for bad in ((0.5, 1.5), (-0.1,), (0.5, 0.5)):
        with pytest.raises(ValueError, match="`quantiles`"):
            sweep.summarize(failing_run, quantiles=bad)


@ON_THE_FAILING_RUN
def test_summarize_approximates_quantiles_of_a_large_store(failing_run, monkeypatch):
    """Beyond the exact limit the quantiles are Dask's, merged from per-block ones: within
    the neighbouring order statistics of the exact ones."""
    monkeypatch.setattr(sweep._read, "_EXACT_ROWS", 0)
    g = zarr.open_group(str(failing_run), mode="r")
    status = g["status"][:]
    x = g["energy_drift"][:][status == 0]
    row = sweep.summarize(failing_run, rows=8)["summaries"]["energy_drift"]
    lo, hi = np.quantile(x, [0.35, 0.65])
    assert hi > lo * 1.01  # a spread the bound below can resolve
    # interpolation between the merged quantiles: a few roundings of slack
    assert lo * (1 - 1e-12) <= row["q50"] <= hi * (1 + 1e-12)
    assert row["mean"] == pytest.approx(x.mean(), rel=1e-13)


# --------------------------------------------------------------------------------------
# Stores keeping the states of every trajectory, of every K-th, or of none
# --------------------------------------------------------------------------------------

PER_TRAJECTORY = (
    "status",
    "num_steps",
    "inertia",
    "energy_drift",
    "max_abs_omega",
    "first_flip_time",
)


@pytest.mark.parametrize("keep", ["none", 3])
@ON_THE_REFERENCE
def test_stores_keeping_some_states_hold_the_full_stores_bits(reference_run, tmp_path, keep):
    """A store keeping no states, or every 3rd trajectory's, holds bitwise the per-trajectory
    variables of the full store of the same sweep, and its rows 0, 3, 6, … of the states;
    xarray opens it, `summarize` and `to_netcdf` read it."""
    out = sweep.run(
        Scenario.from_dict(small()),
        N,
        tmp_path / "k.zarr",
        chunk=7,
        seed=3,
        lanes=16,
        trajectories=keep,
    )
    ref, got = load(reference_run), load(out)
    assert_same({k: ref[k] for k in PER_TRAJECTORY}, {k: got[k] for k in PER_TRAJECTORY})
    ds = xr.open_zarr(out)
    assert ds.attrs["trajectories"] == keep and ds.attrs["dtype"] == "float64"
    if keep == "none":
        assert not {"omega", "quat", "axis", "quat_component"} & set(ds.variables)
    else:
        for k in ("omega", "quat"):
            assert np.array_equal(ref[k][::3], got[k], equal_nan=True), k
        assert ds.omega.dims == ("sampled_trajectory", "time", "axis")
        assert ds.quat.dims == ("sampled_trajectory", "time", "quat_component")
        assert list(ds.sampled_trajectory.values) == [0, 3, 6, 9, 12]
        coord = ds.sampled_trajectory.attrs
        assert coord["units"] == "1" and coord["long_name"] and "every K-th" in coord["description"]
        assert "one trajectory in 3: trajectories 0, 3, 6" in ds.omega.attrs["description"]
        # the chunk, rounded down to a multiple of K, holds whole zarr chunks of states
        assert ds.attrs["chunk"] == 6 and ds.omega.encoding["chunks"][0] == 2
        np.testing.assert_array_equal(  # selected by trajectory index
            ds.status.sel(trajectory=ds.sampled_trajectory).values, ref["status"][::3]
        )
    assert sweep.summarize(out) == sweep.summarize(reference_run)
    nc = sweep.to_netcdf(out, tmp_path / "k.nc")
    xr.testing.assert_identical(xr.open_dataset(nc, engine="netcdf4").load(), ds.load())


@ON_THE_REFERENCE
def test_resume_a_store_of_sampled_states(reference_run, tmp_path):
    """An interrupted store keeping every 3rd trajectory's states is finished by a resumed
    run into the same bits; a resume asking for other states, or another lanes, is refused,
    and `lanes=None` takes the store's."""
    out = tmp_path / "r.zarr"

    def stop(p):
        if p.done >= 6:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        sweep.run(
            Scenario.from_dict(small()),
            N,
            out,
            chunk=6,
            seed=3,
            lanes=16,
            trajectories=3,
            progress=stop,
        )
    assert np.sum(zarr.open_group(str(out), mode="r")["status"][:] >= 0) == 6
    with pytest.raises(ValueError, match="its trajectories is 3, this run's is 'none'"):
        sweep.run(
            Scenario.from_dict(small()), N, out, seed=3, lanes=16, trajectories="none", resume=True
        )
    with pytest.raises(ValueError, match="its lanes is 16, this run's is 8"):
        sweep.run(Scenario.from_dict(small()), N, out, seed=3, lanes=8, trajectories=3, resume=True)
    sweep.run(
        Scenario.from_dict(small(outputs={**small()["outputs"], "trajectories": 3})),
        N,
        out,
        seed=3,
        resume=True,
    )  # the scenario's own setting, the store's lanes
    ref, got = load(reference_run), load(out)
    assert_same({k: ref[k] for k in PER_TRAJECTORY}, {k: got[k] for k in PER_TRAJECTORY})
    for k in ("omega", "quat"):
        assert np.array_equal(ref[k][::3], got[k], equal_nan=True), k


def test_a_summaries_only_store_costs_under_200_bytes_a_trajectory(tmp_path):
    """A store keeping no states holds per trajectory the inertia (9 float64, 72 bytes),
    three summaries (24), `status` (4), `num_steps` (8) and the `trajectory` coordinate
    (8): 116 bytes before compression. Zarr's compressor takes little off the drawn floats
    (the symmetric inertia to 68 bytes) and nearly all of the integers; the metadata files,
    24 kB, are 6 bytes a trajectory at n = 4096. Measured: 92 bytes a trajectory (bound
    200: what the store holds for every trajectory, not a state among it)."""
    n = 4096
    out = sweep.run(
        Scenario.from_dict(small()),
        n,
        tmp_path / "s.zarr",
        chunk=256,
        seed=0,
        lanes=16,
        trajectories="none",
    )
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    assert 80 < size / n < 200, size / n


def test_float32_sweep_agrees_with_float64_solves_of_its_draws(tmp_path):
    """A float32 sweep of gg_axisymmetric at rtol = atol = 1e-6 stores float32 (status and
    num_steps as ints), gives the same bits with 64-bit types on or off, and agrees with
    float64 solves of its own draws (its inertia and initial states) at rtol 1e-12.

    A float32 sweep draws from float32 random numbers: the float64 sweep of the same seed
    draws other values (JAX makes a float64 normal from 64 random bits), so the reference
    is the float64 solve of the float32 draws. The difference is the tolerance's
    truncation error over 30 s (measured 1.5e-4 in ω at the last time, as the float64 solve
    at rtol 1e-6 gives), not float32's round-off (6e-8 a step): the bounds are 3× the
    measured errors."""
    import jax

    d = Scenario.load("gg_axisymmetric").source
    d["solver"].update(rtol=1e-6, atol=1e-6)
    sc, n = Scenario.from_dict(d), 16
    out = sweep.run(sc, n, tmp_path / "f32.zarr", chunk=n, lanes=16, seed=1, dtype="float32")
    with jax.enable_x64(False):
        off = sweep.run(sc, n, tmp_path / "off.zarr", chunk=n, lanes=16, seed=1, dtype="float32")
    names = ("omega", "quat", "inertia", "status", "num_steps", *sc.summaries)
    assert_same(load(out, names), load(off, names))
    ds = xr.open_zarr(out).load()
    assert ds.attrs["dtype"] == "float32" and ds.time.dtype == np.float32
    assert {ds[k].dtype for k in ("omega", "quat", "inertia", *sc.summaries)} == {
        np.dtype(np.float32)
    }
    assert (ds.status.dtype, ds.num_steps.dtype) == (np.int32, np.int64)
    assert np.all(ds.status.values == 0)
    # the float64 reference: the scenario's models built on the stored draws
    values = {k: jnp.broadcast_to(v, (n, *v.shape)) for k, v in sc.nominal().items()}
    values.update(
        {
            "model.inertia": ds.inertia.values.astype(np.float64),
            "initial.omega": ds.omega.values[:, 0].astype(np.float64),
            "initial.attitude": ds.quat.values[:, 0].astype(np.float64),
        }
    )
    models, y0s = jax.vmap(sc.build)({k: jnp.asarray(v) for k, v in values.items()})
    ts = sc.ts.astype(np.float64)
    exact = rb.simulate_batch(models, y0s, ts, model_axes=0, rtol=1e-12, atol=1e-12)
    w, w32 = np.asarray(exact.ys.omega), ds.omega.values.astype(np.float64)
    err = np.linalg.norm(w32 - w, axis=-1) / np.linalg.norm(w, axis=-1)
    assert err[:, -1].max() < 5e-4 and err.max() < 5e-4, err.max()
    for name, bound in (
        ("max_nutation", 4e-5),
        ("min_abs_omega", 4e-5),
        ("max_abs_omega", 3e-5),
    ):  # measured 1.3e-5, 1.1e-5, 8.8e-6
        ref = np.asarray(jax.vmap(SUMMARIES[name].fn)(models, exact))
        assert np.max(np.abs(ds[name].values - ref)) < bound, name
    # the energy drift at rtol 1e-6 (the exact one is ~1e-12): measured 3e-6
    assert ds.energy_drift.values.max() < 1e-5


def test_a_float32_program_takes_its_matrix_products_in_full_float32():
    """JAX's default precision takes a float32 matrix product in TF32 (a 10-bit mantissa)
    on recent NVIDIA GPUs: every `dot_general` of a float32 sweep's program asks for the
    highest precision instead (on a CPU the program runs the same either way)."""
    import jax
    from helpers import equations

    d = Scenario.load("gg_axisymmetric").source
    d["solver"].update(rtol=1e-6, atol=1e-6, dtype="float32")
    sc = Scenario.from_dict(d)
    runner = sweep._chunk._runner(sc, 16, tuple(jax.devices()), 16)
    jaxpr = jax.make_jaxpr(
        lambda i, sc, key: sweep._chunk._chunk_program(sc, runner.lanes, runner.mesh, i, key)
    )(jnp.arange(runner.size), runner.solved, jax.random.key(0))
    dots = [e for e in equations(jaxpr) if e.primitive.name == "dot_general"]
    assert dots and all(e.params["precision"] == (jax.lax.Precision.HIGHEST,) * 2 for e in dots)


def test_chunking_on_a_cpu_and_on_a_gpu():
    """The rule: 1024 and 64 lanes on a CPU; on a GPU a power of two of trajectories per
    device, within half its memory, 2²⁰ and a 1 GiB stored zarr chunk, through the lanes
    `simulate_batch` takes for a share (`default_lanes`: all of a small share, a third of a
    larger one, at most 2¹⁷)."""
    tb = (25_000, 2_592)  # bytes a trajectory: on the device, in the largest stored chunk
    chunking = sweep.chunking
    assert chunking(10**6, platform="cpu", devices=2, memory=None, trajectory_bytes=tb) == (
        1024,
        64,
    )
    assert chunking(
        10**6, platform="cpu", devices=2, memory=None, trajectory_bytes=tb, chunk=300
    ) == (300, 64)
    gpu = {"platform": "gpu", "devices": 1, "memory": 60 * 10**9}
    # 1.2 M fit the memory, but a 2²⁰ chunk of quat (2592 bytes each) is 2.7 GB: 2¹⁸
    assert chunking(10**8, **gpu, trajectory_bytes=tb) == (1 << 18, -(-(1 << 18) // 3))
    # no states stored: the cap of 2²⁰; a smaller device: its memory (0.5 × 16e9 / 25e3)
    assert chunking(10**8, **gpu, trajectory_bytes=(25_000, 72)) == (1 << 20, 1 << 17)
    assert chunking(10**8, **{**gpu, "memory": 16 * 10**9}, trajectory_bytes=(25_000, 72)) == (
        1 << 18,
        -(-(1 << 18) // 3),
    )
    # memory not known: 8 GiB; two devices: a share each
    assert chunking(10**8, **{**gpu, "memory": None}, trajectory_bytes=(25_000, 72)) == (
        1 << 17,
        -(-(1 << 17) // 3),
    )
    assert chunking(10**8, **{**gpu, "devices": 2}, trajectory_bytes=(25_000, 72)) == (
        1 << 21,
        1 << 17,
    )
    # no more than n needs; a small share (a chunk given, say): a lane per trajectory
    assert chunking(1000, **gpu, trajectory_bytes=tb) == (1024, 1024)
    assert chunking(1000, **{**gpu, "devices": 2}, trajectory_bytes=tb) == (1024, 512)
    assert chunking(10**8, **{**gpu, "devices": 2}, trajectory_bytes=tb, chunk=5001) == (5001, 2501)
    assert chunking(10**8, **gpu, trajectory_bytes=(10**12, 72)) == (1, 1)  # at least one
    # every K-th trajectory's states: the chunk a multiple of K, when K is smaller
    assert chunking(
        10**6, platform="cpu", devices=2, memory=None, trajectory_bytes=tb, every=10
    ) == (1020, 64)
    assert chunking(
        10**6, platform="cpu", devices=2, memory=None, trajectory_bytes=tb, every=3000
    ) == (1024, 64)
    assert chunking(10**8, **gpu, trajectory_bytes=(25_000, 72), every=1000) == (1048000, 1 << 17)


def test_trajectory_bytes_of_the_default_scenario():
    """torque_free_flip, float64: 81 × 7 states (4536 bytes), 9 inertia components and 4
    summaries (104), status and num_steps (12) three times over, and 64 lane copies of its
    7 state and 16 drawn values (11,776); its quat, 81 × 4 × 8 = 2592 bytes, when stored."""
    sc = Scenario.load("torque_free_flip")
    assert sweep.trajectory_bytes(sc) == (3 * (4536 + 104 + 12) + 11_776, 2592)
    assert sweep.trajectory_bytes(sc.with_settings(trajectories="none"))[1] == 72
    assert sweep.trajectory_bytes(sc.with_settings(trajectories=100))[1] == 72
    assert sweep.trajectory_bytes(sc.with_settings(trajectories=10))[1] == 260


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_an_interrupt_python_ignored_still_stops_the_sweep(tmp_path):
    """Ctrl-C whose `KeyboardInterrupt` is raised inside a garbage-collector callback (JAX
    registers one), where Python prints "Exception ignored" and goes on: the sweep stops
    after the region it was writing, as for any Ctrl-C, instead of running to the end."""
    fired = []

    def collecting(phase, info):  # the interrupt arrives while the collector runs
        if phase == "start" and not fired:
            fired.append(phase)
            signal.raise_signal(signal.SIGINT)

    def progress(p):
        if p.done >= 6 and not fired:
            gc.callbacks.append(collecting)
            gc.collect()
            assert fired  # and the KeyboardInterrupt was swallowed: we are still here

    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    out = tmp_path / "i.zarr"
    try:
        with pytest.raises(KeyboardInterrupt):
            sweep.run(
                Scenario.from_dict(small()), N, out, chunk=6, seed=3, lanes=16, progress=progress
            )
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, before)
        if collecting in gc.callbacks:
            gc.callbacks.remove(collecting)
    assert np.sum(zarr.open_group(str(out), mode="r")["status"][:] >= 0) == 6


def test_an_interrupt_waits_for_the_region_being_written():
    """Ctrl-C while a region is written is delivered once it is written (zarr writes from
    its own thread, which an interrupt of the main one would leave running: the store would
    then change after the sweep returned); the handler is then the caller's again."""
    from rbdyn_jax.sweep._run import _interrupt_held

    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        written = []
        with pytest.raises(KeyboardInterrupt):
            with _interrupt_held():
                signal.raise_signal(signal.SIGINT)
                written.append("region")  # still runs: the interrupt is held
        assert written == ["region"]
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        with _interrupt_held():  # none held: nothing delivered
            written.append("next")
        assert written == ["region", "next"]
    finally:
        signal.signal(signal.SIGINT, before)
