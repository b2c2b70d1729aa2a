"""`identify.Observations.from_file`: records written with NumPy (NPZ, CSV) and xarray
(netCDF, zarr) read back as the `Observations` built from the same arrays; `trajectories`
keeps the first K, noise levels given override the file's; a missing or bad file is an
error naming it and what is wrong."""

import numpy as np
import pytest
import xarray as xr
from scipy.spatial.transform import Rotation

from rbdyn_jax.identify import Observations

FIELDS = ("ts", "omega", "quat", "sigma_omega", "sigma_quat", "mask", "mask_omega", "mask_quat")
K, N = 3, 6
TS = np.linspace(0.0, 1.0, N)


@pytest.fixture
def record():
    rng = np.random.default_rng(0)
    w = rng.standard_normal((K, N, 3))
    q = rng.standard_normal((K, N, 4))
    return w, q / np.linalg.norm(q, axis=-1, keepdims=True)


def assert_same(a: Observations, b: Observations):
    for name in FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            np.testing.assert_array_equal(x, y, err_msg=name)


def _csv(path, rows, header="trajectory,t,wx,wy,wz,qw,qx,qy,qz"):
    lines = [header, *(",".join(repr(float(x)) for x in r) for r in rows)]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_npz_round_trip(tmp_path, record):
    w, q = record
    np.savez(tmp_path / "obs.npz", ts=TS, omega=w, quat=q, sigma_omega=0.1, sigma_quat=0.02)
    got = Observations.from_file(tmp_path / "obs.npz")
    assert_same(got, Observations(TS, omega=w, quat=q, sigma_omega=0.1, sigma_quat=0.02))
    # a str path; the first K; a noise level given overrides the file's
    two = Observations.from_file(str(tmp_path / "obs.npz"), trajectories=2, sigma_omega=0.5)
    assert_same(two, Observations(TS, omega=w[:2], quat=q[:2], sigma_omega=0.5, sigma_quat=0.02))


def test_the_first_trajectories_keep_a_noise_level_per_sample(tmp_path, record):
    """`trajectories` cuts the arrays that have a trajectory axis only: a σ per sample
    `(n, 3)` or per component, shared by the trajectories, is kept whole. A count that is
    not positive is refused."""
    w, q = record
    sigma = np.linspace(0.1, 0.5, N)[:, None] * np.ones(3)  # (n, 3): one per sample
    sigma_q = np.linspace(0.01, 0.05, N)  # (n,)
    np.savez(tmp_path / "s.npz", ts=TS, omega=w, quat=q, sigma_omega=sigma, sigma_quat=sigma_q)
    for k in (1, 2):
        got = Observations.from_file(tmp_path / "s.npz", trajectories=k)
        assert_same(
            got, Observations(TS, omega=w[:k], quat=q[:k], sigma_omega=sigma, sigma_quat=sigma_q)
        )
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="`trajectories`"):
            Observations.from_file(tmp_path / "s.npz", trajectories=bad)


def test_quaternions_written_to_four_decimals_are_renormalised_when_asked(
    tmp_path, record, capsys, monkeypatch
):
    """A CSV of quaternions rounded to 4 decimals (norms off by up to ~1e-4) is refused,
    naming the option; with `normalize_quat=True` it reads as the unit quaternions of the
    rounded values, and `rbdyn fit` offers the same as `--normalize-quat`."""
    from rbdyn_jax import cli

    monkeypatch.setenv("RBDYN_JAX_CACHE_DIR", "")  # the command leaves JAX's cache off
    w, q = record
    rows = [[k, t, *np.round(q[k, i], 4)] for k in range(K) for i, t in enumerate(TS)]
    path = _csv(tmp_path / "q4.csv", rows, "trajectory,t,qw,qx,qy,qz")
    with pytest.raises(ValueError, match="not a unit quaternion.*`normalize_quat=True`"):
        Observations.from_file(path)
    got = Observations.from_file(path, normalize_quat=True)
    rounded = np.round(q, 4)
    assert_same(got, Observations(TS, quat=rounded, normalize_quat=True))
    unit = rounded / np.linalg.norm(rounded, axis=-1, keepdims=True)
    np.testing.assert_allclose(got.quat, unit, rtol=0, atol=1e-15)  # rounding of the norm
    args = ["fit", str(path), "--model", "torque_free_flip", "--out", str(tmp_path / "f")]
    assert cli.main(args) == 2
    assert "pass --normalize-quat to renormalise" in capsys.readouterr().err
    assert cli.main([*args, "--normalize-quat", "--steps", "1"]) in (0, 6)


def test_npz_of_euler_angles_per_trajectory_times_and_a_mask(tmp_path, record):
    """`euler` with the file's own `seq`, `ts` (K, n) and a `mask` padding the last record."""
    w, q = record
    angles = Rotation.from_quat(q.reshape(-1, 4), scalar_first=True).as_euler("XYZ")
    angles = angles.reshape(K, N, 3)
    ts = np.tile(TS, (K, 1)) + np.arange(K)[:, None]
    mask = np.ones((K, N), bool)
    mask[-1, 4:] = False
    np.savez(tmp_path / "e.npz", ts=ts, euler=angles, seq="XYZ", mask=mask)
    got = Observations.from_file(tmp_path / "e.npz")
    assert_same(got, Observations(ts, euler=angles, seq="XYZ", mask=mask))
    sign = np.sign(np.sum(np.asarray(got.quat) * q, axis=-1, keepdims=True))
    np.testing.assert_allclose((sign * np.asarray(got.quat))[mask], q[mask], atol=1e-12)
    one = Observations.from_file(tmp_path / "e.npz", trajectories=1)
    assert_same(one, Observations(ts[:1], euler=angles[:1], seq="XYZ", mask=mask[:1]))


def test_a_csv_written_by_pandas_with_its_index_column_reads_as_without(tmp_path, record):
    """`DataFrame.to_csv`'s default writes the index first under an empty name: that column
    is ignored, as any column that is no field's (here also a named one)."""
    pd = pytest.importorskip("pandas")
    w, q = record
    rows = [[k, TS[i], *w[k, i], *q[k, i]] for k in range(K) for i in range(N)]
    names = ["trajectory", "t", "wx", "wy", "wz", "qw", "qx", "qy", "qz"]
    table = pd.DataFrame(rows, columns=names).assign(sensor="imu")
    table.to_csv(tmp_path / "indexed.csv")  # the index under an empty header
    assert (tmp_path / "indexed.csv").read_text().startswith(",trajectory,t,")
    got = Observations.from_file(tmp_path / "indexed.csv")
    assert_same(got, Observations.from_file(_csv(tmp_path / "plain.csv", rows)))
    assert_same(got, Observations(np.broadcast_to(TS, (K, N)), omega=w, quat=q))


def test_csv_round_trip_pads_records_of_different_lengths(tmp_path, record):
    w, q = record
    lengths = (N, N - 1, N - 3)
    rows = [[k, TS[i], *w[k, i], *q[k, i]] for k in range(K) for i in range(lengths[k])]
    got = Observations.from_file(_csv(tmp_path / "obs.csv", rows), sigma_quat=0.01)
    mask = np.arange(N)[None, :] < np.array(lengths)[:, None]
    ts = np.where(mask, TS, np.nan)
    want = Observations(
        ts,
        omega=np.where(mask[..., None], w, np.nan),
        quat=np.where(mask[..., None], q, np.nan),
        mask=mask,
        sigma_quat=0.01,
    )
    assert_same(got, want)
    assert not bool(got.mask_omega[2, N - 3 :].any())
    # no `trajectory` column: one record; ω only
    only = _csv(tmp_path / "w.csv", [[TS[i], *w[0, i]] for i in range(N)], "t,wx,wy,wz")
    assert_same(Observations.from_file(only), Observations(TS, omega=w[:1]))
    assert_same(
        Observations.from_file(tmp_path / "obs.csv", trajectories=2),
        Observations(
            ts[:2],
            omega=np.where(mask[:2, :, None], w[:2], np.nan),
            quat=np.where(mask[:2, :, None], q[:2], np.nan),
            mask=mask[:2],
        ),
    )


def test_netcdf_and_zarr_round_trip_keep_the_successful_trajectories(tmp_path, record):
    """A dataset as a sweep store holds it: `omega` and `quat` over (trajectory, time) and a
    `status`; only the successful trajectories (status 0) are read."""
    w, q = record
    ds = xr.Dataset(
        {
            "omega": (("trajectory", "time", "axis"), w),
            "quat": (("trajectory", "time", "quat_component"), q),
            "status": ("trajectory", np.array([0, 2, 0])),
        },
        coords={"time": TS},
    )
    ds.to_netcdf(tmp_path / "obs.nc", engine="scipy")
    ds.to_zarr(tmp_path / "obs.zarr", zarr_format=2)
    want = Observations(TS, omega=w[[0, 2]], quat=q[[0, 2]])
    for path in (tmp_path / "obs.nc", tmp_path / "obs.zarr"):
        assert_same(Observations.from_file(path), want)
        assert_same(
            Observations.from_file(path, trajectories=1, sigma_omega=0.3),
            Observations(TS, omega=w[:1], quat=q[:1], sigma_omega=0.3),
        )


def test_the_formats_load_the_same_record(tmp_path, record):
    """One record written as NPZ, netCDF (xarray, scipy engine) and CSV loads to the same
    `Observations`."""
    w, q = record
    np.savez(tmp_path / "obs.npz", ts=TS, omega=w, quat=q, sigma_omega=0.1)
    xr.Dataset(
        {
            "omega": (("trajectory", "time", "axis"), w),
            "quat": (("trajectory", "time", "quat_component"), q),
        },
        coords={"time": TS},
    ).to_netcdf(tmp_path / "obs.nc", engine="scipy")
    rows = [[k, TS[i], *w[k, i], *q[k, i]] for k in range(K) for i in range(N)]
    a = Observations.from_file(tmp_path / "obs.npz")
    b = Observations.from_file(tmp_path / "obs.nc", sigma_omega=0.1)
    c = Observations.from_file(_csv(tmp_path / "obs.csv", rows), sigma_omega=0.1)
    assert_same(a, b)
    assert_same(a, c)


def test_a_missing_or_bad_file_is_a_clear_error(tmp_path, record):
    w, q = record
    with pytest.raises(FileNotFoundError, match="nowhere.npz: no such file"):
        Observations.from_file(tmp_path / "nowhere.npz")
    np.savez(tmp_path / "colour.npz", ts=TS, omega=w, colour=TS)
    with pytest.raises(ValueError, match=r"colour.npz: unknown arrays \['colour'\]"):
        Observations.from_file(tmp_path / "colour.npz")
    np.savez(tmp_path / "no_ts.npz", omega=w)
    with pytest.raises(ValueError, match="no_ts.npz: no `ts` array"):
        Observations.from_file(tmp_path / "no_ts.npz")
    (tmp_path / "text.npz").write_text("t,wx\n0,1\n")
    with pytest.raises(ValueError, match="text.npz: not an NPZ archive"):
        Observations.from_file(tmp_path / "text.npz")
    _csv(tmp_path / "time.csv", [[0.0, 1.0]], "time,wx")
    with pytest.raises(ValueError, match="time.csv: the header must name a `t` column"):
        Observations.from_file(tmp_path / "time.csv")
    _csv(tmp_path / "half.csv", [[0.0, 1.0, 0.0]], "t,qw,qx")
    with pytest.raises(ValueError, match=r"half.csv: `quat` needs all of the columns"):
        Observations.from_file(tmp_path / "half.csv")
    _csv(tmp_path / "none.csv", [[0.0, 1.0]], "t,speed")
    with pytest.raises(ValueError, match="none.csv: the header names no observed field"):
        Observations.from_file(tmp_path / "none.csv")
    _csv(
        tmp_path / "ids.csv",
        [[0.5, 0.0, 1.0, 2.0, 3.0], [0.0, 1.0, 1.0, 2.0, 3.0]],
        "trajectory,t,wx,wy,wz",
    )
    with pytest.raises(ValueError, match="ids.csv: the `trajectory` column must hold integers"):
        Observations.from_file(tmp_path / "ids.csv")
    (tmp_path / "ragged.csv").write_text("t,wx,wy,wz\n0,1,2,3\n1,2\n")
    with pytest.raises(ValueError, match="ragged.csv: not a CSV table of numbers"):
        Observations.from_file(tmp_path / "ragged.csv")
    (tmp_path / "obs.txt").write_text("not a dataset\n")
    with pytest.raises(
        ValueError, match="obs.txt: not a .npz or .csv file, nor a dataset xarray opens"
    ):
        Observations.from_file(tmp_path / "obs.txt")
    xr.Dataset({"energy_drift": ("trajectory", np.zeros(K))}).to_netcdf(
        tmp_path / "summaries.nc", engine="scipy"
    )
    with pytest.raises(ValueError, match="summaries.nc holds no ω or attitude to fit"):
        Observations.from_file(tmp_path / "summaries.nc")
