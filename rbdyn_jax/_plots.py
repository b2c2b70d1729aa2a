"""PNG plots of a Monte Carlo sweep dataset (the zarr store written by `rbdyn_jax.sweep`).

`plot_sweep` reads the store with xarray and writes up to four figures: histograms of the
per-trajectory summaries, sample time histories of the body rates, their magnitude and the
nutation angle, sample polhodes on their kinetic-energy ellipsoids
(docs/physics.md#torque-free-motion; hodographs of ω_r for relative motion,
docs/physics.md#balancing-transport-moment), and the counts per status code. Only successful
trajectories (`status == 0`) enter the first three. The time histories and polhodes are drawn
from the states the store keeps: every trajectory's, every K-th one's (over
`sampled_trajectory`), or none (a summaries-only store: those two figures are skipped).
Polhodes are drawn only for a model whose ellipsoid is invariant (`_ellipsoid_is_invariant`):
under any other torque ω(t) leaves the ellipsoid of its initial energy, and the time histories
of |ω| and θ show the motion instead.

Axis labels take their names and units from the store's CF attributes (`long_name`, `units`);
angles are in radians, as everywhere in the library and its store (the nutation summaries'
`units` are `rad`). Geometry is drawn to scale: the 3-D axes of a polhode have equal units.
Legends sit outside the axes.

matplotlib and xarray are imported inside `plot_sweep`, so this module imports without them.
Figures are built as `matplotlib.figure.Figure` on an Agg canvas, never through `pyplot`, so no
global backend is switched and no figure is left open in pyplot's registry.
"""

import json
import math
import pathlib
import textwrap

import numpy as np

_AXES = ("x", "y", "z")


def _successful(ds) -> np.ndarray:
    """Positions along `trajectory` (0-based, for `isel`) of the trajectories with `status == 0`.

    **Arguments:**

    - `ds`: a sweep dataset with a `(trajectory,)` variable `status`.

    **Returns:** a sorted `int64` array of positions.
    """
    return np.flatnonzero(np.asarray(ds["status"].values) == 0)


def _stored_states(ds, ok: np.ndarray, n_sample: int):
    """The states of the first `n_sample` successful trajectories the store keeps them for:
    `(labels, omega, quat, inertia, title)`, their trajectory indices, arrays, and the
    figure's title (how many of how many); `None` when there are none (a summaries-only
    store, or no sampled trajectory succeeded).

    A store keeping every K-th trajectory's states has them over the dimension
    `sampled_trajectory`, whose coordinate holds the trajectory indices."""
    if "omega" not in ds or "quat" not in ds:
        return None
    if "sampled_trajectory" not in ds["omega"].dims:
        kept, which, pick = ok, "successful", {"trajectory": ok[:n_sample]}
        labels = np.asarray(ds["trajectory"].values)[ok[:n_sample]]
    else:
        indices = np.asarray(ds["sampled_trajectory"].values)
        kept = np.flatnonzero(np.asarray(ds["status"].sel(trajectory=indices).values) == 0)
        which, pick = "successful sampled", {"sampled_trajectory": kept[:n_sample]}
        labels = indices[kept[:n_sample]]
    if not len(kept):
        return None
    omega, quat = (np.asarray(ds[k].isel(pick).values, dtype=float) for k in ("omega", "quat"))
    inertia = np.asarray(ds["inertia"].sel(trajectory=labels).values, dtype=float)
    return labels, omega, quat, inertia, f"{len(labels)} of {len(kept)} {which} trajectories"


def _nutation(quat: np.ndarray) -> np.ndarray:
    """Nutation angle θ in radians — the angle between the body z axis and the parent z axis — of
    unit quaternions `quat[..., 4]` (`[w, x, y, z]`, body → parent): cos θ = R₃₃ = 1 − 2(x² + y²)
    (the `max_nutation` and `final_nutation` summaries' angle).
    """
    x, y = quat[..., 1], quat[..., 2]
    return np.arccos(np.clip(1.0 - 2.0 * (x**2 + y**2), -1.0, 1.0))


def _energy_ellipsoid(inertia: np.ndarray, energy: float, n_u: int = 25, n_v: int = 13):
    """Grid of points ω on the ellipsoid ωᵀ J ω = 2T, as an array of shape `(3, n_v, n_u)`.

    J may have products of inertia: with J = Σ I_i e_i e_iᵀ (`numpy.linalg.eigh`), the semi-axis
    along the principal axis e_i is sqrt(2T / I_i).
    """
    moments, axes = np.linalg.eigh(inertia)
    u = np.linspace(0.0, 2.0 * np.pi, n_u)
    v = np.linspace(0.0, np.pi, n_v)
    sphere = np.stack(
        [
            np.outer(np.sin(v), np.cos(u)),
            np.outer(np.sin(v), np.sin(u)),
            np.outer(np.cos(v), np.ones_like(u)),
        ]
    )
    return np.einsum("ij,j,jvu->ivu", axes, np.sqrt(2.0 * energy / moments), sphere)


def _ellipsoid_is_invariant(attrs) -> bool:
    """Whether ω(t) of a store's trajectories stays on the ellipsoid of its initial kinetic
    energy (of its initial relative kinetic energy, for relative motion): the condition for
    drawing polhodes.

    From the global attributes `model_kind` and `scenario` (the scenario's source as JSON): a
    `rigid_body` with no torques conserves T (docs/physics.md#torque-free-motion); a
    `relative_rigid_body` whose only torque is one `balancing_transport`, or with no torques
    in the inertial frame, conserves T_r (docs/physics.md#balancing-transport-moment). Any other
    torque changes the energy, and a store without a readable `scenario` is not taken to be
    torque-free.
    """
    try:
        model = json.loads(str(attrs["scenario"]))["model"]
        torques = [t["kind"] for t in model.get("torques", [])]
        frame = model.get("frame", {}).get("kind", "inertial")
    except (KeyError, TypeError, AttributeError, ValueError):
        return False
    kind = attrs.get("model_kind", model.get("kind"))
    if kind == "rigid_body":
        return not torques
    return kind == "relative_rigid_body" and (
        torques == ["balancing_transport"] or (not torques and frame == "inertial")
    )


def _status_names(attrs) -> dict[int, str]:
    """`{code: name}` from the CF attributes `flag_values` and `flag_meanings` of `status`."""
    if "flag_values" not in attrs or "flag_meanings" not in attrs:
        return {}
    return dict(
        zip((int(c) for c in np.ravel(attrs["flag_values"])), str(attrs["flag_meanings"]).split())
    )


def _units(attrs, default: str = "") -> str:
    """The CF `units` attribute, `default` if there is none."""
    return str(attrs.get("units", default) or default)


def _label(name: str, attrs) -> str:
    """An axis label `"<long_name> [<units>]"` from the CF attributes of the variable `name`:
    `name` where there is no `long_name`, no brackets where there are no `units`.
    Dimensionless quantities (units `1`) read `[1]`."""
    what = str(attrs.get("long_name", "") or name)
    units = _units(attrs)
    return f"{what} [{units}]" if units else what


def _omega(relative: bool, component: str = "") -> str:
    """Mathtext for ω — ω_r, the rate relative to the moving frame, if `relative` — or for its
    `component` ("x", "y" or "z")."""
    sub = ",".join(s for s in ("r" if relative else "", component) if s)
    return rf"$\omega_{{{sub}}}$" if sub else r"$\omega$"


def _grid(n: int, max_cols: int) -> tuple[int, int]:
    """(rows, cols) of a grid holding `n ≥ 1` panels, at most `max_cols` wide."""
    cols = min(n, max_cols)
    return math.ceil(n / cols), cols


def _new_figure(title: str, size: tuple[float, float]):
    """A constrained-layout `Figure` on an Agg canvas (outside pyplot: nothing to close)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, layout="constrained")
    FigureCanvasAgg(fig)
    fig.suptitle(title)
    return fig


def _sci_ticks(ax, axis: str = "y") -> None:
    """Tick labels of `axis` with a common power of ten outside [1e-3, 1e4] (so that 1e-4 reads
    as 1 with a ×1e-4 offset, not 0.0001)."""
    formatter = getattr(ax, f"{axis}axis").get_major_formatter()
    if hasattr(formatter, "set_powerlimits"):
        formatter.set_powerlimits((-3, 4))


def _draw_summaries(fig, ds, ok: np.ndarray, names: list[str]) -> None:
    """One histogram per summary in `names` over the successful, finite values, with n/mean/std:
    titled with the summary's name and CF `description`, x labelled with its `long_name` and
    `units`, y with the count of trajectories per bin."""
    rows, cols = _grid(len(names), 3)
    for i, name in enumerate(names):
        ax = fig.add_subplot(rows, cols, i + 1)
        attrs = ds[name].attrs
        values = np.asarray(ds[name].values, dtype=float)[ok]
        values = values[np.isfinite(values)]
        description = str(attrs.get("description", "") or "")
        title = name + (f": {description}" if description else "")
        ax.set_title("\n".join(textwrap.wrap(title, 48)), fontsize=9)
        ax.set_xlabel(_label(name, attrs))
        ax.set_ylabel("count")
        _sci_ticks(ax, "x")
        units = _units(attrs)
        unit = f" {units}" if units and units != "1" else ""
        if values.size:
            counts, _, _ = ax.hist(values, bins=min(30, max(5, int(np.sqrt(values.size)))))
            ax.set_ylim(0, 1.45 * counts.max())  # headroom for the text
            std = values.std(ddof=1) if values.size > 1 else 0.0
            text = f"n = {values.size}\nmean = {values.mean():.4g}{unit}\nstd = {std:.4g}{unit}"
        else:
            text = "no finite values"
        box = {"facecolor": "white", "alpha": 0.8, "lw": 0}
        ax.text(
            0.97, 0.95, text, transform=ax.transAxes, ha="right", va="top", fontsize=8, bbox=box
        )


def _draw_trajectories(fig, time, omega, quat, labels, relative: bool, units: dict) -> None:
    """ω_x, ω_y, ω_z, |ω| and the nutation angle against time, one line per sampled trajectory,
    with one legend for all panels outside them. `units`: the CF attributes of `time` and
    `omega` (`{"time": attrs, "omega": attrs}`)."""
    axes = fig.subplots(5, 1, sharex=True)
    rate = _units(units["omega"], "rad/s")
    for k, label in enumerate(labels):
        for i in range(3):
            axes[i].plot(time, omega[k, :, i], lw=1, label=f"trajectory {label}")
        axes[3].plot(time, np.linalg.norm(omega[k], axis=-1), lw=1)
        axes[4].plot(time, _nutation(quat[k]), lw=1)
    for i, c in enumerate(_AXES):
        axes[i].set_ylabel(f"{_omega(relative, c)} [{rate}]")
    axes[3].set_ylabel(f"|{_omega(relative)}| [{rate}]")
    axes[4].set_ylabel(r"nutation $\theta$ [rad]")
    axes[4].set_xlabel(_label("time", units["time"]))
    for ax in axes:
        _sci_ticks(ax)
    fig.legend(*axes[0].get_legend_handles_labels(), loc="outside right upper", fontsize=8)


def _equal_axes_3d(ax, points: np.ndarray, zoom: float = 0.9) -> None:
    """Limits around `points` (shape `(3, n)`) with a box aspect proportional to their ranges, so
    that a unit is as long on x, y and z and an ellipsoid is drawn to scale."""
    lo, hi = np.nanmin(points, axis=1), np.nanmax(points, axis=1)
    half = 0.5 * (hi - lo)
    half = np.maximum(half, 1e-3 * max(half.max(), np.abs(hi).max(), np.abs(lo).max(), 1e-300))
    mid = 0.5 * (hi + lo)
    ax.set_xlim3d(mid[0] - half[0], mid[0] + half[0])
    ax.set_ylim3d(mid[1] - half[1], mid[1] + half[1])
    ax.set_zlim3d(mid[2] - half[2], mid[2] + half[2])
    ax.set_box_aspect(tuple(2 * half), zoom=zoom)


def _open_view(ax, curve: np.ndarray) -> None:
    """Turn `ax` (z up) to the view in which no arc of `curve` (shape `(n, 3)`) is seen edge-on:
    a planar arc seen from within its plane is drawn as a straight chord (a polhode near the
    separatrix lies on two planes through the intermediate axis). Each bend of the curve has
    a plane, the normal n of two successive steps; the view v taken makes the bends' |n·v|
    largest at their 10th percentile (weighted by the bends' size). Elevations 15°, 30° and
    45°, azimuths 30° to 60° from the x axis in steps of 15° in each quadrant: none looks along
    an axis and hides it."""
    points = curve[np.all(np.isfinite(curve), axis=1)]
    steps = np.diff(points, axis=0)
    bends = np.cross(steps[:-1], steps[1:])
    size = np.linalg.norm(bends, axis=1)
    keep = size > 1e-12 * max(size.max(initial=0.0), 1e-300)
    if keep.sum() < 2:
        return
    normals, weight = bends[keep] / size[keep, None], size[keep] / size[keep].sum()
    best, best_score = (30.0, -60.0), -1.0
    for elev in (15.0, 30.0, 45.0):
        e = np.radians(elev)
        for azim in (q + d for q in (-180.0, -90.0, 0.0, 90.0) for d in (30.0, 45.0, 60.0)):
            a = np.radians(azim)
            view = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
            facing = np.abs(normals @ view)
            order = np.argsort(facing)
            score = facing[order][np.searchsorted(np.cumsum(weight[order]), 0.1)]
            if score > best_score * (1 + 1e-9):
                best, best_score = (elev, azim), score
    ax.view_init(elev=best[0], azim=best[1])


def _draw_polhodes(fig, omega, inertia, labels, relative: bool, surface: str, rate: str) -> None:
    """3-D curves ω(t) of the first (up to 4) trajectories, each on its ellipsoid
    ωᵀ J ω = ω(0)ᵀ J ω(0) (drawn only where J is positive definite and the energy positive),
    at equal scale on the three axes (in `rate` units), seen with no arc edge-on
    (`_open_view`); one legend outside."""
    from matplotlib.ticker import MaxNLocator

    rows, cols = _grid(len(labels), 2)
    handles = {}
    for k, label in enumerate(labels):
        ax = fig.add_subplot(rows, cols, k + 1, projection="3d")
        w0, J = omega[k, 0], inertia[k]
        energy = 0.5 * w0 @ J @ w0
        points = omega[k].T
        if np.all(np.isfinite(J)) and np.isfinite(energy) and energy > 0:
            if np.all(np.linalg.eigvalsh(J) > 0):
                grid = _energy_ellipsoid(J, energy)
                handles[f"ellipsoid {surface}"] = ax.plot_wireframe(*grid, color="0.75", lw=0.4)
                points = np.concatenate([points, grid.reshape(3, -1)], axis=1)
        (handles[f"{_omega(relative)}(t)"],) = ax.plot(*omega[k].T, color="C3", lw=1.5)
        handles[f"{_omega(relative)}(0)"] = ax.scatter(*w0, color="k", s=12)
        ax.set_title(f"trajectory {label}", fontsize=9)
        for axis, c in zip((ax.xaxis, ax.yaxis, ax.zaxis), _AXES, strict=True):
            axis.set_label_text(f"{_omega(relative, c)} [{rate}]")
            axis.set_major_locator(MaxNLocator(5))
        ax.zaxis.set_rotate_label(False)  # read upwards from either side
        ax.zaxis.label.set_rotation(90)
        _equal_axes_3d(ax, points)
        _open_view(ax, omega[k])
    fig.legend(
        list(handles.values()),
        list(handles),
        loc="outside lower center",
        ncols=len(handles),
        fontsize=8,
    )


def _draw_status(fig, status: np.ndarray, names: dict[int, str]) -> None:
    """Horizontal bars of the count per status code: the codes that occur, and 0 (successful)
    always; labelled with their `names`."""
    from matplotlib.ticker import MaxNLocator

    codes = sorted(set(status.tolist()) | {0})
    ax = fig.add_subplot()
    colors = ["C2" if c == 0 else "0.6" if c == -1 else "C3" for c in codes]
    bars = ax.barh(range(len(codes)), [int(np.sum(status == c)) for c in codes], color=colors)
    ax.bar_label(bars, padding=2)
    ax.set_yticks(range(len(codes)), [f"{names.get(c, 'code')} ({c})" for c in codes])
    ax.invert_yaxis()
    ax.set_xlabel("number of trajectories")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.margins(x=0.15)


def plots_dir(store: str | pathlib.Path) -> pathlib.Path:
    """The default folder of a store's plots (`rbdyn plot`): `<store>_plots` beside it."""
    store = pathlib.Path(store)
    return store.with_name(store.name + "_plots")


def plot_sweep(path, out_dir=None, *, n_sample: int = 8) -> list[pathlib.Path]:
    """Write PNG plots of the sweep dataset stored at `path`.

    **Arguments:**

    - `path`: the zarr store (v2 or v3) written by `rbdyn_jax.sweep` (opened with
      `xarray.open_zarr(path, consolidated=False)`).
    - `out_dir`: the folder to write into, created if needed; default `plots_dir(path)`,
      `<path>_plots` beside the store.
    - `n_sample`: how many successful trajectories (the first by index) to draw in
      `trajectories.png`; `polhodes.png` draws the first `min(4, n_sample)` of them.

    **Returns:** the paths written, in this order where present:

    - `summaries.png`: a histogram per summary named in the `summaries` attribute, over the
      successful trajectories with a finite value, each with its count, mean and standard deviation;
      skipped when the dataset has no summaries.
    - `trajectories.png`: ω_x, ω_y, ω_z, |ω| (in the `units` of `omega`) and the nutation
      angle θ (rad) against time (labelled from the `long_name` and `units` of `time`).
    - `polhodes.png`: ω(t) in 3-D on the ellipsoid ωᵀ J ω = ω(0)ᵀ J ω(0)
      (docs/physics.md#torque-free-motion), the three axes at equal scale; for a
      `relative_rigid_body` dataset, the hodograph of ω_r on the ellipsoid of the initial
      relative kinetic energy (docs/physics.md#balancing-transport-moment). Written only where
      that ellipsoid is invariant — a torque-free `rigid_body`, a `relative_rigid_body` under
      the balancing moment alone (read from the `model_kind` and `scenario` attributes);
      under any other torque ω leaves it, and `trajectories.png` shows |ω| and θ instead.
    - `status.png`: the number of trajectories per status code that occurs (and for 0, always),
      named from the `flag_meanings` of `status`.

    Axis labels carry the CF `long_name` and `units` of the variables; angles are in radians.
    When no trajectory succeeded only `status.png` is written. `trajectories.png` and
    `polhodes.png` draw the states the store keeps: of the first successful trajectories, or
    of the first successful sampled ones in a store keeping every K-th trajectory's states
    (`sampled_trajectory`); they are skipped for a store that keeps none.

    **Raises:** `ImportError` without matplotlib or xarray; `ValueError` if `n_sample < 1`.
    """
    try:
        import matplotlib  # noqa: F401  (used by `_new_figure`)
    except ImportError as e:
        raise ImportError("plot_sweep needs matplotlib: `pip install matplotlib`.") from e
    try:
        import xarray as xr
    except ImportError as e:
        raise ImportError("plot_sweep needs xarray and zarr: `pip install xarray zarr`.") from e
    if n_sample < 1:
        raise ValueError(f"`n_sample` must be at least 1, got {n_sample}.")

    path = pathlib.Path(path)
    out_dir = plots_dir(path) if out_dir is None else pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []

    def save(fig, name: str) -> None:
        fig.savefig(out_dir / name, dpi=100)
        written.append(out_dir / name)

    with xr.open_zarr(path, consolidated=False) as ds:
        ok = _successful(ds)
        prefix = f"{ds.attrs['scenario_name']}: " if ds.attrs.get("scenario_name") else ""
        relative = ds.attrs.get("model_kind") == "relative_rigid_body"

        if len(ok):
            names = str(ds.attrs.get("summaries", "")).split()
            names = [n for n in ([names] if isinstance(names, str) else names) if n in ds.data_vars]
            if names:
                rows, cols = _grid(len(names), 3)
                fig = _new_figure(
                    prefix + f"summaries of {len(ok)} successful trajectories", (4 * cols, 3 * rows)
                )
                _draw_summaries(fig, ds, ok, names)
                save(fig, "summaries.png")

        states = _stored_states(ds, ok, n_sample) if len(ok) else None
        if states is not None:
            labels, omega, quat, inertia, title = states
            time = np.asarray(ds["time"].values, dtype=float)
            fig = _new_figure(prefix + title, (9.5, 10))
            units = {k: ds[k].attrs for k in ("time", "omega")}
            _draw_trajectories(fig, time, omega, quat, labels, relative, units)
            save(fig, "trajectories.png")

            if _ellipsoid_is_invariant(ds.attrs):
                n_poly = min(4, len(labels))
                rows, cols = _grid(n_poly, 2)
                if relative:
                    title, surface = "hodograph of ω_r", r"$\omega_r^T J \omega_r = 2T_r(0)$"
                else:
                    title = "polhode on the energy ellipsoid"
                    surface = r"$\omega^T J \omega = 2T(0)$"
                fig = _new_figure(prefix + title, (5 * cols, 4.5 * rows + 0.4))
                _draw_polhodes(
                    fig,
                    omega[:n_poly],
                    inertia[:n_poly],
                    labels[:n_poly],
                    relative,
                    surface,
                    _units(ds["omega"].attrs, "rad/s"),
                )
                save(fig, "polhodes.png")

        status = np.asarray(ds["status"].values)
        status = status[np.isfinite(status)].astype(int)
        names = _status_names(ds["status"].attrs)
        n_codes = len(set(status.tolist()) | {0})
        title = prefix + f"status of {status.size} trajectories"
        fig = _new_figure(title, (7, max(3, 1.5 + 0.45 * n_codes)))
        _draw_status(fig, status, names)
        save(fig, "status.png")
    return written
