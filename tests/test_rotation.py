"""rbdyn_jax.rotation against independent references (docs/physics.md#conventions,
docs/physics.md#kinematics).

References: `scipy.spatial.transform.Rotation` / `Slerp` (an independent implementation of
the same conventions), the literal formulas of docs/physics.md#kinematics, and central finite
differences of explicit rotation paths built with scipy.
"""

import warnings

import equinox as eqx
import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import assert_quat_equal, skew
from hypothesis import given, settings
from jax.test_util import check_grads
from scipy.spatial.transform import Rotation, Slerp

from rbdyn_jax import rotation as rot

INTRINSIC = [a + b + c for a in "XYZ" for b in "XYZ" for c in "XYZ" if a != b and b != c]
SEQS = INTRINSIC + [s.lower() for s in INTRINSIC]
assert len(SEQS) == 24  # 12 sequences × {intrinsic, extrinsic}

# Identities evaluated with a handful of float64 operations on O(1) numbers.
TIGHT = 1e-12


def is_proper(seq):
    return seq[0].lower() == seq[2].lower()


def wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def scipy_euler(seq, angles):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # scipy's gimbal-lock warning
        return Rotation.from_euler(seq, angles)


def scipy_as_euler(r, seq):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return r.as_euler(seq)


# ------------------------------------------------------------------------------------------
# strategies: angles in scipy's ranges, the second one anywhere or within 1e-12..1e-2 of the
# singular set (and exactly on it)
# ------------------------------------------------------------------------------------------

_outer = st.floats(-np.pi, np.pi, allow_nan=False)
_offset = st.one_of(
    st.just(0.0),
    st.integers(-12, -2).map(lambda k: 10.0**k),
    st.floats(1e-12, 1e-2),
)


@st.composite
def angles_for(draw, seq, n=6):
    rows = []
    for _ in range(n):
        a, c = draw(_outer), draw(_outer)
        kind = draw(st.sampled_from(["regular", "near_low", "near_high"]))
        lo, hi = (0.0, np.pi) if is_proper(seq) else (-np.pi / 2, np.pi / 2)
        if kind == "regular":
            b = draw(st.floats(lo, hi))
        elif kind == "near_low":
            b = lo + draw(_offset)
        else:
            b = hi - draw(_offset)
        rows.append([a, b, c])
    return np.array(rows)


# ------------------------------------------------------------------------------------------
# Euler angles vs scipy
# ------------------------------------------------------------------------------------------


def _per_sequence(test):
    """Every sequence, each with its own hypothesis search over angles."""
    return pytest.mark.parametrize("seq", SEQS)(
        settings(max_examples=12, deadline=None)(given(data=st.data())(test))
    )


@_per_sequence
def test_euler_to_quat_matches_scipy(seq, data):
    angles = data.draw(angles_for(seq))
    q = rot.euler_to_quat(angles, seq)
    assert_quat_equal(q, scipy_euler(seq, angles).as_quat(scalar_first=True), atol=TIGHT)
    np.testing.assert_allclose(
        rot.euler_to_dcm(angles, seq), scipy_euler(seq, angles).as_matrix(), atol=TIGHT
    )


@pytest.mark.parametrize("seq", SEQS)
def test_gimbal_lock_error_bound_is_reached_at_the_threshold(seq):
    """The tolerance of the test below: a second angle δ just inside the 1e-7 threshold is
    locked, and dropping δ moves the matrix by up to 2δ, reached to within rounding
    (found by hypothesis in CI at the ZYX angles (0, π/2 − 1e-7, π); exactly at the
    threshold, rounding decides whether the angle is locked)."""
    lo, hi = (0.0, np.pi) if is_proper(seq) else (-np.pi / 2, np.pi / 2)
    d = rot.GIMBAL_LOCK_EPS * (1 - 1e-6)
    rng = np.random.default_rng(0)
    a, c = rng.uniform(-np.pi, np.pi, (2, 64))
    c[:2] = np.pi, -np.pi
    angles = np.concatenate(
        [np.stack([a, np.full(64, lo + d), c], 1), np.stack([a, np.full(64, hi - d), c], 1)]
    )
    r = scipy_euler(seq, angles)
    ours, locked = rot.quat_to_euler(r.as_quat(scalar_first=True), seq, return_gimbal_lock=True)
    assert np.all(np.asarray(locked))
    err = np.abs(np.asarray(rot.euler_to_dcm(ours, seq)) - r.as_matrix()).max(axis=(1, 2))
    assert np.all(err <= 2 * rot.GIMBAL_LOCK_EPS + TIGHT)  # the tolerance used below
    assert np.max(err) > 1.9 * d  # and it is tight: 2δ, not δ


@_per_sequence
def test_quat_to_euler_matches_scipy_including_gimbal_lock(seq, data):
    angles = data.draw(angles_for(seq))
    r = scipy_euler(seq, angles)
    q = r.as_quat(scalar_first=True)
    ours, locked = rot.quat_to_euler(q, seq, return_gimbal_lock=True)
    theirs = scipy_as_euler(r, seq)
    d = np.array(rot.gimbal_lock_distance(theirs, seq))
    # A second angle within rounding of the 1e-7 threshold may fall on either side in
    # either implementation: a tie, not a disagreement. Compare everything else.
    clear = np.abs(d - rot.GIMBAL_LOCK_EPS) > 1e-12
    # Same angles (mod 2π at the ±π seam), including scipy's gimbal-lock choice.
    np.testing.assert_allclose(wrap(np.asarray(ours) - theirs)[clear], 0.0, atol=TIGHT)
    # The mask is exactly scipy's warning condition: second angle within 1e-7 of singular.
    np.testing.assert_array_equal(np.asarray(locked)[clear], (d <= rot.GIMBAL_LOCK_EPS)[clear])
    # At gimbal lock the third angle is 0, as scipy documents.
    np.testing.assert_array_equal(np.asarray(ours)[np.asarray(locked), 2], 0.0)
    # Whatever the case, the angles represent the rotation; in gimbal lock only up to the
    # discarded second-angle offset δ ≤ 1e-7 rad, which moves a matrix entry by up to 2δ.
    # The bound is reached at the threshold itself (δ = 1e-7, a draw of the "near" kind
    # with offset 1e-7: measured 2e-7 plus one rounding), hence TIGHT on top of it.
    back = rot.euler_to_dcm(ours, seq)
    tol = np.where(np.asarray(locked), 2 * rot.GIMBAL_LOCK_EPS + TIGHT, TIGHT)[:, None, None]
    assert np.all(np.abs(np.asarray(back) - r.as_matrix()) <= tol)


@pytest.mark.parametrize("seq", SEQS)
def test_quat_to_euler_exact_half_turns_match_scipy(seq):
    """Half turns about each axis and pairs of axes: angles exactly ±π keep scipy's sign and
    the documented ranges (second angle in [0, π] proper, [−π/2, π/2] Tait–Bryan)."""
    q = np.array(
        [[0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [0, 1, 1, 0], [0, 0, 1, 1], [1, 0, 0, 0]], float
    )
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    ours = np.array(rot.quat_to_euler(q, seq))
    theirs = scipy_as_euler(Rotation.from_quat(q, scalar_first=True), seq)
    np.testing.assert_allclose(ours, theirs, atol=TIGHT)
    lo, hi = (0.0, np.pi) if is_proper(seq) else (-np.pi / 2, np.pi / 2)
    assert np.all((ours[:, 1] >= lo - TIGHT) & (ours[:, 1] <= hi + TIGHT))
    assert np.all(np.abs(ours) <= np.pi)


@pytest.mark.parametrize("seq", SEQS)
def test_euler_round_trip_in_scipy_ranges(seq, rng):
    angles = rng.uniform(-np.pi, np.pi, (50, 3))
    if is_proper(seq):
        angles[:, 1] = rng.uniform(1e-3, np.pi - 1e-3, 50)
    else:
        angles[:, 1] = rng.uniform(-np.pi / 2 + 1e-3, np.pi / 2 - 1e-3, 50)
    back, locked = rot.quat_to_euler(rot.euler_to_quat(angles, seq), seq, return_gimbal_lock=True)
    assert not np.any(locked)
    # Away from the singular set (≥ 1e-3 rad) the inverse is well conditioned.
    np.testing.assert_allclose(wrap(np.asarray(back) - angles), 0.0, atol=1e-11)
    back_dcm = rot.dcm_to_euler(rot.euler_to_dcm(angles, seq), seq)
    np.testing.assert_allclose(wrap(np.asarray(back_dcm) - angles), 0.0, atol=1e-11)


def test_intrinsic_is_reversed_extrinsic(rng):
    """Pars (1971), §7.14 (docs/physics.md#euler-angles): moving-axis rotations = fixed-axis
    ones in reverse order."""
    angles = rng.uniform(-np.pi, np.pi, (20, 3))
    for seq in INTRINSIC:
        q_int = rot.euler_to_quat(angles, seq)
        q_ext = rot.euler_to_quat(angles[:, ::-1], seq[::-1].lower())
        assert_quat_equal(q_int, q_ext, atol=TIGHT)


def test_classical_zxz_matrix():
    """The classical angles: R = Rz(ψ) Rx(θ) Rz(φ) written out by hand
    (docs/physics.md#euler-angles)."""
    psi, theta, phi = 0.7, 1.1, -2.3

    def Rz(a):
        return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])

    def Rx(a):
        return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])

    expected = Rz(psi) @ Rx(theta) @ Rz(phi)
    np.testing.assert_allclose(
        rot.euler_to_dcm(jnp.array([psi, theta, phi]), "ZXZ"), expected, atol=TIGHT
    )


# ------------------------------------------------------------------------------------------
# quaternion algebra, DCM, rotation vectors, slerp vs scipy
# ------------------------------------------------------------------------------------------


def special_rotations():
    """Rotations where naive formulas break: identity, π about each axis and diagonals,
    angles within 1e-9 of π, tiny angles."""
    axes = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, -1, 1], [0, 1, -1]], float)
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.array([0.0, 1e-12, 1e-7, np.pi - 1e-9, np.pi])
    return Rotation.from_rotvec((angles[:, None, None] * axes[None]).reshape(-1, 3))


def test_quat_dcm_against_scipy(rng):
    r = Rotation.concatenate([Rotation.random(200, random_state=rng), special_rotations()])
    q = r.as_quat(scalar_first=True)
    np.testing.assert_allclose(rot.quat_to_dcm(q), r.as_matrix(), atol=TIGHT)
    assert_quat_equal(rot.dcm_to_quat(r.as_matrix()), q, atol=TIGHT)
    # quat ↔ DCM round trip, and the homogeneous form ignores the norm of q.
    assert_quat_equal(rot.dcm_to_quat(rot.quat_to_dcm(q)), q, atol=TIGHT)
    np.testing.assert_allclose(rot.quat_to_dcm(3.0 * q), r.as_matrix(), atol=TIGHT)
    R = np.array(rot.quat_to_dcm(q))
    np.testing.assert_allclose(
        R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=TIGHT
    )
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=TIGHT)


def test_multiply_rotate_conjugate_against_scipy(rng):
    r1 = Rotation.random(100, random_state=rng)
    r2 = Rotation.random(100, random_state=rng)
    q1, q2 = r1.as_quat(scalar_first=True), r2.as_quat(scalar_first=True)
    assert_quat_equal(rot.quat_multiply(q1, q2), (r1 * r2).as_quat(scalar_first=True), atol=TIGHT)
    np.testing.assert_allclose(
        rot.quat_to_dcm(rot.quat_multiply(q1, q2)), r1.as_matrix() @ r2.as_matrix(), atol=TIGHT
    )
    v = rng.normal(size=(100, 3))
    np.testing.assert_allclose(rot.quat_rotate(q1, v), r1.apply(v), atol=TIGHT)
    assert_quat_equal(rot.quat_conjugate(q1), r1.inv().as_quat(scalar_first=True), atol=TIGHT)
    ident = rot.quat_multiply(q1, rot.quat_conjugate(q1))
    np.testing.assert_allclose(ident, np.broadcast_to([1.0, 0, 0, 0], ident.shape), atol=TIGHT)
    # broadcasting of one quaternion against a batch
    np.testing.assert_allclose(rot.quat_rotate(q1[0], v), r1[0].apply(v), atol=TIGHT)


def test_normalize(rng):
    q = rng.normal(size=(10, 4))
    qn = np.array(rot.quat_normalize(q))
    np.testing.assert_allclose(np.linalg.norm(qn, axis=-1), 1.0, atol=TIGHT)
    np.testing.assert_allclose(qn * np.linalg.norm(q, axis=-1, keepdims=True), q, atol=TIGHT)


def test_rotvec_against_scipy(rng):
    r = Rotation.concatenate([Rotation.random(200, random_state=rng), special_rotations()])
    rv = r.as_rotvec()
    assert_quat_equal(rot.quat_from_rotvec(rv), r.as_quat(scalar_first=True), atol=TIGHT)
    q = r.as_quat(scalar_first=True)
    ours = np.array(rot.quat_to_rotvec(q))
    # At angle exactly π, v and −v are the same rotation; compare as rotations there.
    np.testing.assert_allclose(Rotation.from_rotvec(ours).as_matrix(), r.as_matrix(), atol=TIGHT)
    regular = np.linalg.norm(rv, axis=-1) < np.pi - 1e-6
    np.testing.assert_allclose(ours[regular], rv[regular], atol=TIGHT)
    assert np.all(np.linalg.norm(ours, axis=-1) <= np.pi + TIGHT)
    # Sign invariance: q and −q give the same rotation vector (shorter rotation).
    np.testing.assert_allclose(rot.quat_to_rotvec(-q[regular]), rv[regular], atol=TIGHT)


def test_rotvec_taylor_branch_is_continuous():
    """Values just below and above the Taylor threshold agree to rounding."""
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    for angle in [0.0, 1e-14, 1e-8, 0.999e-6, 1.001e-6, 1e-4]:
        v = angle * axis
        ref = Rotation.from_rotvec(v).as_quat(scalar_first=True)
        np.testing.assert_allclose(rot.quat_from_rotvec(v), ref, atol=1e-15)
        np.testing.assert_allclose(rot.quat_to_rotvec(ref), v, atol=1e-15)


def test_slerp_against_scipy(rng):
    r = Rotation.random(2, random_state=rng)
    t = np.linspace(0.0, 1.0, 11)
    ref = Slerp([0.0, 1.0], r)(t).as_quat(scalar_first=True)
    q0, q1 = r.as_quat(scalar_first=True)
    ours = rot.slerp(q0, q1, t)
    assert_quat_equal(ours, ref, atol=TIGHT)
    # Shorter arc whatever the sign of q1; constant angular speed.
    assert_quat_equal(rot.slerp(q0, -q1, t), ref, atol=TIGHT)
    steps = (
        Rotation.from_quat(np.asarray(ours)[1:], scalar_first=True)
        * Rotation.from_quat(np.asarray(ours)[:-1], scalar_first=True).inv()
    )
    np.testing.assert_allclose(steps.magnitude(), steps.magnitude()[0], atol=TIGHT)


# ------------------------------------------------------------------------------------------
# kinematics: finite differences of explicit rotation paths (scipy-built)
# ------------------------------------------------------------------------------------------

# Central differences with h = 1e-5 on O(1) smooth paths: truncation ~h² f''' ≈ 1e-10,
# rounding ~eps/h ≈ 1e-11, so 1e-8 leaves a wide margin yet catches any sign error (O(1)).
H = 1e-5
FD_TOL = 1e-8


def path_angles(t, coeffs, seq):
    """Smooth angles a0 + a1 t + a2 t², the second kept away from gimbal lock."""
    a = coeffs[0] + coeffs[1] * t + coeffs[2] * t**2
    rate = coeffs[1] + 2 * coeffs[2] * t
    return a, rate


def random_coeffs(rng, seq):
    c = rng.uniform(-1, 1, (3, 3))
    c[0, 1] = rng.uniform(0.5, 2.5) if is_proper(seq) else rng.uniform(-1.0, 1.0)
    c[1:, 1] *= 0.1  # second angle stays within ~0.2 rad of its start
    return c


@pytest.mark.parametrize("seq", SEQS)
def test_euler_rates_match_rotation_path(seq, rng):
    """d/dt R(angles(t)) = R [ω]× with ω = euler_rates_to_omega(angles, rates)."""
    for _ in range(3):
        c = random_coeffs(rng, seq)
        t = 0.3
        a, rate = path_angles(t, c, seq)
        R = scipy_euler(seq, a).as_matrix()
        R_dot = (
            scipy_euler(seq, path_angles(t + H, c, seq)[0]).as_matrix()
            - scipy_euler(seq, path_angles(t - H, c, seq)[0]).as_matrix()
        ) / (2 * H)
        omega = np.array(rot.euler_rates_to_omega(a, rate, seq))
        np.testing.assert_allclose(R.T @ R_dot, skew(omega), atol=FD_TOL)
        # The other kinematic forms, consistent with the same path:
        np.testing.assert_allclose(rot.omega_from_dcm(R, R_dot), omega, atol=FD_TOL)
        np.testing.assert_allclose(rot.dcm_derivative(R, omega), R_dot, atol=FD_TOL)
        # inverse map recovers the rates
        np.testing.assert_allclose(rot.omega_to_euler_rates(a, omega, seq), rate, atol=1e-11)

        # quaternion form: q' = ½ q ⊗ (0, ω), along a sign-continuous scipy path
        q = scipy_euler(seq, a).as_quat(scalar_first=True)
        qp = scipy_euler(seq, path_angles(t + H, c, seq)[0]).as_quat(scalar_first=True)
        qm = scipy_euler(seq, path_angles(t - H, c, seq)[0]).as_quat(scalar_first=True)
        qp *= np.sign(qp @ q)
        qm *= np.sign(qm @ q)
        np.testing.assert_allclose(rot.quat_derivative(q, omega), (qp - qm) / (2 * H), atol=FD_TOL)

        # Poisson: γ = body components of a parent-fixed unit vector, γ' = γ × ω
        e = np.array([0.0, 0.0, 1.0])
        gamma = R.T @ e
        gamma_dot = (
            scipy_euler(seq, path_angles(t + H, c, seq)[0]).as_matrix().T @ e
            - scipy_euler(seq, path_angles(t - H, c, seq)[0]).as_matrix().T @ e
        ) / (2 * H)
        np.testing.assert_allclose(rot.poisson(gamma, omega), gamma_dot, atol=FD_TOL)


def test_zxz_literal_formulas(rng):
    """docs/physics.md#euler-angle-rates written out literally (Lecture notes (2016),
    Def. 1.2; Mukhametzyanov (2009), eq. (13); Zinkevich & Kozachenko (2008), eq. (1);
    Shinibaev et al. (2013), eqs. (1), (4))."""
    psi, theta, phi = rng.uniform(-3, 3, 20), rng.uniform(0.05, 3.0, 20), rng.uniform(-3, 3, 20)
    dpsi, dtheta, dphi = rng.normal(size=(3, 20))
    angles = np.stack([psi, theta, phi], -1)
    omega = np.array(rot.euler_rates_to_omega(angles, np.stack([dpsi, dtheta, dphi], -1), "ZXZ"))
    p = dpsi * np.sin(theta) * np.sin(phi) + dtheta * np.cos(phi)
    q = dpsi * np.sin(theta) * np.cos(phi) - dtheta * np.sin(phi)
    r = dpsi * np.cos(theta) + dphi
    np.testing.assert_allclose(omega, np.stack([p, q, r], -1), atol=TIGHT)

    rates = np.array(rot.omega_to_euler_rates(angles, omega, "ZXZ"))
    s = p * np.sin(phi) + q * np.cos(phi)
    expected = np.stack(
        [s / np.sin(theta), p * np.cos(phi) - q * np.sin(phi), r - s / np.tan(theta)], -1
    )
    # 1/sinθ ≤ 20 amplifies rounding: 1e-11.
    np.testing.assert_allclose(rates, expected, atol=1e-11)

    # Shinibaev et al. (2013), eq. (4): body components of the parent z-axis, and
    # ψ' = (pγ + qγ')/(1 − γ''²)
    gamma = np.einsum("nji,j->ni", np.array(rot.euler_to_dcm(angles, "ZXZ")), [0, 0, 1.0])
    np.testing.assert_allclose(
        gamma,
        np.stack([np.sin(theta) * np.sin(phi), np.sin(theta) * np.cos(phi), np.cos(theta)], -1),
        atol=TIGHT,
    )
    np.testing.assert_allclose(
        (p * gamma[:, 0] + q * gamma[:, 1]) / (1 - gamma[:, 2] ** 2), dpsi, atol=1e-10
    )


def test_zyz_pars_formula(rng):
    """Pars (7.16.1), angles (φ, θ, ψ) in intrinsic ZYZ."""
    phi, theta, psi = rng.uniform(-3, 3, (3, 20))
    dphi, dtheta, dpsi = rng.normal(size=(3, 20))
    omega = rot.euler_rates_to_omega(
        np.stack([phi, theta, psi], -1), np.stack([dphi, dtheta, dpsi], -1), "ZYZ"
    )
    w1 = dtheta * np.sin(psi) - dphi * np.sin(theta) * np.cos(psi)
    w2 = dtheta * np.cos(psi) + dphi * np.sin(theta) * np.sin(psi)
    w3 = dphi * np.cos(theta) + dpsi
    np.testing.assert_allclose(omega, np.stack([w1, w2, w3], -1), atol=TIGHT)


@pytest.mark.parametrize("seq", SEQS)
def test_gimbal_lock_distance_is_the_singularity_of_the_rate_map(seq, rng):
    """|det ∂ω/∂(rates)| = sin(distance): the distance vanishes exactly where the map
    loses rank (the 'paradox' of Pars (1971), §7.16)."""
    angles = rng.uniform(-np.pi, np.pi, (30, 3))
    jac = jax.vmap(jax.jacobian(lambda a, r: rot.euler_rates_to_omega(a, r, seq), argnums=1))(
        angles, np.zeros_like(angles)
    )
    d = np.array(rot.gimbal_lock_distance(angles, seq))
    assert np.all((d >= 0) & (d <= np.pi / 2 + TIGHT))
    np.testing.assert_allclose(np.abs(np.linalg.det(np.asarray(jac))), np.sin(d), atol=TIGHT)


def test_singular_rate_map_non_finite_only_at_singular_set():
    omega = jnp.array([0.1, 0.2, 0.3])
    # exactly singular: θ = 0 for ZXZ (sinθ = 0 is exact in floating point)
    assert not np.all(
        np.isfinite(rot.omega_to_euler_rates(jnp.array([0.3, 0.0, 0.2]), omega, "ZXZ"))
    )
    dist = np.array([1e-9, 1e-6, 1e-3, 0.5])
    for seq in SEQS:
        beta = dist if is_proper(seq) else np.pi / 2 - dist
        a = np.stack([np.full(4, 0.3), beta, np.full(4, -0.4)], -1)
        w = np.broadcast_to(omega, a.shape)
        assert np.all(np.isfinite(rot.omega_to_euler_rates(a, w, seq)))
        jac = jax.vmap(
            jax.jacobian(lambda x, y, s=seq: rot.omega_to_euler_rates(x, y, s), argnums=(0, 1))
        )
        assert all(np.all(np.isfinite(x)) for x in jac(a, w))


# ------------------------------------------------------------------------------------------
# jit, vmap and grad of every public function
# ------------------------------------------------------------------------------------------


def _q(rng, *shape):
    return (
        Rotation.random(int(np.prod(shape)), random_state=rng)
        .as_quat(scalar_first=True)
        .reshape(*shape, 4)
    )


def public_calls(rng):
    """(name, function of array args, args) for every public function; generic points."""
    q, q2 = _q(rng, 2, 3), _q(rng, 2, 3)
    v = rng.normal(size=(2, 3, 3))
    ang = rng.uniform(0.3, 1.2, (2, 3, 3))
    R = np.array(rot.quat_to_dcm(q))
    return [
        ("quat_multiply", rot.quat_multiply, (q, q2)),
        ("quat_conjugate", rot.quat_conjugate, (q,)),
        ("quat_normalize", rot.quat_normalize, (2.0 * q,)),
        ("quat_rotate", rot.quat_rotate, (q, v)),
        ("quat_to_dcm", rot.quat_to_dcm, (q,)),
        ("dcm_to_quat", rot.dcm_to_quat, (R,)),
        ("quat_from_rotvec", rot.quat_from_rotvec, (v,)),
        ("quat_to_rotvec", rot.quat_to_rotvec, (q,)),
        ("slerp", rot.slerp, (q, q2, ang[..., 0])),
        ("euler_to_quat", lambda a: rot.euler_to_quat(a, "ZXZ"), (ang,)),
        ("euler_to_quat_xyz", lambda a: rot.euler_to_quat(a, "xyz"), (ang,)),
        ("quat_to_euler", lambda x: rot.quat_to_euler(x, "ZXZ"), (q,)),
        ("quat_to_euler_YXZ", lambda x: rot.quat_to_euler(x, "YXZ"), (q,)),
        ("euler_rates_to_omega", lambda a, r: rot.euler_rates_to_omega(a, r, "ZYZ"), (ang, v)),
        ("omega_to_euler_rates", lambda a, w: rot.omega_to_euler_rates(a, w, "zyx"), (ang, v)),
        ("gimbal_lock_distance", lambda a: rot.gimbal_lock_distance(a, "ZXZ"), (ang,)),
        ("quat_derivative", rot.quat_derivative, (q, v)),
        ("dcm_derivative", rot.dcm_derivative, (R, v)),
        ("omega_from_dcm", rot.omega_from_dcm, (R, np.array(rot.dcm_derivative(R, v)))),
        ("poisson", rot.poisson, (v, v[::-1])),
        ("skew", rot.skew, (v,)),
        ("vee", rot.vee, (R,)),
    ]


def test_jit_and_vmap_equal_eager_loop(rng):
    for name, f, args in public_calls(rng):
        eager = np.asarray(f(*args))
        fj = jax.jit(f)
        np.testing.assert_allclose(fj(*args), eager, atol=1e-14, err_msg=name)
        vm = jax.vmap(jax.vmap(f))(*args)
        loop = np.stack(
            [
                np.stack(
                    [np.asarray(fj(*(a[i, j] for a in args))) for j in range(args[0].shape[1])]
                )
                for i in range(args[0].shape[0])
            ]
        )
        np.testing.assert_allclose(vm, loop, atol=1e-14, err_msg=name)
        np.testing.assert_allclose(eager, loop, atol=1e-14, err_msg=name)


def test_grads_against_finite_differences(rng):
    """Forward and reverse derivatives against central differences (check_grads)."""
    for name, f, args in public_calls(rng):
        one = tuple(np.asarray(a)[0, 0] for a in args)
        if name in ("gimbal_lock_distance",):
            one = (one[0] + np.array([0.0, 0.3, 0.0]),)  # away from its |.| kink
        check_grads(f, one, order=1, modes=("fwd", "rev"), atol=1e-6, rtol=1e-6, eps=1e-6)


def _finite_grad(f, x):
    g = jax.jacobian(f)(jnp.asarray(x))
    return np.all(np.isfinite(np.asarray(g)))


def test_grads_at_singular_points():
    """Rotation angle 0 and π, θ at and near 0: gradients finite (double `where` and Taylor
    series in the singular branches)."""
    # exp map at 0: dq/dv = [0; ½ I]
    np.testing.assert_allclose(
        jax.jacobian(rot.quat_from_rotvec)(jnp.zeros(3)),
        np.vstack([np.zeros(3), 0.5 * np.eye(3)]),
        atol=TIGHT,
    )
    # log map at identity: dv/d(x, y, z) = 2 I
    np.testing.assert_allclose(
        jax.jacobian(rot.quat_to_rotvec)(jnp.array([1.0, 0, 0, 0]))[:, 1:],
        2 * np.eye(3),
        atol=TIGHT,
    )
    for x in [
        [0.0, 1.0, 0.0, 0.0],  # angle π
        [1e-9, 0.6, 0.8, 0.0],  # just below π
        [np.cos(5e-7), np.sin(5e-7), 0.0, 0.0],  # at the Taylor threshold
    ]:
        assert _finite_grad(rot.quat_to_rotvec, x)
    assert _finite_grad(rot.quat_from_rotvec, [np.pi, 0.0, 0.0])
    assert _finite_grad(rot.quat_from_rotvec, [1e-7, -1e-8, 0.0])
    for seq in SEQS:
        base = 0.0 if is_proper(seq) else np.pi / 2
        for off in [0.0, 1e-9, 1e-4]:
            q = scipy_euler(seq, [0.3, base + off, 0.2]).as_quat(scalar_first=True)
            assert _finite_grad(lambda x, s=seq: rot.quat_to_euler(x, s), q)
    assert _finite_grad(lambda q: rot.slerp(q, q, 0.5), [1.0, 0.0, 0.0, 0.0])
    assert _finite_grad(
        lambda t: rot.slerp(jnp.array([1.0, 0, 0, 0]), jnp.array([0.0, 1, 0, 0]), t), 0.5
    )


# ------------------------------------------------------------------------------------------
# bad input
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seq", ["ZZX", "XYY", "XYz", "ABC", "XY", "XYZX", "", 3])
def test_bad_sequence_is_a_value_error(seq):
    with pytest.raises(ValueError, match="`seq`"):
        rot.euler_to_quat(jnp.zeros(3), seq)
    with pytest.raises(ValueError, match="`seq`"):
        rot.quat_to_euler(jnp.array([1.0, 0, 0, 0]), seq)
    with pytest.raises(ValueError, match="`seq`"):
        rot.euler_rates_to_omega(jnp.zeros(3), jnp.zeros(3), seq)


def test_wrong_shapes_name_the_argument():
    with pytest.raises(ValueError, match="`q`"):
        rot.quat_to_dcm(jnp.zeros(3))
    with pytest.raises(ValueError, match="`q2`"):
        rot.quat_multiply(jnp.ones(4), jnp.ones((2, 3)))
    with pytest.raises(ValueError, match="`R`"):
        rot.dcm_to_quat(jnp.eye(4))
    with pytest.raises(ValueError, match="`angles`"):
        rot.euler_to_quat(jnp.zeros((5, 2)), "ZXZ")
    with pytest.raises(ValueError, match="`omega`"):
        rot.quat_derivative(jnp.ones(4), jnp.ones(4))
    with pytest.raises(ValueError, match="`rotvec`"):
        rot.quat_from_rotvec(jnp.ones(2))


def test_zero_quaternion_is_a_runtime_error():
    for f in (
        rot.quat_normalize,
        rot.quat_to_rotvec,
        lambda q: rot.quat_to_euler(q, "ZXZ"),
        jax.jit(rot.quat_normalize),
    ):
        # eqx.EquinoxRuntimeError eagerly; under a bare jax.jit, JAX's runtime error.
        with pytest.raises(
            (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError), match="zero quaternion"
        ):
            jax.block_until_ready(f(jnp.zeros((2, 4))))


def test_dtype_is_preserved():
    """float32 in, float32 out: the library never forces float64 (it leaves JAX's global
    switch to the caller)."""
    q = jnp.array([1.0, 0.0, 0.0, 0.0], dtype=jnp.float32)
    assert rot.quat_to_dcm(q).dtype == jnp.float32
    assert rot.quat_to_euler(q, "ZXZ").dtype == jnp.float32
    assert rot.quat_from_rotvec(jnp.zeros(3, jnp.float32)).dtype == jnp.float32
