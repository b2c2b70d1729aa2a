"""`rbdyn_jax._vector`, the written-out vector helpers shared by rotation, dynamics, torques
and frames, against NumPy (`np.cross`, `J @ v`) and the Euler-sequence rules of
`scipy.spatial.transform.Rotation`.

Tolerances: each component is two or three float64 products and sums of O(1) numbers, so
agreement with NumPy to 1e-14 is rounding; a wrong index or sign is O(1).
"""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rbdyn_jax import _vector


def test_written_out_products_match_numpy(rng):
    """The component-wise `J v` and `a × b` (dynamics and the torques use them) against numpy
    on a batch of non-symmetric matrices and vectors: a wrong index or sign in the
    written-out arithmetic shows at round-off level."""
    M = rng.normal(size=(5, 3, 3))
    a, b = rng.normal(size=(2, 5, 3))
    np.testing.assert_allclose(
        _vector.matvec(jnp.asarray(M), jnp.asarray(a)),
        np.einsum("nij,nj->ni", M, a),
        rtol=1e-14,
        atol=1e-14,
    )
    np.testing.assert_allclose(
        _vector.cross(jnp.asarray(a), jnp.asarray(b)), np.cross(a, b), rtol=1e-14, atol=1e-14
    )


def test_parts_are_the_components_of_the_products(rng):
    """`split`, `cross_parts` and `matvec_parts` work on the components (last axis) and give
    the components of `J @ v` and `np.cross`, also for a single vector and a 4-vector."""
    J = rng.normal(size=(3, 3))
    a, b = rng.normal(size=(2, 3))
    q = rng.normal(size=(7, 4))
    parts = _vector.split(jnp.asarray(q))
    assert len(parts) == 4 and all(p.shape == (7,) for p in parts)
    np.testing.assert_array_equal(np.stack(parts, axis=-1), q)
    Jv = _vector.matvec_parts(jnp.asarray(J), _vector.split(jnp.asarray(a)))
    np.testing.assert_allclose(np.stack(Jv), J @ a, rtol=1e-14, atol=1e-14)
    axb = _vector.cross_parts(_vector.split(jnp.asarray(a)), _vector.split(jnp.asarray(b)))
    np.testing.assert_allclose(np.stack(axb), np.cross(a, b), rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(
        _vector.matvec(jnp.asarray(J), jnp.asarray(a)), J @ a, rtol=1e-14, atol=1e-14
    )
    np.testing.assert_allclose(
        _vector.cross(jnp.asarray(a), jnp.asarray(b)), np.cross(a, b), rtol=1e-14, atol=1e-14
    )


def test_products_stay_elementwise():
    """The reason they are written out: no `dot_general` (XLA:CPU's slow batched-matmul
    library call), only elementwise arithmetic, in the program of `matvec` and `cross`."""
    J, v = jnp.ones((8, 3, 3)), jnp.ones((8, 3))
    for f in (_vector.matvec, _vector.cross):
        args = (J, v) if f is _vector.matvec else (v, v)
        names = {e.primitive.name for e in jax.make_jaxpr(f)(*args).jaxpr.eqns}
        assert "dot_general" not in names, (f.__name__, names)


@pytest.mark.parametrize("extrinsic", [False, True])
def test_parse_seq_accepts_scipy_sequences(extrinsic):
    """The 12 sequences scipy accepts (no axis repeated consecutively), upper case intrinsic
    and lower case extrinsic, with their axis indices."""
    valid = [
        "".join(s) for s in itertools.product("xyz", repeat=3) if s[0] != s[1] and s[1] != s[2]
    ]
    assert len(valid) == 12
    for seq in valid:
        seq = seq if extrinsic else seq.upper()
        Rotation.from_euler(seq, [0.1, 0.2, 0.3])  # scipy accepts it too
        axes, is_extrinsic = _vector.parse_seq(seq)
        assert axes == ["xyz".index(c) for c in seq.lower()] and is_extrinsic == extrinsic


@pytest.mark.parametrize("seq", ["ZZX", "XYz", "XY", "XYZW", "ABC", "xxy", 3])
def test_parse_seq_refuses_bad_sequences(seq):
    with pytest.raises(ValueError, match="`seq`"):
        _vector.parse_seq(seq)
