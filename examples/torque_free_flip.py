"""Torque-free asymmetric body: the intermediate-axis flip and the polhode.

See the physics guide, docs/physics.md#torque-free-motion.

A body with principal moments A < B < C is spun almost about its intermediate axis. The
angular velocity in the body follows a polhode — the intersection of the energy ellipsoid
ωᵀJω = 2T with the momentum sphere |Jω| = |L| — which passes near the separatrix, so the
body flips over again and again. The simulated ω(t) is compared with the Jacobi elliptic
solution (`rbdyn_jax.analytic.torque_free_elliptic`), and T and the inertial L are checked.
The inertia tensor has products of inertia (principal axes rotated in the body); the
reference works in principal axes.

Run: `python examples/torque_free_flip.py` (writes results/examples/torque_free_flip.png).
"""

import argparse
import pathlib

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import rbdyn_jax as rb  # noqa: E402


def main(t_end: float = 120.0, n_out: int = 2401, out_dir: str = "results/examples") -> dict:
    moments = jnp.array([1.0, 2.0, 3.0])
    C = rb.rotation.euler_to_dcm(jnp.array([0.4, 0.9, -0.3]), "ZXZ")  # principal axes
    J = rb.inertia.from_principal(moments, C)
    omega_p0 = jnp.array([0.02, 1.5, 0.03])  # near the intermediate axis, principal frame
    y0 = rb.State(omega=C @ omega_p0, quat=jnp.array([1.0, 0.0, 0.0, 0.0]))
    ts = jnp.linspace(0.0, t_end, n_out)
    model = rb.RigidBody(J)
    traj = rb.simulate(model, y0, ts, rtol=1e-10, atol=1e-10)
    w_principal = np.asarray(traj.ys.omega) @ np.asarray(C)  # Cᵀ ω for each time
    w_ref = np.asarray(rb.analytic.torque_free_elliptic(moments, omega_p0, ts))
    T = np.asarray(rb.invariants.kinetic_energy(model, traj))
    L = np.asarray(rb.invariants.angular_momentum_inertial(model, traj))
    flips = int(np.sum(np.diff(np.sign(w_principal[:, 1])) != 0))
    summary = {
        "max_error_vs_elliptic": float(np.max(np.abs(w_principal - w_ref))),
        "energy_drift": float(np.max(np.abs(T - T[0])) / T[0]),
        "momentum_drift": float(np.max(np.linalg.norm(L - L[:1], axis=-1)) / np.linalg.norm(L[0])),
        "flips": flips,
    }
    print(f"flips of the intermediate axis: {flips}")
    print(
        f"max |ω − ω_elliptic| = {summary['max_error_vs_elliptic']:.2e} rad/s "
        f"(rtol = atol = 1e-10, t ≤ {t_end:g})"
    )
    print(f"energy drift {summary['energy_drift']:.1e}, |L| drift {summary['momentum_drift']:.1e}")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(12, 4.8), layout="constrained")
    fig.get_layout_engine().set(wspace=0.12)  # room for the 3-D axes' z label
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    u, v = np.mgrid[0 : 2 * np.pi : 40j, 0 : np.pi : 20j]
    a, b, c = (np.sqrt(2 * T[0] / m) for m in np.asarray(moments))
    ax.plot_wireframe(
        a * np.cos(u) * np.sin(v),
        b * np.sin(u) * np.sin(v),
        c * np.cos(v),
        color="0.8",
        linewidth=0.4,
    )
    ax.plot(*w_principal.T, color="C3", linewidth=1.0)
    ax.set(xlim=(-a, a), ylim=(-b, b), zlim=(-c, c))
    ax.set_box_aspect((a, b, c), zoom=0.85)  # equal scale on p, q, r: the ellipsoid's shape
    ax.locator_params(nbins=5)  # tick labels apart
    ax.set_title("polhode on the energy ellipsoid ωᵀJω = 2T")
    ax.set_xlabel("p [rad/s]")
    ax.set_ylabel("q [rad/s]")
    ax.set_zlabel("r [rad/s]")
    ax2 = fig.add_subplot(1, 2, 2)
    for k, name in enumerate("pqr"):
        ax2.plot(np.asarray(ts), w_principal[:, k], color=f"C{k}", label=f"{name} simulated")
        ax2.plot(np.asarray(ts)[::40], w_ref[::40, k], "k.", markersize=2)
    ax2.plot([], [], "k.", label="Jacobi elliptic")
    ax2.set_xlabel("t [s]")
    ax2.set_ylabel("ω in principal axes [rad/s]")
    ax2.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # beside the axes
    plural = "s" if flips != 1 else ""
    ax2.set_title(f"{flips} flip{plural}; max error {summary['max_error_vs_elliptic']:.1e} rad/s")
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fig.savefig(out / "torque_free_flip.png", dpi=110)
    plt.close(fig)
    print(f"wrote {out / 'torque_free_flip.png'}")
    return summary


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--t-end", type=float, default=120.0)
    p.add_argument("--out-dir", default="results/examples")
    args = p.parse_args()
    main(t_end=args.t_end, out_dir=args.out_dir)
