"""`Program`: how a function of rbdyn_jax becomes a compiled program, the one way in.

Every solve, sweep chunk and fit is a plain function of its inputs, made a `Program`
where it is defined. A call is compiled once per input *structure* (`eqx.filter_jit`:
arrays are inputs, everything else static), so new parameter values, initial conditions,
times or tolerances reuse the compiled program. What `Program` decides per call:

- **Checks.** Where the inputs a function's checks read were validated before tracing
  (`validated(*args)` holds no tracer: concrete values, checked in NumPy), the function is
  traced with its runtime checks as NaN (`checks.as_nan`): its program holds no host
  callback. Otherwise the call is part of a caller's trace (its times traced, say) and
  takes the caller's mode: its checks raise at run time, or give NaN inside a program
  itself traced with its checks as NaN (a fit's solves). Such a trace is dropped whenever
  the mode switches, so a trace made in one mode is never reused in the other.
- **Storing.** A program traced with its checks as NaN, called at the top level, is stored
  by the on-disk cache of traced programs (`traces.cached`, where JAX's persistent
  compilation cache is configured) and loaded by a later process instead of traced.
- **Compiler options.** Called at the top level, the program compiles with `options`;
  inside a caller's transformation it is part of the caller's program (`xla.filter_jit`).

Every call takes one lock (`checks.exclusive`) before JAX looks up its trace, so two threads
never trace rbdyn_jax's programs in different modes at once.
"""

import functools
from collections.abc import Callable

import jax

from . import checks, traces
from .xla import COMPILER_OPTIONS, filter_jit


def concrete(*xs) -> bool:
    """Whether no leaf of `xs` is traced: values known now, which were checked before
    tracing."""
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(xs))


class Program:
    """`fn` compiled, with its checks as NaN where its inputs were validated before
    tracing (module docstring).

    **Arguments:**

    - `fn`: a function of positional arguments (arrays and static values, pytrees of
      them) returning a pytree of arrays.
    - `validated`: a function of `fn`'s arguments giving those whose checks run before
      tracing (their values checked in NumPy); a call where they are concrete is traced
      with its checks as NaN. `None`: every call's inputs were validated (a sweep's chunk,
      a fit of checked observations).
    - `options`: XLA's compiler options for the program compiled at the top level.
    - `store`: whether a checks-as-NaN program may go to the on-disk cache of traced
      programs (`False` for one `jax.export` cannot serialize, such as a Pallas kernel).
    """

    def __init__(
        self,
        fn: Callable,
        *,
        validated: Callable | None = None,
        options: dict = COMPILER_OPTIONS,
        store: bool = True,
    ):
        self.fn = fn
        self.validated = validated

        @functools.wraps(fn)
        def checks_nan(*args):
            with checks.as_nan():
                return fn(*args)

        # A call whose validated inputs are traced is part of a caller's trace, which may
        # itself be traced with its checks as NaN (a fit's solves): its trace depends on
        # the mode, so it is dropped when the mode switches, like diffeqsolve's.
        self._checked = filter_jit(fn, options)
        checks.mode_dependent(*self._checked.jitted)
        self._as_nan = (
            traces.cached(checks_nan, options) if store else filter_jit(checks_nan, options)
        )
        functools.update_wrapper(self, fn)

    def checks_nan(self, *args) -> bool:
        """Whether a call with `args` is traced with its checks as NaN."""
        return self.validated is None or concrete(self.validated(*args))

    def __call__(self, *args):
        run = self._as_nan if self.checks_nan(*args) else self._checked
        # The lock before JAX looks up or claims a trace: a thread never waits for the lock
        # while it holds a trace another thread may be waiting for.
        with checks.exclusive():
            return run(*args)


def program(
    *, validated: Callable | None = None, options: dict = COMPILER_OPTIONS, store: bool = True
) -> Callable[[Callable], Program]:
    """`Program` as a decorator: `@program(validated=...)` over a function's definition."""
    return functools.partial(Program, validated=validated, options=options, store=store)
