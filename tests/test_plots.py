"""`rbdyn_jax._plots.plot_sweep` on small sweep stores built here with zarr directly.

The store mimics the layout of `rbdyn_jax.sweep`: torque-free rotations (J ω' = Jω × ω with the
quaternion kinematics q' = ½ q ⊗ (0, ω), docs/physics.md#quaternion-kinematics) solved with
scipy, one failed trajectory whose summaries are 1e6 outliers and whose rates turn to NaN, and
one not run yet; every variable carries the CF attributes `units`, `long_name` and
`description`, and the group the scenario's source as JSON (`scenario`, whose torques decide
whether polhodes are drawn).
"""

import functools
import json
import sys

import numpy as np
import pytest
from helpers import wxyz_to_xyzw
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

from rbdyn_jax import _plots

xr = pytest.importorskip("xarray")
zarr = pytest.importorskip("zarr")
matplotlib = pytest.importorskip("matplotlib")

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
FOUR = ["summaries.png", "trajectories.png", "polhodes.png", "status.png"]
STATUS_CODES = {"-1": "not_run", "0": "successful", "1": "max_steps_reached", "2": "nonfinite"}
SUMMARIES = ["max_nutation", "energy_drift", "first_flip_time", "min_abs_omega", "max_abs_omega"]
# name: (units, long_name), as the sweep writes them (a summary's long_name is its name).
CF = {
    "time": ("s", "time"),
    "omega": ("rad/s", "body angular velocity"),
    "quat": ("1", "attitude quaternion"),
    "inertia": ("kg m2", "inertia tensor"),
    "status": ("1", "solver status"),
    "num_steps": ("1", "solver steps"),
    "max_nutation": ("rad", "max_nutation"),
    "energy_drift": ("1", "energy_drift"),
    "first_flip_time": ("s", "first_flip_time"),
    "min_abs_omega": ("rad/s", "min_abs_omega"),
    "max_abs_omega": ("rad/s", "max_abs_omega"),
}
TORQUE_FREE = {"kind": "rigid_body", "torques": []}
RESTORING = {
    "kind": "rigid_body",
    "torques": [
        {"kind": "restoring_moment", "coeffs": [1.0, 0.5], "eps": 0.02},
        {"kind": "body", "moment": [2e-4, -1.2e-4, 4e-4]},
    ],
}
BALANCED = {
    "kind": "relative_rigid_body",
    "frame": {"kind": "euler_angles", "seq": "ZXZ"},
    "torques": [{"kind": "balancing_transport"}],
}
J_DIAG = np.diag([1.0, 2.0, 3.0])
# A rotated body: principal moments (1, 2, 3) with products of inertia.
R_TILT = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
J_ROTATED = R_TILT @ J_DIAG @ R_TILT.T


def rhs(t, y, J):
    """Torque-free Euler equations and quaternion kinematics, state [ω, q_wxyz]."""
    w, q = y[:3], y[3:]
    dw = np.linalg.solve(J, np.cross(J @ w, w))
    qw, qv = q[0], q[1:]
    dq = 0.5 * np.concatenate([[-qv @ w], qw * w + np.cross(qv, w)])
    return np.concatenate([dw, dq])


TIME = np.linspace(0.0, 20.0, 81)
STARTS = [  # near the intermediate axis (flips), near the major and minor axes, a generic one
    (J_DIAG, [0.01, 1.0, 0.01]),
    (J_DIAG, [0.1, 0.05, 1.0]),
    (J_DIAG, [1.0, 0.1, 0.05]),
    (J_ROTATED, R_TILT @ np.array([0.02, 1.0, 0.03])),
    (J_DIAG, [0.4, 0.5, 0.6]),
]


@functools.cache
def solve(i):
    """(J, ω(t), q(t)) of STARTS[i] on TIME, from a 5.7° tilt about x (solved once per session)."""
    J, w0 = STARTS[i]
    q0 = np.array([np.cos(0.05), np.sin(0.05), 0.0, 0.0])
    y0 = np.concatenate([w0, q0])
    sol = solve_ivp(rhs, TIME[[0, -1]], y0, t_eval=TIME, args=(J,), rtol=1e-10, atol=1e-12)
    return J, sol.y[:3].T, sol.y[3:].T


def make_dataset(status):
    """Arrays of a sweep with len(status) trajectories on TIME (sweep layout)."""
    time, T = TIME, len(TIME)
    N = len(status)
    omega, quat = np.full((N, T, 3), np.nan), np.full((N, T, 4), np.nan)
    inertia = np.empty((N, 3, 3))
    summaries = {name: np.full(N, np.nan) for name in SUMMARIES}
    for k, s in enumerate(status):
        J, omega_k, quat_k = solve(k % len(STARTS))
        inertia[k] = J
        if s == -1:
            continue
        omega[k], quat[k] = omega_k, quat_k
        energy = 0.5 * np.einsum("ti,ij,tj->t", omega[k], J, omega[k])
        nutation = _plots._nutation(quat[k])
        w_principal = omega[k] @ np.linalg.eigh(J)[1]
        flips = np.flatnonzero(np.diff(np.sign(w_principal[:, 1])) != 0)
        speed = np.linalg.norm(omega[k], axis=-1)
        summaries["max_nutation"][k] = nutation.max()
        summaries["energy_drift"][k] = np.abs(energy / energy[0] - 1).max()
        summaries["first_flip_time"][k] = time[flips[0] + 1] if len(flips) else np.nan
        summaries["min_abs_omega"][k] = speed.min()
        summaries["max_abs_omega"][k] = speed.max()
        if s != 0:  # a failure: rates stop half-way, summaries are absurd outliers
            omega[k, T // 2 :] = np.nan
            for values in summaries.values():
                values[k] = 1e6
    return time, omega, quat, inertia, np.asarray(status, np.int32), summaries


def write_store(path, status, *, model=TORQUE_FREE, summaries=True, keep="all"):
    """Write a sweep-layout zarr v3 group at `path`; return `path`. `model`: the scenario's
    `[model]` table (its `kind` is the store's `model_kind`). `keep`: whose states it holds, as
    a sweep's `trajectories`: "all", "none", or every K-th trajectory's over the dimension
    `sampled_trajectory`."""
    time, omega, quat, inertia, status, values = make_dataset(status)
    g = zarr.open_group(str(path), mode="w", zarr_format=3)

    def put(name, data, dims):
        a = g.create_array(
            name, shape=data.shape, chunks=data.shape, dtype=data.dtype, dimension_names=dims
        )
        a[...] = data
        if name in CF:
            units, long_name = CF[name]
            a.attrs.update(
                {
                    "units": units,
                    "long_name": long_name,
                    "description": f"the {long_name.replace('_', ' ')}",
                }
            )

    N = len(status)
    put("trajectory", np.arange(N, dtype=np.int64), ["trajectory"])
    put("time", time, ["time"])
    if keep == "all":
        put("omega", omega, ["trajectory", "time", "axis"])
        put("quat", quat, ["trajectory", "time", "quat_component"])
    elif keep != "none":
        put("sampled_trajectory", np.arange(0, N, keep, dtype=np.int64), ["sampled_trajectory"])
        put("omega", omega[::keep], ["sampled_trajectory", "time", "axis"])
        put("quat", quat[::keep], ["sampled_trajectory", "time", "quat_component"])
    put("inertia", inertia, ["trajectory", "row", "col"])
    put("status", status, ["trajectory"])
    g["status"].attrs.update(
        {
            "flag_values": [int(c) for c in STATUS_CODES],
            "flag_meanings": " ".join(STATUS_CODES.values()),
        }
    )
    put("num_steps", np.full(N, 100, dtype=np.int64), ["trajectory"])
    for name, v in values.items():
        put(name, v, ["trajectory"])
    g.attrs.update(
        {
            "summaries": " ".join(SUMMARIES) if summaries else "",
            "model_kind": model["kind"],
            "scenario_name": "test_scenario",
            "rtol": 1e-10,
        }
    )
    g.attrs["scenario"] = json.dumps({"name": "test_scenario", "model": model})
    return path


@pytest.fixture
def store(tmp_path):
    """Six trajectories: four successful, #3 failed (status 1), #5 not run (status -1)."""
    return write_store(tmp_path / "sweep.zarr", [0, 0, 0, 1, 0, -1])


@pytest.fixture
def suptitles(monkeypatch):
    """The figure titles `plot_sweep` sets, recorded."""
    from matplotlib.figure import Figure

    seen, original = [], Figure.suptitle

    def spy(self, t, **kwargs):
        seen.append(t)
        return original(self, t, **kwargs)

    monkeypatch.setattr(Figure, "suptitle", spy)
    return seen


def recording(made):
    """A stand-in for `_plots._new_figure` that keeps each figure in `made` by its title less
    the scenario's name."""
    original = _plots._new_figure

    def spy(title, size):
        fig = original(title, size)
        made[title.split(": ", 1)[-1]] = fig
        return fig

    return spy


@pytest.fixture
def figures(monkeypatch):
    """The figures `plot_sweep` makes, by their title less the scenario's name."""
    made = {}
    monkeypatch.setattr(_plots, "_new_figure", recording(made))
    return made


def assert_legends_outside_axes(fig):
    """No axes holds a legend; the figure's legends overlap no axes (laid out by `savefig`)."""
    renderer = fig.canvas.get_renderer()
    assert all(ax.get_legend() is None for ax in fig.axes)
    for legend in fig.legends:
        box = legend.get_window_extent(renderer)
        for ax in fig.axes:
            assert not box.overlaps(ax.get_window_extent(renderer)), legend.texts[0].get_text()


def assert_png(path):
    """A PNG file that matplotlib reads back as a non-blank image."""
    import matplotlib.image

    assert path.read_bytes()[:8] == PNG_SIGNATURE
    image = matplotlib.image.imread(path)
    assert image.ndim == 3 and image.shape[0] > 200 and image.shape[1] > 200
    assert np.ptp(image[..., :3]) > 0.5  # ink on paper, not a blank canvas


def test_store_opens_with_xarray(store):
    ds = xr.open_zarr(store, consolidated=False)
    assert dict(ds.sizes) == {
        "trajectory": 6,
        "time": 81,
        "axis": 3,
        "quat_component": 4,
        "row": 3,
        "col": 3,
    }
    assert ds["status"].dtype == np.int32 and ds["trajectory"].dtype == np.int64
    assert ds.attrs["summaries"].split() == SUMMARIES
    np.testing.assert_array_equal(_plots._successful(ds), [0, 1, 2, 4])


def test_writes_four_pngs(store, suptitles):
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    open_figures = plt.get_fignums()
    written = _plots.plot_sweep(store)
    assert plt.get_fignums() == open_figures  # nothing left open in pyplot
    out_dir = store.with_name("sweep.zarr_plots")
    assert written == [out_dir / name for name in FOUR]
    assert sorted(p.name for p in out_dir.iterdir()) == sorted(FOUR)
    for path in written:
        assert_png(path)
    assert "test_scenario: polhode on the energy ellipsoid" in suptitles
    assert not any("hodograph" in t for t in suptitles)


@pytest.fixture(scope="module")
def plotted(tmp_path_factory):
    """The figures of one `plot_sweep` (by title less the scenario's name) of a torque-free store
    whose CF attributes of `time`, `omega` and `first_flip_time` are changed, to show that the
    labels read them: trajectories 0, 1 and 3 (products of inertia) successful, 2 failed."""
    store = write_store(tmp_path_factory.mktemp("plotted") / "s.zarr", [0, 0, 1, 0])
    g = zarr.open_group(str(store), mode="r+")
    g["time"].attrs.update({"units": "min", "long_name": "elapsed time"})
    g["omega"].attrs["units"] = "deg/s"
    g["first_flip_time"].attrs.update({"units": "h", "long_name": "time of the first flip"})
    made = {}
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(_plots, "_new_figure", recording(made))
        _plots.plot_sweep(store, store.with_name("out"))
    return made


def test_axis_labels_carry_the_store_units(plotted):
    """Labels come from the CF `long_name` and `units` of the store, histograms count on y,
    angles are in rad."""
    assert sorted(plotted) == sorted(
        [
            "summaries of 3 successful trajectories",
            "3 of 3 successful trajectories",
            "polhode on the energy ellipsoid",
            "status of 4 trajectories",
        ]
    )
    histograms = plotted["summaries of 3 successful trajectories"].axes
    assert {ax.get_xlabel(): ax.get_ylabel() for ax in histograms} == {
        "max_nutation [rad]": "count",
        "energy_drift [1]": "count",
        "time of the first flip [h]": "count",
        "min_abs_omega [rad/s]": "count",
        "max_abs_omega [rad/s]": "count",
    }
    history = plotted["3 of 3 successful trajectories"].axes
    assert [ax.get_ylabel() for ax in history] == [
        *(rf"$\omega_{{{c}}}$ [deg/s]" for c in "xyz"),
        r"|$\omega$| [deg/s]",
        r"nutation $\theta$ [rad]",
    ]
    assert history[-1].get_xlabel() == "elapsed time [min]"
    for ax in plotted["polhode on the energy ellipsoid"].axes:
        assert [ax.get_xlabel(), ax.get_ylabel(), ax.get_zlabel()] == [
            rf"$\omega_{{{c}}}$ [deg/s]" for c in "xyz"
        ]
    assert plotted["status of 4 trajectories"].axes[0].get_xlabel() == "number of trajectories"


def test_legends_sit_outside_the_axes(plotted):
    assert [len(fig.legends) for fig in plotted.values()] == [0, 1, 1, 0]
    for fig in plotted.values():
        assert_legends_outside_axes(fig)


def test_polhodes_are_drawn_to_scale(plotted):
    """Each polhode's 3-D box has the proportions of its axis ranges: a unit is as long on x, y
    and z, so the energy ellipsoid (drawn, and named in the legend) has its true shape."""
    fig = plotted["polhode on the energy ellipsoid"]
    assert [t.get_text() for t in fig.legends[0].texts] == [
        r"ellipsoid $\omega^T J \omega = 2T(0)$",
        r"$\omega$(t)",
        r"$\omega$(0)",
    ]
    assert [ax.get_title() for ax in fig.axes] == [f"trajectory {i}" for i in (0, 1, 3)]
    for ax in fig.axes:
        assert ax.name == "3d"
        ranges = np.ptp([ax.get_xlim3d(), ax.get_ylim3d(), ax.get_zlim3d()], axis=1)
        scale = np.asarray(ax.get_box_aspect()) / ranges
        np.testing.assert_allclose(scale, scale[0], rtol=1e-9)


def test_a_polhode_near_the_separatrix_is_not_seen_edge_on():
    """Two half-ellipses through ±y on the planes z = ±0.9 x (a polhode near the separatrix):
    the view chosen sees both planes obliquely, where the default view (elevation 30°, azimuth
    −60°) looks almost along the first and draws that half as a chord."""
    s = np.linspace(0.0, np.pi, 60)
    curve = np.concatenate(
        [
            np.stack([np.sin(s), 1.5 * np.cos(s), 0.9 * np.sin(s)], 1),
            np.stack([np.sin(s), -1.5 * np.cos(s), -0.9 * np.sin(s)], 1),
        ]
    )
    normals = np.array([[-0.9, 0.0, 1.0], [0.9, 0.0, 1.0]]) / np.hypot(0.9, 1.0)

    def facing(elev, azim):
        e, a = np.radians(elev), np.radians(azim)
        return np.abs(normals @ [np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])

    assert facing(30, -60).min() < 0.1
    ax = _plots._new_figure("", (4, 4)).add_subplot(projection="3d")
    _plots._open_view(ax, curve)
    assert facing(ax.elev, ax.azim).min() > 0.25


@pytest.mark.parametrize(
    "model, invariant",
    [
        (TORQUE_FREE, True),
        ({"kind": "rigid_body"}, True),
        (BALANCED, True),
        ({"kind": "relative_rigid_body"}, True),  # no torques in the inertial frame
        (RESTORING, False),
        ({"kind": "rigid_body", "torques": [{"kind": "gravity_gradient", "eps": 3.0}]}, False),
        ({"kind": "relative_rigid_body", "frame": {"kind": "constant_rate"}}, False),
        (
            {
                "kind": "relative_rigid_body",
                "frame": {"kind": "circular_orbit", "n": 1e-3},
                "torques": [{"kind": "gravity_gradient", "orbit_rate": 1e-3}],
            },
            False,
        ),
        (
            {
                "kind": "relative_rigid_body",
                "torques": [{"kind": "balancing_transport"}, {"kind": "body", "moment": [0, 0, 1]}],
            },
            False,
        ),
    ],
)
def test_polhodes_only_where_the_ellipsoid_is_invariant(model, invariant):
    attrs = {"model_kind": model["kind"], "scenario": json.dumps({"model": model})}
    assert _plots._ellipsoid_is_invariant(attrs) is invariant
    assert not _plots._ellipsoid_is_invariant({"model_kind": "rigid_body"})  # no scenario


def test_a_torqued_model_gets_no_polhodes(tmp_path, figures):
    """Under a restoring moment the energy changes: no panel draws ω on an ellipsoid; the time
    histories show |ω| and the nutation instead."""
    store = write_store(tmp_path / "s.zarr", [0, 0, 1], model=RESTORING)
    written = _plots.plot_sweep(store, tmp_path / "out")
    assert [p.name for p in written] == ["summaries.png", "trajectories.png", "status.png"]
    assert not any("polhode" in t or "hodograph" in t for t in figures)
    for fig in figures.values():
        assert all(ax.name != "3d" for ax in fig.axes)
        texts = [fig.get_suptitle()] + [t.get_text() for leg in fig.legends for t in leg.texts]
        texts += [ax.get_title() for ax in fig.axes]
        assert not any("ellipsoid" in t or "2T" in t for t in texts)
    history = figures["2 of 2 successful trajectories"].axes
    assert [ax.get_ylabel() for ax in history[3:]] == [
        r"|$\omega$| [rad/s]",
        r"nutation $\theta$ [rad]",
    ]


def test_failed_trajectories_are_excluded(tmp_path):
    ds = xr.open_zarr(write_store(tmp_path / "s.zarr", [1, 0, -1, 0, 2]), consolidated=False)
    ok = _plots._successful(ds)
    np.testing.assert_array_equal(ok, [1, 3])
    values = ds["max_abs_omega"].values
    assert np.nanmax(values) == 1e6 and np.all(values[ok] < 10)  # outliers only where failed
    assert np.all(np.isfinite(ds["omega"].values[ok]))


def test_all_failed_writes_only_status(tmp_path, suptitles):
    store = write_store(tmp_path / "s.zarr", [1, -1, 2])
    out_dir = tmp_path / "out"
    assert _plots.plot_sweep(store, out_dir) == [out_dir / "status.png"]
    assert [p.name for p in out_dir.iterdir()] == ["status.png"]
    assert_png(out_dir / "status.png")
    assert suptitles == ["test_scenario: status of 3 trajectories"]


def test_relative_dataset_is_a_hodograph(tmp_path, suptitles):
    store = write_store(tmp_path / "r.zarr", [0, 0], model=BALANCED)
    written = _plots.plot_sweep(store, tmp_path / "out", n_sample=1)
    assert [p.name for p in written] == FOUR
    assert "test_scenario: hodograph of ω_r" in suptitles
    assert not any("polhode" in t for t in suptitles)
    assert "test_scenario: 1 of 2 successful trajectories" in suptitles


def test_no_summaries_skips_that_file(tmp_path):
    store = write_store(tmp_path / "s.zarr", [0, 1], summaries=False)
    written = _plots.plot_sweep(store, tmp_path / "out")
    assert [p.name for p in written] == FOUR[1:]


def test_a_store_of_no_states_skips_their_plots(tmp_path):
    store = write_store(tmp_path / "s.zarr", [0, 1, 0], keep="none")
    written = _plots.plot_sweep(store, tmp_path / "out")
    assert [p.name for p in written] == ["summaries.png", "status.png"]


def test_a_store_of_sampled_states_draws_them(tmp_path, suptitles, monkeypatch):
    """Every 2nd trajectory's states: the successful sampled ones (0 and 4; 2 failed) are
    drawn, labelled with their trajectory index, each with its own inertia."""
    drawn = {}
    monkeypatch.setattr(
        _plots,
        "_draw_polhodes",
        lambda fig, omega, inertia, labels, *a: drawn.update(
            omega=omega, inertia=inertia, labels=labels
        ),
    )
    store = write_store(tmp_path / "s.zarr", [0, 0, 1, 0, 0, -1], keep=2)
    written = _plots.plot_sweep(store, tmp_path / "out")
    assert [p.name for p in written] == FOUR
    assert "test_scenario: 2 of 2 successful sampled trajectories" in suptitles
    assert list(drawn["labels"]) == [0, 4]
    for k, i in enumerate([0, 4]):
        J, omega, _ = solve(i % len(STARTS))
        np.testing.assert_array_equal(drawn["inertia"][k], J)
        np.testing.assert_array_equal(drawn["omega"][k], omega)
    assert_png(tmp_path / "out" / "trajectories.png")
    # no sampled trajectory succeeded: no states to draw
    store = write_store(tmp_path / "f.zarr", [1, 0, 1, 0], keep=2)
    assert [p.name for p in _plots.plot_sweep(store, tmp_path / "f")] == [
        "summaries.png",
        "status.png",
    ]


def test_energy_ellipsoid_with_products_of_inertia():
    w0 = np.array([0.3, -1.1, 0.7])
    energy = 0.5 * w0 @ J_ROTATED @ w0
    points = _plots._energy_ellipsoid(J_ROTATED, energy).reshape(3, -1)
    np.testing.assert_allclose(
        np.einsum("in,ij,jn->n", points, J_ROTATED, points), 2 * energy, rtol=1e-12
    )
    # The extreme |ω| are the semi-axes sqrt(2T / I) along the largest and smallest moments.
    speed = np.linalg.norm(points, axis=0)
    assert speed.max() == pytest.approx(np.sqrt(2 * energy / 1.0), rel=1e-12)
    assert speed.min() == pytest.approx(np.sqrt(2 * energy / 3.0), rel=1e-12)


def test_polhodes_lie_on_their_ellipsoids(tmp_path):
    """The fixture's physics: each successful ω(t) keeps ωᵀ J ω = 2T (what polhodes.png shows)."""
    ds = xr.open_zarr(write_store(tmp_path / "s.zarr", [0, 0, 0, 0, 0]), consolidated=False)
    omega, inertia = ds["omega"].values, ds["inertia"].values
    two_t = np.einsum("kti,kij,ktj->kt", omega, inertia, omega)
    np.testing.assert_allclose(two_t, two_t[:, :1] * np.ones_like(two_t), rtol=1e-8)


def test_nutation_matches_scipy(rng):
    q = rng.normal(size=(50, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    R = Rotation.from_quat(wxyz_to_xyzw(q)).as_matrix()
    expected = np.arccos(np.clip(R[:, 2, 2], -1, 1))
    np.testing.assert_allclose(_plots._nutation(q), expected, atol=1e-12)


def test_status_names_from_cf_flags():
    attrs = {
        "flag_values": np.array([-1, 0, 1], np.int32),
        "flag_meanings": "not_run successful max_steps_reached",
    }
    assert _plots._status_names(attrs) == {-1: "not_run", 0: "successful", 1: "max_steps_reached"}
    assert _plots._status_names({}) == {}


def test_bad_n_sample(store):
    with pytest.raises(ValueError, match="n_sample"):
        _plots.plot_sweep(store, n_sample=0)


def test_missing_matplotlib_says_how_to_install(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    with pytest.raises(ImportError, match="pip install matplotlib"):
        _plots.plot_sweep(tmp_path / "nothing.zarr")
