"""`_xla`: every program rbdyn_jax compiles gets `COMPILER_OPTIONS` when it is compiled at
the top level, and stays callable inside a caller's transformations (JAX refuses compiler
options on a nested jit)."""

import ast
import pathlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rbdyn_jax as rb
from rbdyn_jax import _xla

PACKAGE = pathlib.Path(rb.__file__).parent


def test_top_level_is_false_under_every_transformation():
    seen = []

    def probe(x):
        seen.append(_xla.top_level())
        return x

    for transform in (jax.jit, jax.vmap, jax.grad, jax.jacfwd, eqx.filter_jit):
        seen.clear()
        transform(probe)(jnp.ones(()) if transform is not jax.vmap else jnp.ones(2))
        assert seen == [False], transform
    assert _xla.top_level()


@pytest.mark.parametrize("jitter", [_xla.jit, _xla.filter_jit])
def test_wrapped_function_runs_alike_at_top_level_and_nested(jitter):
    f = jitter(lambda x: jnp.sin(x) * x)
    x = jnp.linspace(0.1, 1.0, 4)
    want = np.sin(np.asarray(x)) * np.asarray(x)
    np.testing.assert_allclose(f(x), want, rtol=1e-15)  # own program, with the options
    np.testing.assert_allclose(jax.jit(f)(x), want, rtol=1e-15)  # nested: a plain jit
    np.testing.assert_allclose(jax.vmap(f)(x), want, rtol=1e-15)
    np.testing.assert_allclose(jax.grad(lambda x: jnp.sum(f(x)))(x),
                               np.sin(np.asarray(x)) + np.asarray(x) * np.cos(np.asarray(x)),
                               rtol=1e-14)


def test_a_nested_jit_with_options_is_what_jax_refuses():
    """Why `_xla` dispatches: if JAX starts accepting this, the dispatch can go."""
    g = jax.jit(jnp.sin, compiler_options=_xla.COMPILER_OPTIONS)
    assert float(g(1.0)) == pytest.approx(np.sin(1.0))
    with pytest.raises(ValueError, match="top-level"):
        jax.jit(lambda x: g(x))(1.0)


def test_the_public_options_go_to_a_callers_jit():
    f = jax.jit(lambda x: jnp.cos(x), compiler_options=rb.COMPILER_OPTIONS)
    assert float(f(0.5)) == pytest.approx(np.cos(0.5))


def direct_jits(path: pathlib.Path) -> list[int]:
    """Lines of the file at `path` that name `jax.jit` or `eqx.filter_jit` in code (not in
    strings): a program compiled without `_xla.COMPILER_OPTIONS`."""
    return sorted(
        node.lineno
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, ast.Attribute)
        and (node.attr, getattr(node.value, "id", None)) in {("jit", "jax"), ("filter_jit", "eqx")}
    )


def test_every_program_is_compiled_through_xla():
    """`_xla.py` owns how rbdyn_jax compiles: every other module jits through its `jit` and
    `filter_jit`, which pass `COMPILER_OPTIONS` (a jit of its own would compile without
    them, ~1/3 slower on CPU)."""
    found = {p.name: direct_jits(p) for p in PACKAGE.glob("*.py") if p.name != "_xla.py"}
    assert not {k: v for k, v in found.items() if v}


def test_jit_checker_sees_a_direct_jit(tmp_path):
    bad = tmp_path / "m.py"
    bad.write_text('"""jax.jit in a docstring"""\nimport jax\nf = jax.jit(g)\n\n'
                   "@eqx.filter_jit\ndef h(): ...\n")
    assert direct_jits(bad) == [3, 5]
