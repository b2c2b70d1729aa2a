"""A call that runs the cheapest of several programs giving the outputs its caller reads.

`cheapest(programs, *args)` traces each program (a function of `args` returning a dict of
named arrays, cheapest first, the last giving every name) and returns the last one's
outputs. It is one equation in the caller's program, and JAX's dead-code elimination, which
runs on the whole program before it is lowered (and so knows which outputs are read), swaps
in the first program that gives every output still read. A plain JAX program cannot
express that choice: its dead-code elimination drops whole equations whose outputs are
not read, but cannot make one computation stand in for another.

The lane solver's derivative uses it (`integrate._sensitivity.lane_jvp`): a loss on a torque-free
body's ω alone then integrates ω's sensitivities (18 columns) instead of those of the
whole state (42), and a loss on the whole state runs the one whole solve.

Under `vmap` the programs are batched and the choice stays open; forward-mode
differentiation (a second derivative) differentiates the program chosen so far.
"""

import jax
from jax.extend import core
from jax.interpreters import ad, batching, mlir, partial_eval as pe

cheapest_p = core.Primitive("rbdyn_cheapest")
cheapest_p.multiple_results = True


def cheapest(programs, *args) -> dict:
    """The outputs (a dict of arrays) of `programs[-1](*args)`, computed by the first of
    `programs` that gives every output the caller reads (see the module docstring). Each
    program is a function of `args` (pytrees of arrays) returning a dict; each one's names
    must be among the last one's, and a name means the same array in all of them."""
    leaves, treedef = jax.tree_util.tree_flatten(args)
    avals = [jax.ShapeDtypeStruct(x.shape, x.dtype) for x in leaves]
    jaxprs, keys = [], []
    for program in programs:
        out_keys = []

        def flat(*a, program=program, out_keys=out_keys):
            out = program(*jax.tree_util.tree_unflatten(treedef, a))
            out_keys.extend(out)
            return [out[k] for k in out_keys]

        jaxprs.append(jax.make_jaxpr(flat)(*avals))
        keys.append(tuple(out_keys))
    if not all(set(k) <= set(keys[-1]) for k in keys):
        raise ValueError("every program's outputs must be among the last program's")
    chosen = len(jaxprs) - 1
    outs = cheapest_p.bind(*leaves, programs=tuple(jaxprs), keys=tuple(keys), chosen=chosen)
    return dict(zip(keys[chosen], outs))


def _run(*args, programs, keys, chosen):
    del keys
    return core.jaxpr_as_fun(programs[chosen])(*args)


def _abstract(*avals, programs, keys, chosen):
    del avals, keys
    return programs[chosen].out_avals, programs[chosen].effects


def _dce(used, eqn):
    """Dead-code elimination: the first program giving every output read."""
    params = eqn.params
    have = params["keys"][params["chosen"]]
    read = {k for k, u in zip(have, used) if u}
    if not read and not eqn.effects:
        return [False] * len(eqn.invars), None
    chosen = next(i for i, k in enumerate(params["keys"]) if read <= set(k))
    old = dict(zip(have, eqn.outvars))
    program = params["programs"][chosen]
    outvars = [
        old[k] if k in read else core.DropVar(aval)
        for k, aval in zip(params["keys"][chosen], program.out_avals)
    ]
    new = core.new_jaxpr_eqn(
        eqn.invars,
        outvars,
        cheapest_p,
        dict(params, chosen=chosen),
        program.effects,
        eqn.source_info,
        eqn.ctx,
    )
    return [True] * len(eqn.invars), new


def _batch(args, dims, *, programs, keys, chosen):
    avals = [jax.ShapeDtypeStruct(x.shape, x.dtype) for x in args]
    batched = tuple(
        jax.make_jaxpr(jax.vmap(core.jaxpr_as_fun(p), in_axes=tuple(dims), out_axes=0))(*avals)
        for p in programs
    )
    outs = cheapest_p.bind(*args, programs=batched, keys=keys, chosen=chosen)
    return outs, [0] * len(outs)


def _jvp(primals, tangents, *, programs, keys, chosen):
    del keys
    tangents = [ad.instantiate_zeros(t) for t in tangents]
    return jax.jvp(core.jaxpr_as_fun(programs[chosen]), tuple(primals), tuple(tangents))


cheapest_p.def_impl(_run)
cheapest_p.def_effectful_abstract_eval(_abstract)
mlir.register_lowering(cheapest_p, mlir.lower_fun(_run, multiple_results=True))
batching.primitive_batchers[cheapest_p] = _batch
ad.primitive_jvps[cheapest_p] = _jvp
pe.dce_rules[cheapest_p] = _dce
