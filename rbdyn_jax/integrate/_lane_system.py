"""What the lane loop integrates (`AbstractLaneSystem`: a model's state, possibly extended
by its sensitivities; `Plain`: the model's own), and the vector field of a whole set of
lanes as one batched state (`LaneField`).

The lane loop, the kernel and the forward sensitivities (`_sensitivity.Sensitivity`) all
integrate an `AbstractLaneSystem`; the controller and the start checks see its `primal`
state alone, so that an extended system takes the model's own steps.
"""

import abc

import equinox as eqx
from jaxtyping import Array

from ..models import AbstractRigidBody
from ._field import Guarded


class AbstractLaneSystem(eqx.Module):
    """What the lane loop integrates: a rigid-body `model`'s state, possibly extended (by
    its sensitivities, say). The loop's start checks, step-size controller and ordering
    see the model's own state alone (`primal`), so the steps are those of the model's own
    solve."""

    model: eqx.AbstractVar[AbstractRigidBody]

    @abc.abstractmethod
    def vector_field(self, t, y, args):
        """The rate of the whole (extended) state."""

    @abc.abstractmethod
    def primal(self, y):
        """The model's own state within the state `y`."""

    @abc.abstractmethod
    def extend(self, ok, y, f, y0, t):
        """The state integrated and its rate at the start `t`, from the model's checked
        start `y` (finite where `ok`), its rate `f` and the given initial state `y0`."""


class Plain(AbstractLaneSystem):
    """The model's own trajectories."""

    model: AbstractRigidBody

    def vector_field(self, t, y, args):
        return self.model.vector_field(t, y, args)

    def primal(self, y):
        return y

    def extend(self, ok, y, f, y0, t):
        return y, f


class LaneField(eqx.Module):
    """The vector field of `lanes` trajectories as one batched state (the lane axis last on
    every leaf), each lane with its own unit time `s` (`unit_time`) and `ok` flag. diffrax's
    solver step then runs on whole `(…, lanes)` arrays: its stage loop combines contiguous
    blocks instead of a vmapped loop of tiny ones (bitwise the same arithmetic), and each
    component of the state is a contiguous row of lanes, which XLA vectorises across lanes
    (with the lanes first, a component is a strided column). `system` carries a lane axis
    last when `batched`."""

    system: AbstractLaneSystem
    batched: bool = eqx.field(static=True)
    t0: Array
    span: Array

    def __call__(self, s, y, ok):  # `Guarded` per lane: the vmapped path's arithmetic
        axis = eqx.if_array(-1) if self.batched else None
        return eqx.filter_vmap(
            lambda m, s, x, ok: Guarded(m, self.t0, self.span)(s, x, ok),
            in_axes=(axis, 0, -1, 0),
            out_axes=-1,
        )(self.system, s, y, ok)
