"""A one-trajectory JAX function run on rows of lanes: `rowwise`.

A kernel that integrates a block of trajectories holds each scalar of a trajectory's state
as a row of lanes, `(block,)`, and works on rows only: a GPU kernel's registers hold rows,
and Triton takes no small matrices (shapes of 3 or 7 are not powers of two; a 3×3 `dot`
has no lanes to spread over). `rowwise(fn, *args)` traces `fn` for ONE trajectory (its
arguments' shapes without the lanes) and evaluates the trace with every array of shape S
held as a NumPy object array of shape S whose elements are rows: an elementwise operation
is applied to each element's rows, a structural one (slice, reshape, concatenate,
broadcast) rearranges the elements, a contraction (`dot_general`) or reduction is unrolled
into sums of rows, a `scan` of static length is unrolled, and a `cond` evaluates its
branches and selects per lane. The arithmetic is the trajectory's own, operation by
operation, so a model's `vector_field`, diffrax's step-size controller and a solver's
interpolant run in a kernel unchanged. An operation with no such form (a `while_loop`, a
gather, a host callback) is refused by name (`unsupported`).

An element is a JAX array of shape `()` (the same for every lane: a constant of the trace)
or `(block,)`.
"""

import jax
import jax.extend.core as jcore
import jax.numpy as jnp
import numpy as np

# Primitives applied element by element: the operands share the result's shape.
ELEMENTWISE = frozenset(
    {
        "abs",
        "acos",
        "acosh",
        "add",
        "add_any",
        "and",
        "asin",
        "asinh",
        "atan",
        "atan2",
        "atanh",
        "cbrt",
        "ceil",
        "clamp",
        "convert_element_type",
        "copy",
        "copy_p",
        "cos",
        "cosh",
        "div",
        "eq",
        "erf",
        "erfc",
        "exp",
        "exp2",
        "expm1",
        "floor",
        "ge",
        "gt",
        "integer_pow",
        "is_finite",
        "le",
        "log",
        "log1p",
        "logistic",
        "lt",
        "max",
        "min",
        "mul",
        "ne",
        "neg",
        "nextafter",
        "not",
        "or",
        "pow",
        "reduce_precision",
        "rem",
        "round",
        "rsqrt",
        "select_n",
        "sign",
        "sin",
        "sinh",
        "sqrt",
        "square",
        "stop_gradient",
        "sub",
        "tan",
        "tanh",
        "xor",
        "optimization_barrier",
    }
)
# Calls of an inner jaxpr, and the parameter holding it.
CALLS = {
    "jit": "jaxpr",
    "pjit": "jaxpr",
    "closed_call": "call_jaxpr",
    "core_call": "call_jaxpr",
    "custom_jvp_call": "call_jaxpr",
    "custom_vjp_call": "call_jaxpr",
    "custom_vjp_call_jaxpr": "fun_jaxpr",
    "checkpoint": "jaxpr",
    "remat": "jaxpr",
}
REDUCTIONS = {
    "reduce_sum": "add",
    "reduce_max": "max",
    "reduce_min": "min",
    "reduce_prod": "mul",
    "reduce_and": "and",
    "reduce_or": "or",
}
STRUCTURAL = frozenset(
    {
        "broadcast_in_dim",
        "reshape",
        "squeeze",
        "expand_dims",
        "concatenate",
        "stack",
        "slice",
        "rev",
        "transpose",
        "split",
        "iota",
        "dot_general",
        "scan",
        "cond",
    }
)
SUPPORTED = ELEMENTWISE | STRUCTURAL | frozenset(CALLS) | frozenset(REDUCTIONS)
_BINARY = {
    "add": jax.lax.add_p,
    "max": jax.lax.max_p,
    "min": jax.lax.min_p,
    "mul": jax.lax.mul_p,
    "and": jax.lax.and_p,
    "or": jax.lax.or_p,
}


# The parameters read below are JAX's jaxpr internals, which change between releases;
# tests/test_rows.py checks each form against `jax.vmap` and runs under the next JAX too.


def _open(j):
    """A jaxpr parameter as (jaxpr, constants): a closed jaxpr, or an open one (a scan's
    body and a cond's branches are open from jax 0.11)."""
    return (j.jaxpr, j.consts) if hasattr(j, "consts") else (j, ())


def _scan_counts(p) -> tuple[int, int]:
    """A scan's numbers of constants and of carries: its parameters' counts, or the groups
    of its flat input tree (jax ≥ 0.11)."""
    if "num_consts" in p:
        return p["num_consts"], p["num_carry"]
    consts, carry, _ = p["ft_in"].unpack()
    return len(consts), len(carry)


def _inner(eqn):
    """The jaxpr (and its constants) an eqn calls, or `None`."""
    name = CALLS.get(eqn.primitive.name)
    return None if name is None else _open(eqn.params[name])


def _subjaxprs(eqn):
    inner = _inner(eqn)
    if inner is not None:
        return [inner[0]]
    if eqn.primitive.name == "scan":
        return [_open(eqn.params["jaxpr"])[0]]
    if eqn.primitive.name == "cond":
        return [_open(b)[0] for b in eqn.params["branches"]]
    return []


def unsupported(jaxpr) -> set[str]:
    """The primitives of `jaxpr` (and the jaxprs it calls) that `rowwise` cannot run."""
    out = set()
    for eqn in jaxpr.eqns:
        if eqn.primitive.name not in SUPPORTED:
            out.add(eqn.primitive.name)
        for sub in _subjaxprs(eqn):
            out |= unsupported(sub)
    return out


def objects(shape, fill) -> np.ndarray:
    """An object array of `shape` with `fill(index)` at each index."""
    out = np.empty(shape, dtype=object)
    for idx in np.ndindex(*shape):
        out[idx] = fill(idx)
    return out


def _constant(val, aval) -> np.ndarray:
    if isinstance(val, jax.core.Tracer):
        raise ValueError(
            "a function run on rows closes over a traced value; pass it as an argument."
        )
    val = np.asarray(val)
    return objects(aval.shape, lambda idx: jnp.asarray(val[idx], aval.dtype))


def _lifted(elems):
    """Elements broadcast to a common shape: `()` or the rows' `(block,)`."""
    shape = max((e.shape for e in elems), key=len)
    return [e if e.shape == shape else jnp.broadcast_to(e, shape) for e in elems]


def _bind(prim, *elems, **params):
    elems = _lifted([jnp.asarray(e) for e in elems])
    if prim is jax.lax.neg_p and elems[0].shape == ():
        # A constant negated as a product by −1 (exact, signed zeros included; an unsigned
        # one as 0 − x): Pallas's Triton lowering cannot negate a literal (JAX 0.11).
        x = elems[0]
        if jnp.issubdtype(x.dtype, jnp.unsignedinteger):
            return jax.lax.sub_p.bind(jnp.zeros((), x.dtype), x)
        return jax.lax.mul_p.bind(x, jnp.asarray(-1, x.dtype))
    return prim.bind(*elems, **params)


def _elementwise(eqn, ins):
    shape = eqn.outvars[0].aval.shape

    def at(x, idx):  # NumPy's broadcasting of a size-1 axis or a lower rank
        idx = idx[len(idx) - x.ndim :]
        return x[tuple(0 if n == 1 else i for n, i in zip(x.shape, idx))]

    return [
        objects(shape, lambda idx: _bind(eqn.primitive, *(at(x, idx) for x in ins), **eqn.params))
    ]


def _identity(op, dtype):
    """The value a reduction by `op` starts from (its result over no elements)."""
    dtype = np.dtype(dtype)
    if op in ("add", "or"):
        return jnp.zeros((), dtype)
    if op in ("mul", "and"):
        return jnp.ones((), dtype)
    if dtype == np.bool_:
        return jnp.asarray(op == "min")
    if jnp.issubdtype(dtype, jnp.inexact):
        return jnp.asarray(-np.inf if op == "max" else np.inf, dtype)
    info = jnp.iinfo(dtype)
    return jnp.asarray(info.min if op == "max" else info.max, dtype)


def _fold(op, elems, dtype):
    """`elems` reduced by `op`, left to right; none: the identity. A sum of several terms
    ends with + 0 as XLA's reduction starts from 0: −0 + −0 is then +0, as there."""
    if not elems:
        return _identity(op, dtype)
    acc = elems[0]
    for e in elems[1:]:
        acc = _bind(_BINARY[op], acc, e)
    if op == "add" and len(elems) > 1:
        acc = _bind(jax.lax.add_p, acc, jnp.zeros((), acc.dtype))
    return acc


def _dot_general(eqn, lhs, rhs):
    (lc, rc), (lb, rb) = eqn.params["dimension_numbers"]
    lfree = [d for d in range(lhs.ndim) if d not in lc and d not in lb]
    rfree = [d for d in range(rhs.ndim) if d not in rc and d not in rb]
    L = np.transpose(lhs, (*lb, *lfree, *lc))
    R = np.transpose(rhs, (*rb, *rc, *rfree))
    nb, nl, nk = len(lb), len(lfree), len(lc)
    bshape, lshape = L.shape[:nb], L.shape[nb : nb + nl]
    kshape, rshape = L.shape[nb + nl :], R.shape[nb + nk :]
    aval = eqn.outvars[0].aval

    def entry(idx):
        b, i, j = idx[:nb], idx[nb : nb + nl], idx[nb + nl :]
        # The operands in the result's dtype (JAX takes a float32 and a float64 one)
        terms = [
            _bind(
                jax.lax.mul_p,
                jnp.asarray(L[b + i + k]).astype(aval.dtype),
                jnp.asarray(R[b + k + j]).astype(aval.dtype),
            )
            for k in np.ndindex(*kshape)
        ]
        return _fold("add", terms, aval.dtype).astype(aval.dtype)

    return [objects(bshape + lshape + rshape, entry)]


def _reduce(eqn, x):
    axes = tuple(eqn.params["axes"])
    keep = [d for d in range(x.ndim) if d not in axes]
    moved = np.transpose(x, (*keep, *axes))
    shape = moved.shape[: len(keep)]
    flat = moved.reshape(shape + (-1,))
    dtype = eqn.outvars[0].aval.dtype
    return [
        objects(shape, lambda idx: _fold(REDUCTIONS[eqn.primitive.name], list(flat[idx]), dtype))
    ]


def _first(x, i):
    """`x[i]` along the first axis, as an array (NumPy gives the element for a 1-D array)."""
    return x[i : i + 1].reshape(x.shape[1:])


def _scan(eqn, ins):
    p = eqn.params
    (nc, ncar), length, body = _scan_counts(p), p["length"], _open(p["jaxpr"])
    consts, carry, xs = ins[:nc], list(ins[nc : nc + ncar]), ins[nc + ncar :]
    ys = []
    steps = range(length - 1, -1, -1) if p["reverse"] else range(length)
    for i in steps:
        outs = eval_jaxpr(*body, [*consts, *carry, *(_first(x, i) for x in xs)])
        carry, y = outs[:ncar], outs[ncar:]
        ys.append(y)
    if p["reverse"]:
        ys = ys[::-1]
    stacked = [
        np.stack([y[k] for y in ys])
        if ys
        else objects(v.aval.shape, lambda idx, v=v: jnp.zeros((), v.aval.dtype))
        for k, v in enumerate(eqn.outvars[ncar:])
    ]
    return [*carry, *stacked]


def _cond(eqn, ins):
    index, ops = ins[0], ins[1:]
    branches = [eval_jaxpr(*_open(b), ops) for b in eqn.params["branches"]]
    if len(branches) == 1:
        return branches[0]
    i = index[()]
    if i.dtype == jnp.bool_ or len(branches) > 2:
        which = i
    else:
        which = i.astype(jnp.int32)
    return [
        objects(
            outs[0].shape,
            lambda idx, outs=outs: _bind(jax.lax.select_n_p, which, *(o[idx] for o in outs)),
        )
        for outs in zip(*branches)
    ]


def _apply(eqn, ins):
    name, p = eqn.primitive.name, eqn.params
    if name in ELEMENTWISE:
        return _elementwise(eqn, ins)
    inner = _inner(eqn)
    if inner is not None:
        return eval_jaxpr(inner[0], inner[1], ins)
    if name in REDUCTIONS:
        return _reduce(eqn, ins[0])
    x = ins[0] if ins else None
    if name == "broadcast_in_dim":
        bd = p["broadcast_dimensions"]
        return [
            objects(
                p["shape"],
                lambda idx: x[tuple(0 if x.shape[i] == 1 else idx[d] for i, d in enumerate(bd))],
            )
        ]
    if name == "reshape":
        return [x.reshape(p["new_sizes"])]
    if name == "squeeze":
        return [x.reshape(eqn.outvars[0].aval.shape)]
    if name == "expand_dims":
        return [x.reshape(eqn.outvars[0].aval.shape)]
    if name == "concatenate":
        return [np.concatenate(ins, axis=p["dimension"])]
    if name == "stack":
        return [np.stack(ins, axis=p["axis"])]
    if name == "slice":
        strides = p["strides"] or (1,) * x.ndim
        return [
            x[
                tuple(
                    slice(a, b, s)
                    for a, b, s in zip(p["start_indices"], p["limit_indices"], strides)
                )
            ]
        ]
    if name == "rev":
        return [np.flip(x, axis=tuple(p["dimensions"]))]
    if name == "transpose":
        return [np.transpose(x, p["permutation"])]
    if name == "split":
        cuts = np.cumsum(p["sizes"])[:-1]
        return list(np.split(x, cuts, axis=p["axis"]))
    if name == "iota":
        aval = eqn.outvars[0].aval
        d = p["dimension"]  # NumPy's: a constant, not an operation of the trace
        values = np.arange(aval.shape[d]).reshape((-1,) + (1,) * (len(aval.shape) - d - 1))
        return [_constant(np.broadcast_to(values, aval.shape), aval)]
    if name == "dot_general":
        return _dot_general(eqn, *ins)
    if name == "scan":
        return _scan(eqn, ins)
    if name == "cond":
        return _cond(eqn, ins)
    raise ValueError(f"the operation `{name}` has no form on rows of lanes.")


def eval_jaxpr(jaxpr, consts, args) -> list[np.ndarray]:
    """`jaxpr` evaluated on object arrays of rows (`rowwise`)."""
    env = {}

    def read(v):
        if isinstance(v, jcore.Literal):
            return _constant(v.val, v.aval)
        return env[v]

    for v, c in zip(jaxpr.constvars, consts):
        env[v] = _constant(c, v.aval)
    for v, a in zip(jaxpr.invars, args):
        env[v] = a
    for eqn in jaxpr.eqns:
        outs = _apply(eqn, [read(v) for v in eqn.invars])
        for v, o in zip(eqn.outvars, outs):
            if not isinstance(v, jcore.DropVar):
                env[v] = o
    return [read(v) for v in jaxpr.outvars]


def _aval(x: np.ndarray) -> jax.ShapeDtypeStruct:
    dtype = x.flat[0].dtype if x.size else jnp.result_type(float)
    return jax.ShapeDtypeStruct(x.shape, dtype)


def trace(fn, *args):
    """`fn`'s closed jaxpr for one trajectory and its output structure; `args` are pytrees
    of object arrays of rows (or of `jax.ShapeDtypeStruct`s)."""
    leaves, tree = jax.tree_util.tree_flatten(args)
    avals = [_aval(x) if isinstance(x, np.ndarray) else x for x in leaves]
    closed, out = jax.make_jaxpr(lambda *xs: fn(*tree.unflatten(xs)), return_shape=True)(*avals)
    return closed, jax.tree_util.tree_structure(out)


def rowwise(fn, *args):
    """`fn(*args)` for one trajectory, evaluated on rows of lanes: every leaf of `args` is
    an object array of the trajectory's shape whose elements are rows (`()` or `(block,)`
    JAX arrays); so is every leaf of the result."""
    closed, out_tree = trace(fn, *args)
    bad = unsupported(closed.jaxpr)
    if bad:
        raise ValueError(f"operations with no form on rows of lanes: {sorted(bad)}.")
    outs = eval_jaxpr(closed.jaxpr, closed.consts, jax.tree_util.tree_leaves(args))
    return jax.tree_util.tree_unflatten(out_tree, outs)
