"""A Lagrange top under a slowly varying restoring moment, against its averaged motion
(Zinkevich & Kozachenko (2008); docs/physics.md#restoring-moment).

A dynamically symmetric top (A = B, C) spins fast about its axis, r0 = 1, under the restoring
moment k(τ, ψ) sinθ (cos φ, −sin φ, 0) with k = ε K(τ) sin ψ, K(τ) = 1 + 0.5 τ, τ = ε t, plus a
small constant body-fixed moment M = ε² M* (the perturbation of Zinkevich & Kozachenko (2008),
eq. (3)). The full equations are integrated in the paper's form, eq. (1) — Euler's equations
with ZXZ angles (`EulerAngleRigidBody`) — over t ∈ [0, 1/ε] from p0 = q0 = 0 (the axis released
without precession, so the fast nutation is fully excited), and compared with the averaged
solutions of `rbdyn_jax.analytic`:

- first approximation: θ = θ0, r = r0 + M3 t / C, tan(ψ/2) = tan(ψ0/2) exp(F1(τ)); its error
  is the O(ε) nutation (amplitude ~ A k / (C r0)²) plus the O(ε) drift of the mean motion;
- second approximation: the fast nutation and the O(ε) mean corrections, error O(ε²).

The paper's assumptions (its eq. (2)) hold: sqrt(p² + q²) ≲ 2k/(C r0) ≪ r, C r0² = 1.5 ≫ k ≤ 1.5 ε,
|M| = O(ε²) ≪ k. Measured at ε = 0.02 (ε = 0.01): first approximation max|Δψ| 8.8e-3
(4.2e-3), max|Δθ| 1.5e-2 (7.3e-3) — O(ε), the θ error being the nutation, which swings
between θ0 and θ0 + 2·(its amplitude) rather than about θ0; second approximation max|Δψ|
1.2e-3 (3.0e-4), max|Δθ| 8.2e-4 (2.0e-4) — O(ε²). The second approximation takes
M1 = M2 = 0: the body-fixed M1, M2 average out over the spin but shift the nutation by
O(ε²); without them its errors are 2.6e-4 and 2.0e-4 (≈ 0.6 ε²).

Run: `python examples/lagrange_top.py` (writes results/examples/lagrange_top.png).
"""

import argparse
import pathlib

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import rbdyn_jax as rb  # noqa: E402

K_COEFFS = (1.0, 0.5)  # K(τ) = 1 + 0.5 τ
M_STAR = (0.5, -0.3, 1.0)  # M = ε² M*, body axes


def K(tau):
    """K(τ) = Σ K_COEFFS[i] τ^i, the same polynomial as `PolynomialSinPsi(K_COEFFS, ε)`."""
    return sum(c * tau**i for i, c in enumerate(K_COEFFS))


def main(eps: float = 0.02, n_out: int = 2001, out_dir: str = "results/examples") -> dict:
    A, C = 1.0, 1.5
    r0, psi0, theta0, phi0 = 1.0, 1.0, 0.8, 0.3
    M = eps**2 * np.asarray(M_STAR)
    torque = rb.RestoringMoment(rb.PolynomialSinPsi(jnp.array(K_COEFFS), eps)) + rb.BodyTorque(
        jnp.asarray(M)
    )
    model = rb.EulerAngleRigidBody(jnp.diag(jnp.array([A, A, C])), torque)
    y0 = rb.EulerState(omega=jnp.array([0.0, 0.0, r0]), angles=jnp.array([psi0, theta0, phi0]))
    ts = jnp.linspace(0.0, 1.0 / eps, n_out)
    traj = rb.simulate(model, y0, ts, rtol=1e-11, atol=1e-11)
    psi, theta, _ = np.asarray(traj.ys.angles).T
    r = np.asarray(traj.ys.omega)[:, 2]

    top = dict(A=A, C=C, r0=r0, psi0=psi0, theta0=theta0, eps=eps, K=K, M3=float(M[2]))
    first = [np.asarray(x) for x in rb.analytic.lagrange_top_first_approximation(ts, **top)]
    second = [
        np.asarray(x)
        for x in rb.analytic.lagrange_top_second_approximation(ts, **top, phi0=phi0, p0=0.0, q0=0.0)
    ]
    err = lambda a, b: float(np.max(np.abs(a - b)))  # noqa: E731
    summary = {
        "eps": eps,
        "psi_change": float(psi[-1] - psi[0]),
        "psi_error_first": err(psi, first[0]),
        "theta_error_first": err(theta, first[1]),
        "r_error_first": err(r, first[2]),
        "psi_error_second": err(psi, second[0]),
        "theta_error_second": err(theta, second[1]),
        "nutation_amplitude": float(np.max(theta) - np.min(theta)) / 2,
    }
    print(
        f"ε = {eps:g}, t ∈ [0, {1 / eps:g}]: ψ advances by {summary['psi_change']:.4f} rad, "
        f"nutation half-amplitude {summary['nutation_amplitude']:.2e} rad"
    )
    print(
        f"first approximation:  max|Δψ| = {summary['psi_error_first']:.2e}, "
        f"max|Δθ| = {summary['theta_error_first']:.2e}, max|Δr| = {summary['r_error_first']:.1e}"
        f"   (O(ε) = {eps:.0e})"
    )
    print(
        f"second approximation: max|Δψ| = {summary['psi_error_second']:.2e}, "
        f"max|Δθ| = {summary['theta_error_second']:.2e}   (O(ε²) = {eps**2:.0e})"
    )

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.asarray(ts)
    fig, axes = plt.subplots(2, 2, figsize=(12, 7), sharex=True, layout="constrained")
    style_1 = dict(color="k", linestyle="--", linewidth=1.0, label="first approximation")
    style_2 = dict(color="C1", linestyle=":", linewidth=1.2, label="second approximation")
    ax = axes[0, 0]
    ax.plot(t, psi, color="C0", linewidth=1.0, label="simulated")
    ax.plot(t, first[0], **style_1)
    ax.plot(t, second[0], **style_2)
    ax.set_ylabel("ψ [rad]")
    ax.set_title("precession ψ: tan(ψ/2) = tan(ψ0/2) exp(F1(τ))")
    ax = axes[0, 1]
    ax.plot(t, theta, color="C0", linewidth=0.8, label="simulated")
    ax.plot(t, first[1], **style_1)
    ax.plot(t, second[1], **style_2)
    ax.set_ylabel("θ [rad]")
    ax.set_title("nutation θ: from rest, between θ0 and θ0 + 2a")
    ax = axes[1, 0]
    ax.plot(t, r, color="C0", linewidth=1.0, label="simulated")
    ax.plot(t, first[2], **style_1)
    ax.set_ylabel("r [rad/s]")
    ax.set_xlabel("t [s]")
    ax.set_title(f"spin r = r0 + M3 t / C (max error {summary['r_error_first']:.0e} rad/s)")
    # one legend for the three solution panels, above them
    fig.legend(
        *axes[0, 0].get_legend_handles_labels(), loc="outside upper center", ncols=3, fontsize=8
    )
    ax = axes[1, 1]
    ax.semilogy(t, np.abs(psi - first[0]) + 1e-16, color="k", linewidth=0.7, label="|ψ − ψ first|")
    ax.semilogy(
        t, np.abs(theta - first[1]) + 1e-16, color="0.6", linewidth=0.7, label="|θ − θ first|"
    )
    ax.semilogy(
        t, np.abs(psi - second[0]) + 1e-16, color="C1", linewidth=0.7, label="|ψ − ψ second|"
    )
    ax.semilogy(
        t, np.abs(theta - second[1]) + 1e-16, color="C3", linewidth=0.7, label="|θ − θ second|"
    )
    ax.axhline(eps, color="k", linestyle="--", linewidth=0.6)
    ax.axhline(eps**2, color="C1", linestyle="--", linewidth=0.6)
    ax.set_ylim(1e-8, 1.0)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("absolute error [rad]")
    ax.set_title(f"errors (dashed: ε = {eps:g}, ε²)")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # beside the axes
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fig.savefig(out / "lagrange_top.png", dpi=110)
    plt.close(fig)
    print(f"wrote {out / 'lagrange_top.png'}")
    return summary


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--eps", type=float, default=0.02)
    p.add_argument("--out-dir", default="results/examples")
    args = p.parse_args()
    main(eps=args.eps, out_dir=args.out_dir)
