"""The `rbdyn` command (the only layer that prints or parses files; DESIGN.md).

`rbdyn demo` is the main job for now: the shipped default body — a rigid cloud of point
masses with products of inertia — its inertia, principal axes and planar moments
(PHYSICS.md §3), and a short steady rotation about its major axis propagated exactly by
the quaternion exponential map, with the first integrals it must keep (PHYSICS.md §4).
Later issues grow this into the Monte Carlo sweep and the identification demo.
"""

import argparse
import sys
import time


def _default_body():
    """Point masses (kg) and positions (m) of the shipped default body."""
    import numpy as np

    masses = np.array([2.0, 1.5, 1.0, 1.0, 0.5, 0.8])
    positions = np.array(
        [
            [0.30, 0.10, 0.00],
            [-0.20, 0.25, 0.05],
            [0.00, -0.30, 0.10],
            [-0.10, -0.05, -0.25],
            [0.15, 0.05, 0.30],
            [-0.05, 0.20, -0.15],
        ]
    )
    return masses, positions


def demo(n_steps: int = 5, duration: float = 10.0) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    from . import inertia, rotation

    t0 = time.perf_counter()
    masses, positions = _default_body()
    com = (masses[:, None] * positions).sum(0) / masses.sum()
    J = inertia.from_point_masses(masses, positions, about=com)
    moments, axes = inertia.principal_axes(J)
    Jp = inertia.planar(J)
    print("rbdyn demo: the default body (6 point masses, about its centre of mass)")
    print(f"  mass {masses.sum():.3f} kg, centre of mass {np.round(com, 4)} m")
    print("  inertia tensor J [kg m²] (PHYSICS.md §3):")
    for row in np.asarray(J):
        print("    " + "  ".join(f"{x:+.5f}" for x in row))
    A, B, C = np.asarray(moments)
    print(f"  principal moments A ≤ B ≤ C: {A:.5f}, {B:.5f}, {C:.5f}")
    print(f"  planar moments A', B', C':    {(B + C - A) / 2:.5f}, {(C + A - B) / 2:.5f}, "
          f"{(A + B - C) / 2:.5f}  (eig J' = {np.round(np.linalg.eigvalsh(Jp), 5)})")
    print(f"  physically consistent: {bool(inertia.is_physical(J))}")
    angles = rotation.dcm_to_euler(axes, "ZXZ")
    print(f"  principal frame as ZXZ angles (ψ, θ, φ) [deg]: {np.round(np.degrees(angles), 3)}")

    # Steady rotation about the major axis is an exact torque-free motion (PHYSICS.md §4):
    # ω constant in the body, q(t) = q0 ⊗ exp(ω t). Its integrals: T and L_inertial.
    omega = 2.0 * axes[:, 2]
    q0 = rotation.dcm_to_quat(axes)
    ts = jnp.linspace(0.0, duration, n_steps + 1)
    qs = rotation.quat_multiply(q0, rotation.quat_from_rotvec(ts[:, None] * omega[None, :]))
    L_inertial = rotation.quat_rotate(qs, inertia.angular_momentum(J, omega))
    T = inertia.kinetic_energy(J, omega)
    print(f"\n  steady spin |ω| = 2 rad/s about the major axis for {duration:g} s:")
    print("      t [s]   ψ, θ, φ [deg]                      |L_inertial − L(0)|")
    eul = np.degrees(np.asarray(rotation.quat_to_euler(qs, "ZXZ")))
    for t, e, L in zip(np.asarray(ts), eul, np.asarray(L_inertial)):
        drift = np.linalg.norm(L - np.asarray(L_inertial[0]))
        print(f"    {t:7.2f}   {e[0]:9.3f} {e[1]:9.3f} {e[2]:9.3f}        {drift:.2e}")
    print(f"  kinetic energy T = {float(T):.6f} J, |L| = {float(jnp.linalg.norm(L_inertial[0])):.6f}")
    print(f"done in {time.perf_counter() - t0:.2f} s")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="rbdyn", description="Rotational dynamics of rigid bodies in JAX."
    )
    sub = parser.add_subparsers(dest="command", required=True)
    p_demo = sub.add_parser("demo", help="summarise and spin the shipped default body")
    p_demo.add_argument("--steps", type=int, default=5, help="output steps (default 5)")
    p_demo.add_argument("--duration", type=float, default=10.0, help="seconds (default 10)")
    args = parser.parse_args(argv)
    if args.command == "demo":
        if args.steps < 1:
            parser.error("--steps must be ≥ 1")
        return demo(args.steps, args.duration)
    return 2  # unreachable: argparse rejects unknown commands


if __name__ == "__main__":
    sys.exit(main())
