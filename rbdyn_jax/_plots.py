"""PNG plots of a Monte Carlo sweep dataset (the zarr store written by `rbdyn_jax.sweep`).

`plot_sweep` reads the store with xarray and writes four figures: histograms of the per-trajectory
summaries, sample time histories of the body rates and nutation angle, sample polhodes on their
kinetic-energy ellipsoids (docs/physics.md#torque-free-motion; hodographs of ω_r for relative
motion, docs/physics.md#balancing-transport-moment), and the counts per status code. Only
successful trajectories (`status == 0`) enter the first three. The time histories and polhodes
are drawn from the states the store keeps: every trajectory's, every K-th one's (over
`sampled_trajectory`), or none (a summaries-only store: those two figures are skipped).

matplotlib and xarray are imported inside `plot_sweep`, so this module imports without them.
Figures are built as `matplotlib.figure.Figure` on an Agg canvas, never through `pyplot`, so no
global backend is switched and no figure is left open in pyplot's registry.
"""

import math
import pathlib

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


def _nutation_deg(quat: np.ndarray) -> np.ndarray:
    """Nutation angle θ in degrees — the angle between the body z axis and the parent z axis — of
    unit quaternions `quat[..., 4]` (`[w, x, y, z]`, body → parent): cos θ = R₃₃ = 1 − 2(x² + y²).
    """
    x, y = quat[..., 1], quat[..., 2]
    return np.degrees(np.arccos(np.clip(1.0 - 2.0 * (x**2 + y**2), -1.0, 1.0)))


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


def _status_names(attrs) -> dict[int, str]:
    """`{code: name}` from the CF attributes `flag_values` and `flag_meanings` of `status`."""
    if "flag_values" not in attrs or "flag_meanings" not in attrs:
        return {}
    return dict(zip((int(c) for c in np.ravel(attrs["flag_values"])),
                    str(attrs["flag_meanings"]).split()))


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


def _draw_summaries(fig, ds, ok: np.ndarray, names: list[str]) -> None:
    """One histogram per summary in `names` over the successful, finite values, with n/mean/std."""
    rows, cols = _grid(len(names), 3)
    for i, name in enumerate(names):
        ax = fig.add_subplot(rows, cols, i + 1)
        values = np.asarray(ds[name].values, dtype=float)[ok]
        values = values[np.isfinite(values)]
        ax.set_title(name)
        if values.size:
            counts, _, _ = ax.hist(values, bins=min(30, max(5, int(np.sqrt(values.size)))))
            ax.set_ylim(0, 1.4 * counts.max())  # headroom for the text
            std = values.std(ddof=1) if values.size > 1 else 0.0
            text = f"n = {values.size}\nmean = {values.mean():.4g}\nstd = {std:.4g}"
        else:
            text = "no finite values"
        box = {"facecolor": "white", "alpha": 0.8, "lw": 0}
        ax.text(
            0.97, 0.95, text, transform=ax.transAxes, ha="right", va="top", fontsize=8, bbox=box
        )


def _draw_trajectories(fig, time, omega, quat, labels, relative: bool) -> None:
    """ω_x, ω_y, ω_z and the nutation angle against time, one line per sampled trajectory."""
    axes = fig.subplots(4, 1, sharex=True)
    for k, label in enumerate(labels):
        for i in range(3):
            axes[i].plot(time, omega[k, :, i], lw=1, label=f"trajectory {label}")
        axes[3].plot(time, _nutation_deg(quat[k]), lw=1)
    for i, c in enumerate(_AXES):
        axes[i].set_ylabel(f"{_omega(relative, c)} [rad/s]")
    axes[3].set_ylabel(r"nutation $\theta$ [deg]")
    axes[3].set_xlabel("time [s]")
    axes[0].legend(fontsize=7, ncols=min(len(labels), 4), loc="upper right")


def _draw_polhodes(fig, omega, inertia, labels, relative: bool, surface: str) -> None:
    """3-D curves ω(t) of the first (up to 4) trajectories, each on its ellipsoid
    ωᵀ J ω = ω(0)ᵀ J ω(0) (drawn only where J is positive definite and the energy positive)."""
    rows, cols = _grid(len(labels), 2)
    for k, label in enumerate(labels):
        ax = fig.add_subplot(rows, cols, k + 1, projection="3d")
        w0, J = omega[k, 0], inertia[k]
        energy = 0.5 * w0 @ J @ w0
        if np.all(np.isfinite(J)) and np.isfinite(energy) and energy > 0:
            if np.all(np.linalg.eigvalsh(J) > 0):
                grid = _energy_ellipsoid(J, energy)
                ax.plot_wireframe(*grid, color="0.75", lw=0.4, label=surface)
        ax.plot(*omega[k].T, color="C3", lw=1.5, label=f"{_omega(relative)}(t)")
        ax.scatter(*w0, color="k", s=12, label=f"{_omega(relative)}(0)")
        ax.set_title(f"trajectory {label}", fontsize=9)
        ax.set_xlabel(_omega(relative, "x"))
        ax.set_ylabel(_omega(relative, "y"))
        ax.set_zlabel(_omega(relative, "z"))
        ax.set_aspect("equal")
        ax.set_box_aspect(None, zoom=0.85)  # room for the z label
        if k == 0:
            ax.legend(fontsize=7, loc="upper left")


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
    ax.set_xlabel("trajectories")
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
    - `trajectories.png`: ω_x, ω_y, ω_z (rad/s) and the nutation angle θ (deg) against time.
    - `polhodes.png`: ω(t) in 3-D on the ellipsoid ωᵀ J ω = ω(0)ᵀ J ω(0)
      (docs/physics.md#torque-free-motion); for a `relative_rigid_body` dataset, the
      hodograph of ω_r on the ellipsoid of the initial relative kinetic energy
      (docs/physics.md#balancing-transport-moment: conserved only when the transport moment
      is balanced).
    - `status.png`: the number of trajectories per status code that occurs (and for 0, always),
      named from the `flag_meanings` of `status`.

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
            fig = _new_figure(prefix + title, (8, 9))
            _draw_trajectories(fig, time, omega, quat, labels, relative)
            save(fig, "trajectories.png")

            n_poly = min(4, len(labels))
            rows, cols = _grid(n_poly, 2)
            if relative:
                title, surface = (
                    "hodograph of ω_r",
                    "ellipsoid of the initial relative kinetic energy",
                )
            else:
                title, surface = "polhode on the energy ellipsoid", "energy ellipsoid"
            fig = _new_figure(prefix + title, (5 * cols, 4.5 * rows))
            _draw_polhodes(
                fig, omega[:n_poly], inertia[:n_poly], labels[:n_poly], relative, surface
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
