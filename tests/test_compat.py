"""What rbdyn_jax relies on of its dependencies' internals (`rbdyn_jax/_compat.py`), pinned.

Each test states one behaviour the library depends on; a new diffrax, equinox or JAX that
changes it fails here, by name. The last test holds that no other file reaches into them.
"""

import pathlib
import re

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rbdyn_jax as rb
from rbdyn_jax import _compat

PACKAGE = pathlib.Path(rb.__file__).parent


def test_trace_state_clean_tells_top_level_from_traced():
    seen = []
    assert _compat.trace_state_clean()
    jax.jit(lambda x: seen.append(_compat.trace_state_clean()) or x)(1.0)
    jax.make_jaxpr(lambda x: seen.append(_compat.trace_state_clean()) or x)(1.0)
    assert seen == [False, False]


def test_backends_are_initialized_after_a_computation():
    jnp.zeros(1).block_until_ready()
    assert _compat.backends_are_initialized() is True


def test_wrapped_term_is_the_term_diffeqsolve_hands_its_solver():
    """The lane loop steps diffrax's solver on this term: it must be the one diffeqsolve
    steps on, or the lanes would not take diffeqsolve's steps bitwise."""
    seen = []

    class Spy(diffrax.Tsit5):
        def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
            seen.append(type(terms))
            return super().step(terms, t0, t1, y0, args, solver_state, made_jump)

    term = diffrax.ODETerm(lambda t, y, args: -y)
    diffrax.diffeqsolve(term, Spy(), 0.0, 1.0, 0.1, jnp.ones(2))
    assert seen and all(t is type(_compat.wrapped_term(term)) for t in seen)
    y0 = jnp.array([1.0, 2.0])
    wrapped = _compat.wrapped_term(term)
    state = diffrax.Tsit5().init(wrapped, 0.0, 0.1, y0, None)
    mine = diffrax.Tsit5().step(wrapped, 0.0, 0.1, y0, None, state, False)[0]
    direct = diffrax.diffeqsolve(
        term, diffrax.Tsit5(), 0.0, 0.1, 0.1, y0, stepsize_controller=diffrax.ConstantStepSize()
    ).ys[-1]
    np.testing.assert_array_equal(mine, direct)


def test_unwrapped_term_is_the_callers_term_and_its_direction():
    """`LiePoissonSplitting` finds the model behind the term diffeqsolve hands it: that
    term must unwrap to the caller's own, with the direction of time (−1 for a solve
    from a later time to an earlier one), and a term stepped by hand is its own."""
    fields, directions = [], []

    class Spy(diffrax.Euler):
        def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
            inner, direction = _compat.unwrapped_term(terms)
            fields.append(inner.vector_field)
            jax.debug.callback(lambda d: directions.append(int(d)), direction)
            return super().step(terms, t0, t1, y0, args, solver_state, made_jump)

    term = diffrax.ODETerm(lambda t, y, args: -y)
    forward = diffrax.diffeqsolve(term, Spy(), 0.0, 1.0, 0.5, jnp.ones(2))
    backward = diffrax.diffeqsolve(term, Spy(), 1.0, 0.0, -0.5, jnp.ones(2))
    jax.block_until_ready((forward, backward))
    assert fields and all(f is term.vector_field for f in fields)
    assert set(directions) == {1, -1}
    assert _compat.unwrapped_term(term) == (term, 1)


def test_result_values_are_int_codes_of_the_enumeration():
    names = _compat.result_names(diffrax.RESULTS)
    assert names["successful"] is diffrax.RESULTS.successful
    codes = {name: int(_compat.result_value(item)) for name, item in names.items()}
    assert codes["successful"] == 0 and len(set(codes.values())) == len(codes)
    held = _compat.result_with_value(
        diffrax.RESULTS.successful, jnp.asarray([codes["max_steps_reached"], 0])
    )
    assert isinstance(held, type(diffrax.RESULTS.successful))
    np.testing.assert_array_equal(held == diffrax.RESULTS.max_steps_reached, [True, False])


def test_rbdyn_results_extend_diffrax_codes_with_the_same_values():
    ours = rb.integrate.result_names()
    for name, item in _compat.result_names(diffrax.RESULTS).items():
        assert ours[int(_compat.result_value(item))] == name
    assert "nonfinite_state" in ours.values()


def test_error_mode_nan_turns_a_failed_check_into_nan():
    def checked(x):
        return eqx.error_if(x, x < 0, "negative")

    assert _compat.error_mode() == "raise"
    with _compat.error_mode_set("nan"):
        assert _compat.error_mode() == "nan"
        out = jax.jit(lambda x: checked(x))(jnp.asarray(-1.0))  # a new trace
    assert bool(jnp.isnan(out))
    assert _compat.error_mode() == "raise"
    with pytest.raises(Exception, match="negative"):
        jax.jit(lambda x: checked(x))(jnp.asarray(-2.0)).block_until_ready()


def test_uncommitted_frees_a_stored_programs_output():
    """A call of an exported program commits its outputs (`jit`'s, for inputs none of which
    is committed, are not); `uncommitted` gives the same values, dtype and sharding,
    uncommitted."""
    x = jnp.arange(3.0)
    exported = jax.export.export(jax.jit(lambda x: 2.0 * x))(x)
    y = jax.jit(exported.call)(x)
    assert y.committed and not jax.jit(lambda x: 2.0 * x)(x).committed
    free = _compat.uncommitted(y)
    assert not free.committed and free.sharding == y.sharding and free.dtype == y.dtype
    np.testing.assert_array_equal(free, [0.0, 2.0, 4.0])


def test_only_compat_reaches_into_internals():
    pattern = re.compile(
        r"jax\._src|diffrax\._|equinox\._|\._value\b|\._name_to_item|"
        r"EQX_ON_ERROR"
    )
    offenders = [
        str(p.relative_to(PACKAGE))
        for p in PACKAGE.rglob("*.py")
        if p.name != "_compat.py" and pattern.search(p.read_text())
    ]
    assert offenders == []
