"""Which state leaves' sensitivities a derivative must carry: a dependency analysis of the
vector field's JVP."""

import jax
import jax.extend


def reads(jaxpr) -> list[set[int]]:
    """For each output of `jaxpr`, the inputs it is computed from: a dependency analysis
    over its equations, exact through nested `jit`s and conservative (every output reads
    every input) through any other equation that holds a sub-program."""
    deps = {v: {i} for i, v in enumerate(jaxpr.invars)}

    def of(v):
        return deps.get(v, set()) if isinstance(v, jax.extend.core.Var) else set()

    for eqn in jaxpr.eqns:
        ins = [of(v) for v in eqn.invars]
        sub = eqn.params.get("jaxpr") if eqn.primitive.name in ("jit", "pjit") else None
        if sub is not None and len(sub.jaxpr.invars) == len(ins):
            outs = [set().union(*(ins[j] for j in d)) for d in reads(sub.jaxpr)]
        else:
            outs = [set().union(*ins)] * len(eqn.outvars)
        for v, d in zip(eqn.outvars, outs):
            deps[v] = d
    return [of(v) for v in jaxpr.outvars]


def closed_groups(model, t, y) -> list[tuple[int, ...]]:
    """For each leaf i of the state `y` (one trajectory), the smallest set of leaves,
    containing i, whose tangents' rates read only their own tangents (in the jaxpr of the
    field's `jax.jvp`, `reads`): the columns a sensitivity solve of leaf i must carry. For
    a torque-free body, or a torque fixed in the body, ω̇ does not read the attitude:
    (ω) for ω and (ω, q) for q; under gravity, (ω, q) for both."""
    n = len(jax.tree_util.tree_leaves(y))

    def tangent(y, dy):
        return jax.jvp(lambda y: model.vector_field(t, y, None), (y,), (dy,))[1]

    jaxpr = jax.make_jaxpr(tangent)(y, y).jaxpr
    read = [{j - n for j in d if j >= n} for d in reads(jaxpr)]
    groups = []
    for i in range(n):
        group, todo = {i}, [i]
        while todo:
            new = read[todo.pop()] - group
            group |= new
            todo += list(new)
        groups.append(tuple(sorted(group)))
    return groups
