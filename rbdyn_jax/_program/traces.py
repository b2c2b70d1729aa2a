"""An on-disk cache of traced programs, beside JAX's persistent compilation cache.

JAX's persistent cache stores compiled XLA programs, but a new process must still trace the
Python function to find which program it needs, and for a diffrax solve the trace is most of a
warm first call (far more than the cache lookup). When JAX's cache is configured
(`jax_compilation_cache_dir`), the solves of `rbdyn_jax.integrate` and the fits of
`rbdyn_jax.identify` (their Levenberg–Marquardt program) are therefore also exported
(`jax.export`: the traced program as StableHLO, with JAX's serialization) into
`<cache dir>/rbdyn_jax-traces/`, and a later process with the same inputs loads that instead of
tracing: the same program, the same results (tested bitwise), its compilation then served by
JAX's cache as before.

The danger of such a cache is serving a stale program: a trace depends on Python code and
on every static value the code reads, which JAX's cache never sees. So an entry's key is
built from a complete description of the call, and a call it cannot describe exactly is
never cached (it is traced, as without this module):

- the versions of JAX and of every library the program's code comes from (diffrax,
  equinox, lineax, optimistix, optax, jaxtyping, numpy), a digest of rbdyn_jax's own source
  files, the JAX settings that change a trace (float64, matmul precision, dtype promotion),
  the platform and the number of devices;
- the call's pytree: every node type, which must come from one of those libraries (a
  user's own torque class is not versioned by anything here, so its model is not cached),
  every static value (numbers, strings, functions and classes of those libraries by name,
  numpy constants by content), and the shape, dtype and weak type of every array.

Inside a caller's own transformation (its `jax.jit(jax.grad(loss))`, say) a solve is part
of the caller's program, which rbdyn_jax cannot store. There the lane solver's loops, the
expensive part of that trace, are stored alone (`embedded`) and called by `jax.export`'s
`call`: the caller's trace then holds the stored loop instead of tracing it anew.

`RBDYN_JAX_TRACE_CACHE=0` in the environment turns the cache off.
"""

import enum
import functools
import hashlib
import importlib.metadata
import os
import pathlib
import pickle
import sys
import types

import equinox as eqx
import jax
import numpy as np

from .. import _compat
from .devices import WHOLE, mesh
from .xla import COMPILER_OPTIONS, export, filter_jit, jit, top_level

# The modules whose classes and functions a key may name: their code is versioned by
# `_environment` (builtins by the Python version, which changes the bytecode cache anyway).
_LIBRARIES = (
    "builtins",
    "rbdyn_jax",
    "diffrax",
    "equinox",
    "lineax",
    "optimistix",
    "optax",
    "jax",
    "jaxlib",
    "jaxtyping",
    "numpy",
)
_DISTRIBUTIONS = (
    "jax",
    "jaxlib",
    "diffrax",
    "equinox",
    "lineax",
    "optimistix",
    "optax",
    "jaxtyping",
    "numpy",
    "flatbuffers",
)
_SUBDIR = "rbdyn_jax-traces"

stats = {"hits": 0, "stores": 0, "uncacheable": 0}  # this process's use of the cache (tests)
_LOADED: dict[str, tuple] = {}  # key -> (jitted exported call, output treedef)
_KEYS: dict[tuple, str | None] = {}  # `_memo_key`'s memo
_UNEXPORTABLE: set[str] = set()  # keys whose trace `jax.export` refused
_EMBEDDED: dict[str, tuple] = {}  # key -> (exported program, output treedef), for `embedded`


class _Unsafe(Exception):
    """A value the key cannot describe exactly."""


def directory() -> pathlib.Path | None:
    """Where the traces go: `rbdyn_jax-traces/` in JAX's persistent cache directory, or
    `None` when that cache is not configured (or `RBDYN_JAX_TRACE_CACHE=0`)."""
    if os.environ.get("RBDYN_JAX_TRACE_CACHE", "1") == "0":
        return None
    if not jax.config.jax_enable_compilation_cache:
        return None
    d = jax.config.jax_compilation_cache_dir
    return None if not d else pathlib.Path(d) / _SUBDIR


@functools.cache
def _environment() -> str:
    """What every key shares: library versions and rbdyn_jax's source digest."""
    h = hashlib.sha256(sys.version.encode())
    for name in _DISTRIBUTIONS:
        try:
            h.update(f"{name}={importlib.metadata.version(name)};".encode())
        except importlib.metadata.PackageNotFoundError:
            h.update(f"{name}=none;".encode())
    root = pathlib.Path(__file__).parent.parent  # the rbdyn_jax package
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def _ours(obj) -> bool:
    module = getattr(obj, "__module__", None) or ""
    return module.split(".")[0] in _LIBRARIES


def _name(obj) -> str:
    if not _ours(obj):
        raise _Unsafe(obj)
    return f"{obj.__module__}.{obj.__qualname__}"


def _value(v):
    """An exact, process-independent description of a static value, or `_Unsafe`."""
    if v is None or isinstance(v, (bool, int, float, complex, str, bytes)):
        return (type(v).__name__, repr(v))
    if isinstance(v, (tuple, list)):
        return (type(v).__name__, tuple(_value(x) for x in v))
    if isinstance(v, dict):
        return ("dict", tuple((_value(k), _value(x)) for k, x in v.items()))
    if isinstance(v, (frozenset, set)):
        return (type(v).__name__, tuple(sorted(repr(_value(x)) for x in v)))
    if isinstance(v, (np.ndarray, np.generic)):
        a = np.asarray(v)
        return ("ndarray", str(a.dtype), a.shape, hashlib.sha256(a.tobytes()).hexdigest())
    if isinstance(v, np.dtype):
        return ("dtype", str(v))
    if isinstance(v, enum.Enum):
        return ("enum", _name(type(v)), v.name)
    if isinstance(v, type):
        return ("type", _name(v))
    if isinstance(v, types.FunctionType):
        cells = tuple(_value(c.cell_contents) for c in v.__closure__ or ())
        return ("function", _name(v), cells, _value(v.__defaults__))
    if isinstance(v, (types.BuiltinFunctionType, np.ufunc)):
        return ("builtin", getattr(v, "__module__", None), v.__name__)
    if isinstance(v, functools.partial):
        return ("partial", _value(v.func), _value(v.args), _value(v.keywords))
    if isinstance(v, jax.sharding.Mesh):  # its devices: the first ones of the platform
        if [d.id for d in v.devices.flat] != list(range(v.devices.size)):
            raise _Unsafe(v)
        return ("mesh", v.axis_names, v.devices.flat[0].platform, v.devices.size)
    if isinstance(v, eqx.Module):
        return ("tree", _tree(v))
    if _ours(type(v)) and " at 0x" not in repr(v):  # sentinels (equinox's `Missing`, …)
        return ("object", _name(type(v)), repr(v))
    raise _Unsafe(v)


def _treedef(t):
    data = t.node_data()
    if data is None:
        return "*"
    node, aux = data
    return (_name(node), _value(aux), tuple(_treedef(c) for c in t.children()))


def _tree(tree):
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    return _treedef(treedef), tuple(_leaf(x) for x in leaves)


def _aval(x) -> tuple:
    """What a trace sees of an array: shape, dtype and weak type (numpy: never weak)."""
    weak = bool(jax.typeof(x).weak_type) if isinstance(x, jax.Array) else False
    return ("array", tuple(x.shape), str(x.dtype), weak)


def _leaf(x):
    return _aval(x) if eqx.is_array(x) else _value(x)


def _settings() -> tuple:
    """The JAX settings a trace depends on, and the devices it is lowered for."""
    c = jax.config
    return (
        c.jax_enable_x64,
        str(c.jax_default_matmul_precision),
        c.jax_numpy_dtype_promotion,
        c.jax_numpy_rank_promotion,
        jax.default_backend(),
        jax.device_count(),
    )


def key(name: str, args: tuple, options: dict = COMPILER_OPTIONS) -> str | None:
    """The cache key of `name(*args)` compiled with XLA's `options`, or `None` if the call
    cannot be described exactly (then it must not be cached)."""
    try:
        description = (name, _environment(), _tree(args), _settings(), _value(options))
    except _Unsafe:
        return None
    return hashlib.sha256(repr(description).encode()).hexdigest()


def _load(path: pathlib.Path):
    try:
        entry = pickle.loads(path.read_bytes())
        exported = jax.export.deserialize(bytearray(entry["exported"]))
        return exported, jax.tree_util.tree_structure(entry["tree"])
    except Exception:  # missing, partly written or from an incompatible version
        return None


def _export(path: pathlib.Path, fn, dyn, static, leaves):
    dyn_tree = jax.tree_util.tree_structure(dyn)
    out_tree = []

    def flat(*xs):
        out = fn(*eqx.combine(jax.tree_util.tree_unflatten(dyn_tree, xs), static))
        out_leaves, treedef = jax.tree_util.tree_flatten(out)
        out_tree.append(treedef)
        return out_leaves

    try:
        exported = export(flat)(*leaves)
    except Exception:  # not exportable (a host callback, say): the caller traces it anew,
        return None  # raising there as it would have without this cache
    try:
        skeleton = jax.tree_util.tree_unflatten(out_tree[0], [0] * out_tree[0].num_leaves)
        blob = pickle.dumps({"tree": skeleton, "exported": bytes(exported.serialize())})
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_bytes(blob)
        tmp.replace(path)  # atomic: a reader sees all of an entry or none
        stats["stores"] += 1
    except Exception:  # not serializable (or not writable): traced, used, not stored
        pass
    return exported, out_tree[0]


def _memo_key(name, treedef, leaves, options=COMPILER_OPTIONS):
    """`key(name, args)` looked up by value in this process's memo, whose keys are the
    JAX settings, the pytree structure (equinox's static fields compared by `==`), the
    static values with their types, and the arrays' shapes and dtypes: a dict lookup
    instead of the full description, which is too slow to build on every call."""
    memo = (
        name,
        tuple(sorted(options.items())),
        _settings(),
        treedef,
        tuple(
            _aval(x)
            if eqx.is_array(x)
            else (type(x), repr(x))
            if isinstance(x, (float, complex))  # 0.0 == -0.0
            else (type(x), x)
            for x in leaves
        ),
    )
    try:
        return _KEYS[memo]
    except KeyError:
        pass
    except Exception:  # an unhashable or incomparable static value: describe in full
        return key(name, jax.tree_util.tree_unflatten(treedef, leaves), options)
    k = key(name, jax.tree_util.tree_unflatten(treedef, leaves), options)
    if len(_KEYS) > 1024:
        _KEYS.clear()
    _KEYS[memo] = k
    return k


def _entry(where, k, fn, args, arrays):
    """Key `k`'s stored program and output structure: loaded, or else traced from `fn(*args)`
    with `arrays` (its arrays, or their shapes and dtypes) as inputs and stored; `None`
    (remembered) if `jax.export` refuses it."""
    path = where / f"{k}.jaxexport"
    entry = _load(path)
    if entry is not None:
        stats["hits"] += 1
        return entry
    dyn, static = eqx.partition(args, eqx.is_array)
    entry = _export(path, fn, dyn, static, arrays)
    if entry is None:
        _UNEXPORTABLE.add(k)
        stats["uncacheable"] += 1
    return entry


def _as_they_are(arrays):
    return arrays


def _placement(exported):
    """How to place the inputs of a stored program: as they are for one device; for a
    program over several (the lane solver's devices), replicated over the same first
    devices, as `jit` placed them when it was traced."""
    if exported.nr_devices == 1:
        return _as_they_are
    replicated = jax.sharding.NamedSharding(mesh(jax.devices()[: exported.nr_devices]), WHOLE)
    return lambda arrays: [jax.device_put(x, replicated) for x in arrays]


def cached(fn, options: dict = COMPILER_OPTIONS):
    """`filter_jit(fn, options)`, with `fn`'s traced program stored on disk and reused
    by later processes where `directory()` is set, the call is made at the top level with
    concrete arrays, and `key` can describe it (a loaded program is compiled with the same
    XLA `options`). `fn` must be traced with no host callback (rbdyn_jax's checks-as-NaN
    programs), or it cannot be exported. Inside a caller's transformation `fn` is part of
    the caller's program (which may call `embedded` programs of its own)."""
    name = f"{fn.__module__}.{fn.__qualname__}"
    jitted = filter_jit(fn, options)

    @functools.wraps(fn)
    def call(*args):
        where = directory()
        if where is None or not top_level():  # not cached, or a caller's program
            return jitted(*args)
        leaves, treedef = jax.tree_util.tree_flatten(args)
        arrays = [x for x in leaves if eqx.is_array(x)]
        if any(isinstance(x, jax.core.Tracer) for x in arrays):
            return jitted(*args)
        k = _memo_key(name, treedef, leaves, options)
        if k is None or k in _UNEXPORTABLE:
            stats["uncacheable"] += 1
            return jitted(*args)
        if k not in _LOADED:
            entry = _entry(where, k, fn, args, arrays)
            if entry is None:  # not exportable: traced as without the cache, from now on
                return jitted(*args)
            exported, out_tree = entry
            _LOADED[k] = (jit(exported.call, options), out_tree, _placement(exported))
        run, out_tree, place = _LOADED[k]
        outs = run(*place(arrays))
        if place is _as_they_are and not any(x.committed for x in arrays):
            # committed by the stored program's call, where `jitted`'s would not be
            outs = [_compat.uncommitted(x) for x in outs]
        return jax.tree_util.tree_unflatten(out_tree, outs)

    return call


def embedded(fn, *args):
    """`fn(*args)` with `fn`'s program stored on disk alone (where `directory()` is set),
    and called as the stored program by a later process instead of tracing `fn`: inside a
    caller's trace, which then holds it as one `call_exported` (the lane solver's loop, when
    its solve is traced inside a caller's transformation: `integrate/_batching.py`).

    Its key describes the call as `key` does (shapes and dtypes of the arrays, traced or
    not; every static value), with equinox's error mode, which changes the trace. The
    stored program has neither a JVP nor a batching rule of its own: `jax.custom_jvp` and
    `jax.custom_batching.custom_vmap` give it `fn`'s, traced only when a caller's
    transformation reaches it (`jax.jvp` of `fn`; `jax.vmap` of `fn`), so any
    transformation gives what `fn` itself would. `fn` must return a pytree of arrays."""
    where = directory()
    if where is None:
        return fn(*args)
    mode = _compat.error_mode()
    name = f"{fn.__module__}.{fn.__qualname__}[embedded, {mode}]"
    leaves, treedef = jax.tree_util.tree_flatten(args)
    # A program over several devices cannot be called inside a caller's program over one.
    several = any(isinstance(x, jax.sharding.Mesh) and x.devices.size > 1 for x in leaves)
    k = None if several else _memo_key(name, treedef, leaves)
    if k is None or k in _UNEXPORTABLE:
        stats["uncacheable"] += 1
        return fn(*args)
    arrays = [x for x in leaves if eqx.is_array(x)]
    if k not in _EMBEDDED:
        specs = [
            jax.ShapeDtypeStruct(x.shape, x.dtype, weak_type=jax.typeof(x).weak_type)
            for x in arrays
        ]  # traced or not: the stored program takes them as inputs
        entry = _entry(where, k, fn, args, specs)
        if entry is None:
            return fn(*args)
        _EMBEDDED[k] = entry
    exported, out_tree = _EMBEDDED[k]
    dyn, static = eqx.partition(args, eqx.is_array)
    dyn_tree = jax.tree_util.tree_structure(dyn)

    def traced(*xs):  # `fn` itself, on the flat arrays: the transformations' fallback
        out = fn(*eqx.combine(jax.tree_util.tree_unflatten(dyn_tree, list(xs)), static))
        return tuple(jax.tree_util.tree_leaves(out))

    @jax.custom_jvp
    def run(*xs):
        @jax.custom_batching.custom_vmap
        def stored(*xs):
            return tuple(exported.call(*xs))

        @stored.def_vmap
        def _(axis_size, in_batched, *xs):
            axes = [0 if b else None for b in in_batched]
            out = jax.vmap(traced, in_axes=axes, axis_size=axis_size)(*xs)
            return out, tuple(True for _ in out)

        return stored(*xs)

    @run.defjvp
    def _(primals, tangents):
        return jax.jvp(traced, primals, tangents)

    return jax.tree_util.tree_unflatten(out_tree, list(run(*arrays)))
