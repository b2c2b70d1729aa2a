"""Transport frames (`rbdyn_jax.frames`) against independent references.

See docs/physics.md#transport-frame and docs/physics.md#circular-orbit.

References that cannot be wrong in the same way as the library: central finite differences
of the frame's own attitude, `R_eᵀ R_e' = [ω_e¹]×`, scipy's `from_euler` / `from_rotvec`,
and for a ZXZ frame the literal kinematic formula of docs/physics.md#euler-angle-rates
(Mukhametzyanov (2009), eq. (14)).

Finite differences use central steps h with truncation error ~h²·|f'''| and rounding
~1e-16/h (h = 1e-5 ⇒ both ≲ 1e-10).
"""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    FD_H,
    FD_TOL,
    FRAME_C,
    TIGHT,
    PolyAngles,
    assert_quat_equal,
    frame_omega1,
    frame_rot,
    np_angles,
    np_rates,
    random_quat,
    scipy_rot,
    skew,
    xyzw_to_wxyz,
    zxz_omega,
)
from scipy.spatial.transform import Rotation

import rbdyn_jax as rb

# Jitted evaluation (one compile per frame structure, shared across tests) is much faster
# than eager op-by-op dispatch of the nested `jvp`s (as `helpers.eval_kinematics`).
# (Python floats would be static under `filter_jit`: times are converted to arrays first.)
_eval_frame = eqx.filter_jit(lambda frame, t: frame(t))


def eval_frame(frame, t):
    return _eval_frame(frame, jnp.asarray(t, dtype=jnp.float64))


# ------------------------------------------------------------------------------------------
# Transport frames
# ------------------------------------------------------------------------------------------


def _check_frame_derivatives(frame, times):
    """R_eᵀ dR_e/dt = [ω_e¹]× and ε_e¹ = dω_e¹/dt, both by central FD of the frame itself."""
    for t in times:
        t = float(t)
        q, w1, e1 = eval_frame(frame, t)
        R = np.asarray(rb.rotation.quat_to_dcm(q))
        dR = (
            np.asarray(rb.rotation.quat_to_dcm(eval_frame(frame, t + FD_H)[0]))
            - np.asarray(rb.rotation.quat_to_dcm(eval_frame(frame, t - FD_H)[0]))
        ) / (2 * FD_H)
        np.testing.assert_allclose(R.T @ dR, skew(np.asarray(w1)), atol=FD_TOL)
        dw = (
            np.asarray(eval_frame(frame, t + FD_H)[1]) - np.asarray(eval_frame(frame, t - FD_H)[1])
        ) / (2 * FD_H)
        np.testing.assert_allclose(e1, dw, atol=FD_TOL)


@pytest.mark.parametrize("seq", ["ZXZ", "XYZ", "zyx"])
def test_euler_angle_frame(seq, rng):
    angles = PolyAngles(jnp.asarray(FRAME_C))
    frame = rb.EulerAngleFrame(angles, seq=seq)
    ts = [0.0, 0.7, 2.9]
    _check_frame_derivatives(frame, ts)
    for t in ts:
        q, w1, _ = eval_frame(frame, t)
        assert_quat_equal(q, xyzw_to_wxyz(frame_rot(FRAME_C, seq, t).as_quat()), atol=TIGHT)
        # ω_e¹ against an independent FD of scipy's attitude
        np.testing.assert_allclose(w1, frame_omega1(FRAME_C, seq, t), atol=FD_TOL)
    # A ZXZ frame also matches the literal formula: Mukhametzyanov (2009), eq. (14);
    # docs/physics.md#euler-angle-frames
    if seq == "ZXZ":
        t = 1.1
        np.testing.assert_allclose(
            eval_frame(frame, t)[1],
            zxz_omega(np_angles(FRAME_C, t), np_rates(FRAME_C, t)),
            atol=TIGHT,
        )
    # Zero angles at t = 0 ⇒ identity; quat0 pre-multiplies and leaves ω_e¹, ε_e¹ unchanged.
    c0 = FRAME_C.copy()
    c0[1, 0] = 0.0
    q, _, _ = rb.EulerAngleFrame(PolyAngles(jnp.asarray(c0)), seq=seq)(jnp.asarray(0.0))
    assert_quat_equal(q, [1.0, 0.0, 0.0, 0.0], atol=TIGHT)
    q0 = random_quat(rng)
    framed = rb.EulerAngleFrame(angles, seq=seq, quat0=jnp.asarray(q0))
    for t in ts:
        qa, wa, ea = eval_frame(framed, t)
        qb, wb, eb = eval_frame(frame, t)
        assert_quat_equal(
            qa, xyzw_to_wxyz((scipy_rot(q0) * frame_rot(FRAME_C, seq, t)).as_quat()), atol=TIGHT
        )
        np.testing.assert_allclose(wa, wb, atol=TIGHT)
        np.testing.assert_allclose(ea, eb, atol=TIGHT)


def test_constant_rate_frame(rng):
    w_e = rng.normal(size=3)
    frame = rb.ConstantRate(w_e)
    q, w1, e1 = eval_frame(frame, 0.0)
    assert_quat_equal(q, [1.0, 0.0, 0.0, 0.0], atol=TIGHT)
    ts = [0.0, 0.4, 3.3]
    _check_frame_derivatives(frame, ts)
    q0 = random_quat(rng)
    framed = rb.ConstantRate(w_e, quat0=q0)
    assert_quat_equal(eval_frame(framed, 0.0)[0], q0, atol=TIGHT)
    for t in ts:
        q, w1, e1 = eval_frame(frame, t)
        assert_quat_equal(q, xyzw_to_wxyz(Rotation.from_rotvec(w_e * t).as_quat()), atol=TIGHT)
        np.testing.assert_allclose(w1, w_e, atol=TIGHT)
        np.testing.assert_allclose(e1, 0.0, atol=0)
        assert_quat_equal(
            eval_frame(framed, t)[0],
            xyzw_to_wxyz((scipy_rot(q0) * Rotation.from_rotvec(w_e * t)).as_quat()),
            atol=TIGHT,
        )


def test_circular_orbit_frame():
    """docs/physics.md#circular-orbit (LVLH): ω_e¹ = (0, −n, 0); the nadir z1 turns about the
    orbit normal −y1 at rate n; the satellite r = −z1 moves along x1, and r × v = n (−y1)."""
    n = 0.63
    frame = rb.CircularOrbit(n)
    assert_quat_equal(eval_frame(frame, 0.0)[0], [1.0, 0.0, 0.0, 0.0], atol=TIGHT)
    ts = np.linspace(0.0, 2 * np.pi / n, 7)
    _check_frame_derivatives(frame, ts)

    def axes(t):
        return np.asarray(rb.rotation.quat_to_dcm(eval_frame(frame, t)[0]))  # columns x1 y1 z1

    normal = -axes(0.0)[:, 1]
    for t in ts:
        _, w1, e1 = eval_frame(frame, t)
        np.testing.assert_allclose(w1, [0.0, -n, 0.0], atol=TIGHT)
        np.testing.assert_allclose(e1, 0.0, atol=0)
        R = axes(t)
        np.testing.assert_allclose(-R[:, 1], normal, atol=TIGHT)  # the normal is fixed
        np.testing.assert_allclose(R[:, 2], [-np.sin(n * t), 0.0, np.cos(n * t)], atol=TIGHT)
        r = -R[:, 2]
        v = -(axes(t + FD_H)[:, 2] - axes(t - FD_H)[:, 2]) / (2 * FD_H)
        np.testing.assert_allclose(v, n * R[:, 0], atol=FD_TOL)  # along-track
        np.testing.assert_allclose(np.cross(r, v), n * normal, atol=FD_TOL)


@pytest.mark.parametrize("seq", ["ZZX", "XYz", "XY", "XYZW", "ABC"])
def test_euler_angle_frame_bad_seq(seq):
    with pytest.raises(ValueError, match="`seq`"):
        rb.EulerAngleFrame(PolyAngles(jnp.asarray(FRAME_C)), seq=seq)
