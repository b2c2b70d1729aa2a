"""`_rows.rowwise`, the evaluator that runs a one-trajectory function on rows of lanes (the
kernel strategy's core), against `jax.vmap` of the same function. It reads JAX's jaxpr
parameters (a scan's counts and body, a cond's branches, the jaxpr of a call), which
change between JAX releases: these tests exercise each form, and run under the next JAX
too (`core`), so a change there fails here by name rather than inside a kernel.

Both sides do the same float64 operations in possibly different order (a contraction is
unrolled into a sum of rows), so they agree to a few ulps: 1e-14 relative (the scan's
carries grow to O(100)) and absolute.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rbdyn_jax.integrate import _rows

B = 5
ROUND_OFF = 1e-14


def as_rows(x):
    """(B, *S) → an object array of shape S whose elements are rows (B,)."""
    x = jnp.asarray(x)
    return _rows.objects(x.shape[1:], lambda idx: x[(slice(None), *idx)])


def from_rows(obj):
    """An object array of rows (or of lane-independent constants) → (B, *S)."""
    rows = [jnp.broadcast_to(e, (B,)) for e in obj.reshape(-1)]
    return jnp.stack(rows, axis=-1).reshape((B, *obj.shape)) if rows else jnp.zeros((B, 0))


def check(fn, *args):
    expected = jax.vmap(fn)(*args)
    got = _rows.rowwise(fn, *(as_rows(a) for a in args))
    assert jax.tree_util.tree_structure(expected) == jax.tree_util.tree_structure(got)
    for e, g in zip(jax.tree_util.tree_leaves(expected), jax.tree_util.tree_leaves(got)):
        g = from_rows(g)
        assert g.dtype == e.dtype
        np.testing.assert_allclose(g, e, rtol=ROUND_OFF, atol=ROUND_OFF)


@pytest.fixture
def data():
    rng = np.random.default_rng(0)
    return (
        jnp.asarray(rng.normal(size=(B, 3, 3))),
        jnp.asarray(rng.normal(size=(B, 3))),
        jnp.asarray(rng.normal(size=(B, 4, 3))),
    )


def test_contractions_reductions_and_structure(data):
    m, v, _ = data

    def fn(m, v):
        w = m @ v + jnp.cross(v, m[0])
        s = jnp.concatenate([w, jnp.sum(m, axis=0), jnp.max(m, axis=1)])
        return jnp.sin(s[::-1]) * jnp.arange(9.0), jnp.einsum("ij,ji->", m, m.T), m.T[1:]

    check(fn, m, v)


def test_scan_with_constants_carries_and_inputs_both_ways(data):
    m, v, xs = data

    def fn(m, v, xs):
        def body(carry, x):
            a, b = carry
            return (m @ a + x, b * jnp.tanh(x[0])), (a[1] * x, b)

        fwd = jax.lax.scan(body, (v, v[0]), xs)
        back = jax.lax.scan(body, (v, v[2]), xs, reverse=True)
        return fwd, back

    check(fn, m, v, xs)


def test_cond_selects_per_lane_and_calls_are_followed(data):
    _, v, _ = data

    @jax.custom_jvp
    def soft(x):
        return jnp.log1p(jnp.exp(x))

    soft.defjvp(lambda p, t: (soft(p[0]), t[0] * jax.nn.sigmoid(p[0])))

    @jax.jit
    def inner(x):
        return x**2 - 1.0

    def fn(v):
        picked = jax.lax.cond(v[0] > 0, lambda x: inner(x), lambda x: soft(x), v)
        return picked + jnp.where(v[1] > v[2], v, -v)

    check(fn, v)


def test_negated_constants_keep_their_signed_zeros(data):
    """A constant of the trace is negated as a product by −1 (Pallas's Triton lowering
    cannot negate a literal): exactly −x, the sign of a zero included."""
    _, v, _ = data

    def fn(v):
        return jnp.stack([-jnp.zeros(()), -jnp.ones(()) * 0.0, -v[0]]), 1.0 / -jnp.zeros(())

    expected, got = jax.vmap(fn)(v), _rows.rowwise(fn, as_rows(v))
    for e, g in zip(expected, got):
        g = np.asarray(from_rows(g))
        np.testing.assert_array_equal(g, e)
        np.testing.assert_array_equal(np.signbit(g), np.signbit(e))


def test_mixed_dtypes_empty_reductions_signed_zero_sums_and_unsigned_constants(data):
    """A float32 operand contracted with a float64 one (a float64 result), reductions over
    no elements (their identities), sums of negative zeros (+0, as XLA's reduction from
    0 gives; seen through 1/x = +inf and atan2) and a negated unsigned constant (wrapping)."""
    m, v, _ = data

    def fn(m, v):
        w = jax.lax.dot(m.astype(jnp.float32), v, preferred_element_type=jnp.float64)
        none = v[:0]
        zeros = jnp.zeros((3, 3)) @ -jnp.abs(v)
        return (
            w,
            jnp.sum(none),
            jnp.max(none, initial=-1.0),
            jnp.prod(none),
            1.0 / zeros,
            1.0 / jnp.sum(0.0 * -jnp.abs(v)),
            jnp.arctan2(0.0, zeros),
            -jnp.asarray(3, jnp.uint32) + jnp.abs(v).astype(jnp.uint32),
        )

    check(fn, m, v)


def test_what_has_no_form_on_rows_is_named(data):
    _, v, _ = data

    def loop(v):
        return jax.lax.while_loop(lambda x: x[0] < 10.0, lambda x: x * 2.0 + 1.0, v)

    def gather(v):
        return v[jnp.argmax(v)]

    for fn, name in ((loop, "while"), (gather, "dynamic_slice")):
        with pytest.raises(ValueError, match=name):
            _rows.rowwise(fn, as_rows(v))
