"""`LiePoissonSplitting`: the rigid body split into exactly solved flows and composed to
order 2, 4 or 6, a structure-preserving `diffrax` solver
(docs/physics.md#geometric-integration).

In the principal frame of the inertia, with the body angular momentum `L = I ω`, the
kinetic energy `H = Σ L_i²/(2 I_i)` is written as `|L|²/(2 I_a)` (a function of the Casimir
|L|², whose flow turns the attitude about L and leaves L fixed in the body) plus `½ d_i L_i²`
for the two other axes i, `d_i = 1/I_i − 1/I_a` (each flow turns L and the attitude about the
principal axis i at the rate `d_i L_i`, which it keeps): three exactly solved flows, of which
the Casimir's commutes with the others — elementary rotations, as in the splittings of Touma
& Wisdom (1994) and Dullweber, Leimkuhler & McLachlan (1997). Which split and which order of
the flows gives the smallest error depends on the moments (Fassò (2003)); a = the
intermediate axis, chosen by measurement, gives the smallest energy error of the splittings
compared in docs/physics.md#splitting-the-free-body. Strang's symmetric composition of the
flows is of order 2; McLachlan's (1995) and Kahan & Li's (1997) symmetric compositions of it
are of orders 4 and 6 (`_composition`). A torque of the attitude alone — uniform gravity,
the gravity gradient, the restoring moment k(τ, ψ) with its slow time, a constant moment
fixed in the body or in space — is an exact kick `L ← L + h M(q)`, which leaves the
attitude as it is, run half a step before and after the free flows
(docs/physics.md#potential-torques-as-kicks).

Every free sub-flow is a rotation: the inertial angular momentum (of the torque-free body; a
kick changes it as the torque does) and the quaternion's norm change only by rounding, and
the energy error of the torque-free body and of the potential torques stays bounded over
exponentially long times (Hairer, Lubich & Wanner (2006), chapter IX) instead of growing as
an adaptive Runge–Kutta method's does. The rounding is kept small too: each flow's increment
is added with compensation (`Principal`), and for the torque-free body the Casimir's flow,
the same rotation at every step, is deferred to the outputs (`Stepper`), so that |L| and |q|
stay within a few 1e-14 of their values over 10⁶ periods
(docs/performance.md#long-horizons).
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from .. import _compat
from ..state import State
from ._composition import COMPOSITIONS, Scheme
from ._exact_flows import Principal, PrincipalFrame
from ._field import Guarded
from ._splittable import check_splittable
from ._splitting_step import INNER, OUTER, Stepper

ORDERS = tuple(COMPOSITIONS)


class SplittingState(eqx.Module):
    """What the solver carries from step to step: the principal frame, the state in it
    after the last step, that step's output in body axes, and the solver time `sync` since
    which the Casimir's flow is deferred (for the torque-free body, `Stepper`). A step
    starts from the state carried where its `y0` is that output (bitwise), so that the
    body-axes round trip, whose rounding would accumulate step after step (|L| and the
    quaternion's norm would drift), is taken once per output instead of once per step."""

    frame: PrincipalFrame
    principal: Principal
    y: State
    sync: Array


def _recovered(terms, args):
    """The rigid-body model behind the term, the unit time's `t0` and `span`, the
    direction of time and the ok flag (`None` for an unguarded term)."""
    term, direction = _compat.unwrapped_term(terms)
    if not isinstance(term, diffrax.ODETerm):
        raise ValueError(
            "`LiePoissonSplitting` takes one `diffrax.ODETerm` of a rigid-body "
            f"model, got {type(term).__name__}."
        )
    field = term.vector_field
    if isinstance(field, Guarded):  # the field of `simulate` / `simulate_batch`
        return field.model, field.t0, field.span, direction, args
    owner = getattr(field, "__self__", None)
    if owner is not None and getattr(field, "__func__", None) is getattr(
        type(owner), "vector_field", None
    ):  # diffrax.ODETerm(model.vector_field)
        return owner, jnp.zeros(()), jnp.ones(()), direction, None
    raise ValueError(
        "`LiePoissonSplitting` needs the rigid-body model behind the term: "
        "solve with `rbdyn_jax.simulate` / `simulate_batch`, or give "
        "`diffrax.diffeqsolve` the term `diffrax.ODETerm(model.vector_field)`; "
        f"got a term of {type(field).__name__}."
    )


class SplittingInterpolation(diffrax.AbstractLocalInterpolation):
    """Dense output of a splitting step: the state at a time inside the step is the
    composed step from its start over the part of the step elapsed, of the method's order
    and on the same manifold (unit quaternion, |L| kept), not a polynomial through the
    ends."""

    t0: Array
    t1: Array
    y0: State
    y1: State
    start: Principal
    sync: Array
    stepper: Stepper

    def evaluate(self, t0, t1=None, left=True):
        del left
        if t1 is not None:
            return jax.tree_util.tree_map(lambda a, b: a - b, self.evaluate(t1), self.evaluate(t0))
        st = self.stepper
        y = st.guarded(
            st.body(st.advance(self.t0, self.start, t0 - self.t0), t0 - self.sync), self.y0
        )
        return jax.tree_util.tree_map(
            lambda mid, end, start: jnp.where(
                t0 == self.t1, end, jnp.where(t0 == self.t0, start, mid)
            ),
            y,
            self.y1,
            self.y0,
        )


class LiePoissonSplitting(diffrax.AbstractSolver):
    """The Lie–Poisson splitting of the rigid body, of order 2, 4 or 6: a fixed-step,
    structure-preserving solver for long horizons (docs/physics.md#geometric-integration).

    The kinetic energy, in the inertia's principal frame, is split into three terms whose flows
    are exact rotations of the angular momentum and of the attitude (a Casimir's and two
    principal axes'); a torque of the attitude alone (`UniformGravity`, `GravityGradient`,
    `RestoringMoment` with its slow time, `BodyTorque`, `InertialTorque`, and their sums)
    enters as exact kicks `L ← L + h M(q)`. The flows are composed by Strang's splitting
    (order 2) and by the symmetric compositions of McLachlan (1995) (order 4, 5 stages) and
    Kahan & Li (1997) (order 6, 9 stages). The quaternion's norm is kept to rounding without
    renormalisation, and so is the inertial angular momentum of the torque-free body (within
    a few 1e-14 over 10⁶ periods); the energy error of the torque-free body and of the
    potential torques (the heavy top, the gravity-gradient body) stays bounded, without the
    linear drift of an adaptive Runge–Kutta method (docs/performance.md#long-horizons).

    Use it as any diffrax solver with a fixed step: `rb.simulate(model, y0, ts,
    solver=rb.LiePoissonSplitting(6), dt0=T / 100, max_steps=...)`; `simulate` then takes
    `diffrax.ConstantStepSize()` (rtol and atol mean nothing here). `simulate_batch` runs it
    under `Vmap` (every trajectory takes the same fixed steps, so lockstep wastes nothing;
    `Lanes` refuses it). Outputs between steps are the composed step over the part of the
    step elapsed, so they keep the method's order and norms. Differentiable by
    differentiating the steps (diffrax's default `RecursiveCheckpointAdjoint`; a
    `BacksolveAdjoint` hands the solver a term without the model, which is refused); where
    two principal moments are equal, the derivative of the principal axes (`eigh`'s) is not
    finite, and neither is the gradient with respect to the inertia.

    Takes `RigidBody` models only; another model, or a torque that depends on the rates or
    that the splitting does not know (`BalancingTransport`, a torque of your own), is
    refused with a `ValueError`: use an adaptive solver there.

    **Arguments:**

    - `order`: 2, 4 or 6 (default 6).
    """

    splitting_order: int = eqx.field(static=True)

    term_structure = diffrax.AbstractTerm
    interpolation_cls = SplittingInterpolation

    def __init__(self, order: int = 6):
        if isinstance(order, bool) or order not in ORDERS:
            raise ValueError(f"`order` must be one of {ORDERS}, got {order!r}.")
        self.splitting_order = int(order)

    def order(self, terms) -> int:
        return self.splitting_order

    def check_model(self, model) -> None:
        """Raise a `ValueError` naming the model or its torque where this solver cannot
        integrate `model` geometrically (see above); return where it can. `simulate` and
        `simulate_batch` call it before tracing."""
        check_splittable(model)

    def _stepper(self, terms, args, frame) -> Stepper:
        model, t0, span, direction, ok = _recovered(terms, args)
        gammas = COMPOSITIONS[self.splitting_order]
        outer, inner = str(OUTER), str(INNER)
        kicked = check_splittable(model)
        if kicked:  # K(h/2) ∘ Casimir(h) ∘ F(h) ∘ K(h/2)
            scheme = Scheme(
                ("kick", 0.5),
                ((outer, 0.5), (inner, 1.0), (outer, 0.5), ("casimir", 1.0)),
                gammas,
                clock=inner,
            )
        else:  # the Casimir's flow commutes with the others: deferred to the outputs
            scheme = Scheme((outer, 0.5), ((inner, 1.0),), gammas, clock=inner)
        if frame is None:
            frame = PrincipalFrame.of(model.inertia)
        return Stepper(
            model,
            jnp.asarray(t0),
            jnp.asarray(span),
            jnp.asarray(direction),
            ok,
            frame,
            scheme,
            deferred=not kicked,
        )

    def init(self, terms, t0, t1, y0, args) -> SplittingState:
        stepper = self._stepper(terms, args, None)
        return SplittingState(stepper.frame, stepper.principal(y0), y0, jnp.asarray(t0))

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del made_jump
        stepper = self._stepper(terms, args, solver_state.frame)
        carried = jnp.stack(
            [
                jnp.all(a == b)
                for a, b in zip(
                    jax.tree_util.tree_leaves(y0), jax.tree_util.tree_leaves(solver_state.y)
                )
            ]
        ).all()
        start = jax.tree_util.tree_map(
            lambda a, b: jnp.where(carried, a, b), solver_state.principal, stepper.principal(y0)
        )
        sync = jnp.where(carried, solver_state.sync, t0)
        end = stepper.guarded(stepper.advance(t0, start, t1 - t0), start)
        y1 = stepper.guarded(stepper.body(end, t1 - sync), y0)
        dense_info = dict(y0=y0, y1=y1, start=start, sync=sync, stepper=stepper)
        state = SplittingState(solver_state.frame, end, y1, sync)
        return y1, None, dense_info, state, diffrax.RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


__all__ = ["ORDERS", "LiePoissonSplitting"]
