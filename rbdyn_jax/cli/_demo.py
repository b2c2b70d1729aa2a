"""`rbdyn demo` (the shipped default body, one trajectory, printed) and `rbdyn scenarios`
(the shipped scenarios, read from their files: no JAX)."""

import time


def scenarios_command() -> int:
    """Print each shipped scenario's name and description (read from the files: no JAX)."""
    from .._catalogue import catalogue

    for name, description in catalogue().items():
        print(f"{name:28s} {description}")
    return 0


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


def demo(n_steps: int = 5, duration: float = 100.0) -> int:
    """`rbdyn demo`: the default body's inertia, and its flips about the intermediate axis
    over `duration` seconds, ω printed at `n_steps` + 1 times."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    from .. import inertia, rotation

    t0 = time.perf_counter()
    masses, positions = _default_body()
    com = (masses[:, None] * positions).sum(0) / masses.sum()
    J = inertia.from_point_masses(masses, positions, about=com)
    moments, axes = inertia.principal_axes(J)
    Jp = inertia.planar(J)
    print("rbdyn demo: the default body (6 point masses, about its centre of mass)")
    print(f"  mass {masses.sum():.3f} kg, centre of mass {np.round(com, 4)} m")
    print("  inertia tensor J [kg m²] (docs/physics.md#inertia-tensor):")
    for row in np.asarray(J):
        print("    " + "  ".join(f"{x:+.5f}" for x in row))
    A, B, C = np.asarray(moments)
    print(f"  principal moments A ≤ B ≤ C: {A:.5f}, {B:.5f}, {C:.5f}")
    print(
        f"  planar moments A', B', C':    {(B + C - A) / 2:.5f}, {(C + A - B) / 2:.5f}, "
        f"{(A + B - C) / 2:.5f}  (eig J' = {np.round(np.linalg.eigvalsh(Jp), 5)})"
    )
    print(f"  physically consistent: {bool(inertia.is_physical(J))}")
    angles = rotation.dcm_to_euler(axes, "ZXZ")
    print(f"  principal frame as ZXZ angles (ψ, θ, φ) [deg]: {np.round(np.degrees(angles), 3)}")

    # The default scenario: torque-free spin started 1° off the intermediate principal axis,
    # which flips again and again (Euler–Poinsot, docs/physics.md#torque-free-motion),
    # solved with diffrax.
    from .. import invariants
    from ..integrate import RESULTS, simulate
    from ..models import RigidBody
    from ..state import State

    tilt = np.radians(1.0)
    omega0 = 2.0 * (np.cos(tilt) * axes[:, 1] + np.sin(tilt) * axes[:, 0])
    body = RigidBody(J)
    y0 = State(omega=jnp.asarray(omega0), quat=rotation.dcm_to_quat(axes))
    ts = jnp.linspace(0.0, duration, n_steps * 100 + 1)
    t1 = time.perf_counter()
    traj = simulate(body, y0, ts, rtol=1e-10, atol=1e-10)
    jax.block_until_ready(traj)
    t_first = time.perf_counter() - t1
    t1 = time.perf_counter()
    jax.block_until_ready(simulate(body, y0, ts, rtol=1e-10, atol=1e-10))
    t_again = time.perf_counter() - t1
    T = np.asarray(invariants.kinetic_energy(body, traj))
    L = np.asarray(invariants.angular_momentum_inertial(body, traj))
    along_b = np.asarray(traj.ys.omega) @ np.asarray(axes[:, 1])
    flips = int(np.sum(np.diff(np.sign(along_b)) != 0))
    print(
        f"\n  torque-free spin |ω| = 2 rad/s, 1° off the intermediate axis, t ∈ [0, {duration:g}] s"
    )
    print(
        f"    result: {RESULTS[traj.result] or 'successful'}, "
        f"{int(traj.stats['num_steps'])} steps (Tsit5, rtol = atol = 1e-10)"
    )
    print(f"    intermediate-axis flips: {flips}")
    print(f"    energy drift max|T − T0|/T0:       {np.max(np.abs(T - T[0])) / T[0]:.2e}")
    print(
        f"    momentum drift max|L − L0|/|L0|:   "
        f"{np.max(np.linalg.norm(L - L[:1], axis=-1)) / np.linalg.norm(L[0]):.2e}"
    )
    print(f"    quaternion norm drift removed:     {float(traj.stats['norm_drift']):.2e}")
    print(f"    time: first call {t_first:.2f} s (with compilation), again {t_again * 1e3:.1f} ms")
    for t, w in zip(np.asarray(ts)[::100], np.asarray(traj.ys.omega)[::100]):
        print(f"    t = {t:7.2f} s   ω_body = ({w[0]:+.4f}, {w[1]:+.4f}, {w[2]:+.4f}) rad/s")
    print(f"done in {time.perf_counter() - t0:.2f} s")
    return 0
