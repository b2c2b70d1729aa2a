"""What the kernel cannot run, by name, beside the solvers, controllers and adjoints the
lane loop refuses too (`_lane_step.step_refuse`): `field_refuse`, a model whose vector
field, or its derivative, has an operation with no form on rows of lanes
(`_rows.unsupported`).

`Kernel.solve` refuses a solve by `step_refuse` before it compiles anything; the default
strategy on a GPU asks `field_refuse`, which traces the field's JVP for one trajectory
(the field and the derivative the kernel integrates for a gradient: a `custom_jvp` rule
runs only there) and keeps its verdict per structure, static values, shapes and dtypes,
so that choosing costs no trace on the next call of the same kind.
"""

import equinox as eqx
import jax

from ._field import array_axes
from ._rows import trace, unsupported


def field_refuse(model, y0s, model_axes) -> str | None:
    """Why the kernel cannot evaluate `model`'s vector field on rows of lanes (the
    operations it cannot run, by name), or `None`. Traces the field for one trajectory
    from the shapes of `model` (mapped by `model_axes`) and `y0s` (a leading batch axis);
    the verdict is kept for the next call with the same structure, static values, shapes
    and dtypes (the default's choice on a GPU then costs no trace per call)."""
    key = _signature(model, y0s, model_axes)
    try:
        verdict = _VERDICTS.get(key, _MISSING) if key is not None else _MISSING
    except (TypeError, ValueError):  # a static value that cannot be compared (an array)
        key, verdict = None, _MISSING
    if verdict is _MISSING:
        verdict = _field_refuse(model, y0s, model_axes)
        if key is not None:
            _VERDICTS[key] = verdict
            while len(_VERDICTS) > 256:  # the oldest first
                del _VERDICTS[next(iter(_VERDICTS))]
    return verdict


_VERDICTS: dict = {}
_MISSING = object()


def _signature(model, y0s, model_axes):
    """What `field_refuse`'s verdict depends on: the pytrees' structure (static fields
    included), each array's shape and dtype and each other leaf's value; `None` where a
    value is unhashable."""
    leaves, tree = jax.tree_util.tree_flatten((model, y0s, model_axes))
    key = (
        tree,
        tuple((type(x), x.shape, x.dtype) if hasattr(x, "dtype") else (type(x), x) for x in leaves),
    )
    try:
        hash(key)
    except (TypeError, ValueError):
        return None
    return key


def _field_refuse(model, y0s, model_axes) -> str | None:
    def one(x):  # an array's shape for one trajectory; another leaf as it is
        return jax.ShapeDtypeStruct(x.shape[1:], x.dtype) if hasattr(x, "shape") else x

    if model_axes is not None:
        model = eqx.filter_eval_shape(
            lambda m: eqx.filter_vmap(lambda x: x, in_axes=(array_axes(model_axes),))(m), model
        )
        model = jax.tree_util.tree_map(one, model)
    dyn, static = eqx.partition(
        model, lambda x: eqx.is_array(x) or isinstance(x, jax.ShapeDtypeStruct)
    )
    dyn = jax.tree_util.tree_map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), dyn)
    y = jax.tree_util.tree_map(one, y0s)
    t = jax.ShapeDtypeStruct((), jax.tree_util.tree_leaves(y)[0].dtype)

    def field_jvp(d, t, y):  # the field and its derivative w.r.t. the state and the model
        floats, rest = eqx.partition((d, y), eqx.is_inexact_array)

        def field(floats):
            d, y = eqx.combine(floats, rest)
            return eqx.combine(d, static).vector_field(t, y, None)

        return jax.jvp(field, (floats,), (floats,))

    closed, _ = trace(field_jvp, dyn, t, y)
    bad = unsupported(closed.jaxpr)
    if not bad:
        return None
    return (
        f"cannot run this model on rows of lanes: its vector field or its derivative uses "
        f"{sorted(bad)}, which have no form on rows (write the field on vector components)"
    )
