"""`_cheapest`: one equation that runs the cheapest program giving what its caller reads.

Which program runs is decided by JAX's dead-code elimination (`dce_jaxpr`, which `jit`
runs on the whole program before lowering). The toy programs here differ in one
operation (only the large one takes a cosine), so the choice can be read both off the
equation after elimination and off the program `jit` lowers.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import cheapest_call

from rbdyn_jax.integrate._cheapest import cheapest


def small(x, y):
    return {"a": jnp.sin(x) * y}


def large(x, y):
    return {"a": jnp.sin(x) * y, "b": jnp.cos(x) + y}


def both(x, y):
    return cheapest([small, large], x, y)


def chosen(f, *args):
    """The program `f`'s `cheapest` equation runs after dead-code elimination."""
    return cheapest_call(jax.make_jaxpr(f)(*args)).params["chosen"]


X, Y = jnp.linspace(0.1, 1.0, 4), jnp.array(2.0)


@pytest.mark.parametrize("reads, program", [("a", 0), ("b", 1), ("ab", 1)])
def test_the_first_program_giving_what_is_read_runs(reads, program):
    def f(x, y):
        out = both(x, y)
        return sum(jnp.sum(out[k]) for k in reads)

    assert chosen(f, X, Y) == program
    assert ("cosine" in jax.jit(f).lower(X, Y).as_text()) == bool(program)
    expected = sum(jnp.sum(large(X, Y)[k]) for k in reads)
    np.testing.assert_allclose(jax.jit(f)(X, Y), expected, rtol=1e-15)
    np.testing.assert_allclose(f(X, Y), expected, rtol=1e-15)  # eager: the last program


def test_vmap_keeps_the_choice_open_and_batches_the_programs():
    def f(x, y):
        return both(x, y)["a"]

    ys = jnp.array([1.0, 2.0, 3.0])
    assert chosen(jax.vmap(f, in_axes=(None, 0)), X, ys) == 0
    np.testing.assert_allclose(
        jax.jit(jax.vmap(f, in_axes=(None, 0)))(X, ys), jnp.sin(X)[None] * ys[:, None], rtol=1e-15
    )


def test_derivatives_of_the_chosen_program():
    """Forward mode differentiates the program chosen so far (the last one, before
    elimination); reverse mode transposes that: both against the closed form."""

    def f(x):
        out = both(x, Y)
        return jnp.sum(out["a"] + out["b"] ** 2)

    expected = jnp.cos(X) * Y - 2 * (jnp.cos(X) + Y) * jnp.sin(X)
    np.testing.assert_allclose(jax.jit(jax.grad(f))(X), expected, rtol=1e-14)
    np.testing.assert_allclose(jax.jacfwd(f)(X), expected, rtol=1e-14)


def test_programs_must_give_names_of_the_last():
    with pytest.raises(ValueError, match="among the last"):
        cheapest([large, small], X, Y)
