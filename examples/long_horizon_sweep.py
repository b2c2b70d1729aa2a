"""Long horizons: a Monte Carlo sweep of heavy tops with the structure-preserving splitting.

See the physics guide, docs/physics.md#geometric-integration.

A heavy top (the benchmarks' inertia J with products of inertia, weight 1 at r_c = (0, 0,
0.5)) is swept over dispersed initial rates for a long time, twice: with the splitting
`LiePoissonSplitting` of order 6 at a fixed step (`[solver] method = "LiePoissonSplitting"`,
`dt`), and with diffrax's Tsit5 at the default tolerance rtol = atol = 1e-8. Each sweep
stores every trajectory's states and its `energy_drift` (the largest relative error of the
energy ½ωᵀJω + m g r_c·γ over the output times). The energy error of the splitting stays at
the size its step gives it for as long as the sweep runs; Tsit5's grows with time. The
script prints both sweeps' energy drifts and wall times, and plots the energy error against
time for one top and the drifts of all of them.

Run: `python examples/long_horizon_sweep.py` (writes results/examples/long_horizon_sweep.png;
`--n`, `--t-end`, `--dt` set the sweep's size, horizon and the splitting's step).
"""

import argparse
import pathlib
import tempfile
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import rbdyn_jax as rb  # noqa: E402
from rbdyn_jax import sweep  # noqa: E402
from rbdyn_jax.scenario import Scenario  # noqa: E402

J = [[2.0, 0.05, 0.0], [0.05, 3.0, 0.02], [0.0, 0.02, 4.0]]


def scenario(t_end: float, n_out: int, solver: dict) -> Scenario:
    """The heavy-top scenario with the `[solver]` table `solver` (the TOML of the tutorial,
    as a dict)."""
    return Scenario.from_dict(
        {
            "name": "heavy_top_long",
            "description": "Heavy top over a long horizon",
            "model": {
                "kind": "rigid_body",
                "inertia": {"matrix": J},
                "torques": [{"kind": "uniform_gravity", "weight": 1.0, "com": [0.0, 0.0, 0.5]}],
            },
            "initial": {
                "omega": {"dist": "normal", "mean": [0.8, 0.1, 0.6], "std": 0.05},
                "attitude": {"euler": [0.3, 0.7, 0.2], "seq": "ZXZ"},
            },
            "time": {"t1": t_end, "n": n_out},
            "solver": solver,
            "outputs": {"summaries": ["energy_drift", "max_nutation"]},
        }
    )


def run(sc: Scenario, n: int, folder: pathlib.Path, name: str):
    """Sweep `n` trajectories of `sc` into `folder/name.zarr`; the store's arrays and the
    wall time (the first chunk's compilation included). On a CPU a sweep solves blocks of 8
    × `lanes` trajectories per device, padding the last: `lanes` is chosen so that one
    block per device holds the sweep."""
    lanes = max(1, -(-n // (8 * jax.device_count())))
    t0 = time.perf_counter()
    out = sweep.run(sc, n, folder / f"{name}.zarr", seed=0, lanes=lanes)
    wall = time.perf_counter() - t0
    ds = sweep.open_dataset(out)
    return {
        k: ds[k].values for k in ("omega", "quat", "inertia", "status", "num_steps", "energy_drift")
    }, wall


def energy_error(sc: Scenario, store: dict, i: int) -> np.ndarray:
    """|E(t)/E0 − 1| of trajectory `i` from its stored states."""
    model = rb.RigidBody(
        jnp.asarray(store["inertia"][i]), rb.UniformGravity(1.0, jnp.array([0.0, 0.0, 0.5]))
    )
    traj = rb.Trajectory(
        ts=jnp.asarray(sc.ts),
        ys=rb.State(jnp.asarray(store["omega"][i]), jnp.asarray(store["quat"][i])),
        stats={},
        result=rb.RESULTS.successful,
    )
    E = np.asarray(rb.invariants.energy(model, traj))
    return np.abs(E / E[0] - 1.0)


def main(
    n: int = 32,
    t_end: float = 5_000.0,
    dt: float = 0.2,
    n_out: int = 2001,
    out_dir: str = "results/examples",
) -> dict:
    splitting = scenario(t_end, n_out, {"method": "LiePoissonSplitting", "order": 6, "dt": dt})
    adaptive = scenario(
        t_end, n_out, {"method": "Tsit5", "rtol": 1e-8, "atol": 1e-8, "max_steps": 1 << 24}
    )
    with tempfile.TemporaryDirectory() as tmp:
        folder = pathlib.Path(tmp)
        split_store, split_wall = run(splitting, n, folder, "splitting")
        tsit_store, tsit_wall = run(adaptive, n, folder, "tsit5")
    assert np.all(split_store["status"] == 0) and np.all(tsit_store["status"] == 0)
    summary = {
        "splitting_max_energy_drift": float(split_store["energy_drift"].max()),
        "tsit5_max_energy_drift": float(tsit_store["energy_drift"].max()),
        "splitting_steps": float(split_store["num_steps"].mean()),
        "tsit5_mean_steps": float(tsit_store["num_steps"].mean()),
        "splitting_wall_s": split_wall,
        "tsit5_wall_s": tsit_wall,
    }
    e_split = energy_error(splitting, split_store, 0)
    e_tsit = energy_error(adaptive, tsit_store, 0)
    # The splitting's error is the same at the start and at the end; Tsit5's grows.
    quarter = len(e_split) // 4
    summary["splitting_late_over_early"] = float(
        e_split[-quarter:].max() / e_split[1:quarter].max()
    )
    summary["tsit5_late_over_early"] = float(e_tsit[-quarter:].max() / e_tsit[1:quarter].max())
    print(
        f"{n} heavy tops to t = {t_end:g} ({n_out} output times), energy drift "
        "max |E/E0 − 1| over the outputs:"
    )
    print(
        f"  LiePoissonSplitting(6), dt = {dt:g}: {summary['splitting_steps']:.0f} steps, "
        f"median {np.median(split_store['energy_drift']):.1e}, largest "
        f"{summary['splitting_max_energy_drift']:.1e}; {split_wall:.1f} s"
    )
    print(
        f"  Tsit5, rtol = atol = 1e-8: {summary['tsit5_mean_steps']:.0f} steps on average, "
        f"median {np.median(tsit_store['energy_drift']):.1e}, largest "
        f"{summary['tsit5_max_energy_drift']:.1e}; {tsit_wall:.1f} s"
    )
    print(
        "  largest error over the last quarter ÷ over the first, top 0: splitting "
        f"{summary['splitting_late_over_early']:.2f}, "
        f"Tsit5 {summary['tsit5_late_over_early']:.1f}"
    )

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.5), layout="constrained")
    ts = splitting.ts
    ax1.loglog(ts[1:], e_tsit[1:], lw=0.8, label="Tsit5, rtol = 1e-8")
    ax1.loglog(ts[1:], e_split[1:], lw=0.8, label=f"LiePoissonSplitting(6), dt = {dt:g}")
    ax1.set_xlabel("t")
    ax1.set_ylabel("|E/E0 − 1|")
    ax1.set_title("Energy error of one top")
    ax1.legend()
    ax1.grid(True, which="both", alpha=0.3)
    bins = np.logspace(
        np.log10(min(split_store["energy_drift"].min(), tsit_store["energy_drift"].min())) - 0.2,
        np.log10(max(split_store["energy_drift"].max(), tsit_store["energy_drift"].max())) + 0.2,
        40,
    )
    ax2.hist(tsit_store["energy_drift"], bins=bins, alpha=0.7, label="Tsit5, rtol = 1e-8")
    ax2.hist(
        split_store["energy_drift"],
        bins=bins,
        alpha=0.7,
        label=f"LiePoissonSplitting(6), dt = {dt:g}",
    )
    ax2.set_xscale("log")
    ax2.set_xlabel(f"energy drift over t ≤ {t_end:g}")
    ax2.set_ylabel("tops")
    ax2.set_title(f"Energy drift of the {n} tops of each sweep")
    ax2.legend()
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "long_horizon_sweep.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    print(f"wrote {path}")
    return summary


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=32, help="trajectories per sweep (32)")
    p.add_argument("--t-end", type=float, default=5_000.0, help="horizon (5000)")
    p.add_argument("--dt", type=float, default=0.2, help="the splitting's step (0.2)")
    p.add_argument("--out-dir", default="results/examples", help="output folder")
    args = p.parse_args()
    main(n=args.n, t_end=args.t_end, dt=args.dt, out_dir=args.out_dir)
