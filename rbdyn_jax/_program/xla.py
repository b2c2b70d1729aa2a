"""How rbdyn_jax compiles: every program it compiles goes through `jit` or `filter_jit`
here, which pass `COMPILER_OPTIONS` to XLA.

XLA:CPU compiles each fused kernel of a program through its MLIR "fusion emitters" by
default. Up to jaxlib 0.10 its classic emitters remain, and compile a solver program (~100
kernels) markedly faster, and the program runs as fast (the performance page,
docs/performance.md). `xla_cpu_use_fusion_emitters` is a field of XLA's `DebugOptions`;
only the CPU backend reads it, but every backend parses a program's options and refuses one
its XLA does not know, so `COMPILER_OPTIONS` holds only the options of the running jaxlib's
XLA (`known_options`; the XLA of jaxlib 0.11 has no classic emitters and no such option).

JAX takes compiler options only from the outermost `jit` of a program (a nested one
raises). So the wrappers here pass them when called at the top level and are plain jits
inside a caller's transformation, whose program compiles with the caller's options: pass
`compiler_options=rbdyn_jax.COMPILER_OPTIONS` to your own `jax.jit` for the same saving.

`flags.py` sets what compiler options cannot: XLA's process-wide flags (`XLA_FLAGS`),
read once when JAX starts its backend. `import rbdyn_jax` sets them (one XLA CPU device
per core, every while loop compiled whole; flags already in `XLA_FLAGS` win) unless
`RBDYN_JAX_CONFIGURE_XLA=0` is in the environment or JAX's backend is already running;
`configure_xla` (re-exported here) sets them explicitly, for another device count.
"""

import functools

import equinox as eqx
import jax
import jaxlib

from .. import _compat
from . import checks
from .flags import (
    configure_xla as configure_xla,
    loops_compiled_whole as loops_compiled_whole,
)

# Options that only some XLA versions know: name → the first jaxlib (major, minor) whose XLA
# refuses it ("No such compile option").
RETIRED = {"xla_cpu_use_fusion_emitters": (0, 11)}


def jaxlib_version() -> tuple[int, int]:
    """The running jaxlib's (major, minor): the version of its XLA."""
    return tuple(int(p) for p in jaxlib.__version__.split(".")[:2])


def known_options(options: dict, version: tuple[int, int] | None = None) -> dict:
    """`options` less those the XLA of jaxlib `version` (default the running one) no longer
    knows (`RETIRED`)."""
    version = jaxlib_version() if version is None else version
    return {k: v for k, v in options.items() if k not in RETIRED or version < RETIRED[k]}


COMPILER_OPTIONS = known_options({"xla_cpu_use_fusion_emitters": False})

# For a program compiled at the first call of every process and run for a short while, whose
# compile time is most of that call: `identify.fit`'s. XLA's backend optimisation level 1
# (of 0–3, default 2) compiles the benchmark's fit faster and runs it about as fast; the
# lane solver runs markedly slower there, so solves keep `COMPILER_OPTIONS` (the
# performance page).
QUICK_COMPILE_OPTIONS = {**COMPILER_OPTIONS, "xla_backend_optimization_level": 1}


def top_level() -> bool:
    """Whether nothing is being traced now: a jitted call here compiles its own program."""
    return _compat.trace_state_clean()


def _dispatch(jitter, fn, options):
    own, nested = jitter(fn, compiler_options=options), jitter(fn)

    @functools.wraps(fn)
    def call(*args, **kwargs):
        return (own if top_level() else nested)(*args, **kwargs)

    call.jitted = (own, nested)  # the two jits, whose cached traces may be dropped
    return call


def jit(fn, options=COMPILER_OPTIONS):
    """`jax.jit(fn)`, compiled with `options` when called at the top level."""
    return _dispatch(jax.jit, fn, options)


def filter_jit(fn, options=COMPILER_OPTIONS):
    """`eqx.filter_jit(fn)`, compiled with `options` when called at the top level."""
    return _dispatch(eqx.filter_jit, fn, options)


def nested_filter_jit(fn):
    """`eqx.filter_jit(fn)` for a function called only while a program is traced (it never
    compiles a program of its own, so it needs no options). JAX traces it once per input
    structure and the enclosing program holds one `jit` call per use; the trace, its
    batching under `vmap` and its lowering are then shared by every use of that structure.
    Its cached traces are dropped when the check mode changes (`checks.as_nan`)."""
    return checks.mode_dependent(eqx.filter_jit(fn))


def export(fn):
    """`jax.export.export(jax.jit(fn))`: `fn` traced and lowered, for storing (`traces.py`).
    Nothing is compiled here; the exported program is compiled through `jit`."""
    return jax.export.export(jax.jit(fn))
