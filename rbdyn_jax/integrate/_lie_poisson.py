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

import math

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .. import _compat, rotation
from .._vector import split
from ..inertia import principal_axes
from ..models import RigidBody
from ..state import State
from ..torques import (
    BodyTorque,
    GravityGradient,
    InertialTorque,
    NoTorque,
    RestoringMoment,
    SumTorque,
    UniformGravity,
)
from ._composition import COMPOSITIONS, Scheme
from ._field import Guarded

ORDERS = tuple(COMPOSITIONS)
# The torques whose moment depends on the attitude (and, for the restoring moment, on time
# through its slow time τ = ε t) alone: the flow of L' = M(t, q), q' = 0 is the exact kick
# L ← L + h M. `NoTorque` adds nothing. Exact classes, not subclasses: a subclass may
# depend on the rates. Uniform gravity and the gravity gradient derive from a potential
# (the method is then symplectic, its energy error bounded); the others have none, and the
# method keeps its order, |q| and the free flows' structure but no energy.
KICKED = (UniformGravity, GravityGradient, RestoringMoment, BodyTorque, InertialTorque)

# The split of the kinetic energy (docs/physics.md#splitting-the-free-body): the spherical
# term |L|²/(2 I_a) of the principal axis `CASIMIR_AXIS` (0, 1, 2: moments ascending), and
# the axis flows of the other two, `OUTER` run half a step before and after `INNER`. Of the
# 6 choices (and the 6 orders of the three-axis splitting), this one's energy error is the
# smallest on the torque-free body of docs/performance.md#long-horizons (k² = 0.89; order 6
# at T/50: 1.7e-9, against 4e-9 to 8e-8 and 1.5e-7 to 3.9e-6), and the smallest or near it
# on rotations about the largest and the smallest axes.
CASIMIR_AXIS, OUTER, INNER = 1, 0, 2
# How many stages of a composed step are unrolled in its loop (`jax.lax.scan`'s `unroll`).
UNROLL = 1


def _refusal(what: str) -> str:
    return (
        f"`LiePoissonSplitting` cannot integrate {what} geometrically: it splits a "
        "`RigidBody` whose torque depends on the attitude alone (`NoTorque`, "
        "`UniformGravity`, `GravityGradient`, `RestoringMoment`, `BodyTorque`, "
        "`InertialTorque` and their sums), which acts as an exact kick. Use an adaptive "
        "solver for this model: the default `diffrax.Tsit5()`, or `diffrax.Dopri8()` "
        "with tight tolerances (docs/physics.md#what-the-splitting-cannot-treat)."
    )


def check_splittable(model) -> bool:
    """Whether `model` has a torque to kick with (False: torque-free); a `ValueError`
    naming the model or the torque where the splitting cannot treat it."""
    if type(model) is not RigidBody:
        name = type(model).__name__
        raise ValueError(
            _refusal(
                f"a `{name}`, a subclass of `RigidBody` whose equations it does not know"
                if isinstance(model, RigidBody)
                else f"a `{name}` (the relative-motion equations and the Euler-angle and Poisson "
                "state forms have no such split)"
            )
        )
    parts = model.torque.torques if isinstance(model.torque, SumTorque) else (model.torque,)
    kicked = False
    for torque in parts:
        if type(torque) is NoTorque:
            continue
        if type(torque) not in KICKED:
            raise ValueError(
                _refusal(
                    f"the torque `{type(torque).__name__}` (a moment that depends on the rates, "
                    "or one whose dependence the splitting does not know, has no exactly solved "
                    "flow of its own)"
                )
            )
        kicked = True
    return kicked


def fixed_steps(span: float, dt: float) -> int:
    """The steps of `dt` that cover `span`: ⌈span / dt⌉, a quotient within rounding of a
    whole number counting as that number (a last step that rounding would leave shorter
    than 1e-12 of `dt` is not one)."""
    return math.ceil(span / dt * (1.0 - 1e-12))


def fixed_step_controller(model, ts, controller, rtol, atol, dt0, max_steps):
    """The step-size controller of a `LiePoissonSplitting` solve, checked before it is
    traced: the model and its torque (`check_splittable`), no tolerances, a fixed-step
    controller (`diffrax.ConstantStepSize()` where none is given, or `diffrax.StepTo`), a
    positive `dt0` for `ConstantStepSize`, and, where `ts` and `dt0` are concrete, a
    `max_steps` that covers `ts` in steps of `dt0`."""
    check_splittable(model)
    if rtol is not None or atol is not None:
        raise ValueError(
            "`LiePoissonSplitting` takes fixed steps (`dt0`): `rtol` and `atol` "
            "mean nothing to it; leave them out."
        )
    if controller is None:
        controller = diffrax.ConstantStepSize()
    if not isinstance(controller, (diffrax.ConstantStepSize, diffrax.StepTo)):
        raise ValueError(
            "`LiePoissonSplitting` takes fixed steps: `stepsize_controller` "
            "must be `diffrax.ConstantStepSize()` (the default, with `dt0`) or "
            f"`diffrax.StepTo(ts)`, got {type(controller).__name__}."
        )
    if isinstance(controller, diffrax.StepTo):
        return controller
    if dt0 is None:
        raise ValueError(
            "`dt0` is the fixed step of `LiePoissonSplitting`: give it (in the "
            "unit of `ts`; a fiftieth to a hundredth of the motion's period "
            "suits order 6, docs/physics.md#choosing-the-step)."
        )
    if isinstance(dt0, jax.core.Tracer) or isinstance(ts, jax.core.Tracer):
        return controller
    if not float(dt0) > 0:
        raise ValueError(f"`dt0` must be a positive step, got {dt0!r}.")
    t = np.asarray(ts)
    steps = fixed_steps(float(t[-1]) - float(t[0]), float(dt0))
    if max_steps < steps:
        raise ValueError(
            f"`max_steps` = {max_steps} is fewer than the {steps} steps of "
            f"`dt0` = {float(dt0):g} from ts[0] to ts[-1]: give `max_steps` ≥ "
            f"{steps}."
        )
    return controller


class PrincipalFrame(eqx.Module):
    """The inertia's principal frame: `moments` (ascending), `axes` (columns: the
    principal axes in body components, right-handed) and `quat`, the attitude of the
    principal frame in the body (`R(quat) = axes`). A body attitude q becomes the principal
    frame's `q ⊗ quat`, and ω the components `axesᵀ ω`."""

    moments: Float[Array, "3"]
    axes: Float[Array, "3 3"]
    quat: Float[Array, "4"]

    @classmethod
    def of(cls, inertia) -> "PrincipalFrame":
        moments, axes = principal_axes(inertia)
        return cls(moments, axes, rotation.dcm_to_quat(axes))


def _q_times(q, p):
    """Hamilton product `q ⊗ p` on components (lists of four arrays)."""
    w, x, y, z = q
    a, b, c, d = p
    return [
        w * a - x * b - y * c - z * d,
        w * b + x * a + y * d - z * c,
        w * c - x * d + y * a + z * b,
        w * d + x * c - y * b + z * a,
    ]


def _two_sum(hi, lo, d):
    """`hi + lo + d` as a new pair `(hi, lo)`: the rounding error of the sum kept in `lo`
    (compensated summation by Knuth's TwoSum, whose last step recovers the rounding of
    `hi + b` exactly; `b = d + lo` is itself rounded, at the size of the increment's ulp).
    XLA keeps floating-point additions in the order written (no reassociation)."""
    b = d + lo
    s = hi + b
    bb = s - hi
    return s, (hi - (s - bb)) + (b - bb)


def _axis_flow(i: int, L, q, rate):
    """The exact flow of `½ d_i L_i²` for a time h, with `rate = d_i h`: L and the
    attitude turn about the principal axis i by `θ = rate L_i` (L_i kept), `L ← Rot(e_i,
    −θ) L` in body components, `q ← q ⊗ (cos θ/2, sin θ/2 e_i)`. Returns the increments of
    L (`{j: ΔL_j}`) and of q, from `cos θ − 1 = −2 sin²(θ/2)` and `cos(θ/2) − 1 =
    −sin²(θ/2) / (1 + cos(θ/2))`: small numbers, whose rounding is small against L and q."""
    j, k = (i + 1) % 3, (i + 2) % 3
    half = 0.5 * rate * L[i]
    sh, ch = jnp.sin(half), jnp.cos(half)
    s, cm = 2.0 * sh * ch, -2.0 * sh * sh  # sin θ, cos θ − 1
    dL = {j: cm * L[j] + s * L[k], k: cm * L[k] - s * L[j]}
    chm = -sh * sh / (1.0 + ch)  # cos(θ/2) − 1
    w, v = q[0], q[1:]
    dv = [None] * 3
    dw = chm * w - sh * v[i]
    dv[i], dv[j], dv[k] = chm * v[i] + sh * w, chm * v[j] + sh * v[k], chm * v[k] - sh * v[j]
    return dL, [dw, *dv]


def _casimir_rotation(L, rate, increment):
    """The rotation of the exact flow of `|L|²/(2 I_a)` for a time h, with `rate = h /
    I_a`: L kept in the body, the attitude turned about it by `φ = rate |L|`, `q ← q ⊗
    (cos φ/2, sin φ/2 L/|L|)` (the identity at L = 0, with finite derivatives there).
    Returns that quaternion, or with `increment` its difference from the identity, `(cos
    φ/2 − 1, …)`, as `_axis_flow` (for the small angle of a step; near φ = 2π the
    increment's form loses accuracy)."""
    n2 = L[0] * L[0] + L[1] * L[1] + L[2] * L[2]
    nonzero = n2 > 0
    n = jnp.sqrt(jnp.where(nonzero, n2, 1.0))
    half = 0.5 * rate * n
    sn, c = jnp.sin(half), jnp.cos(half)
    scale = jnp.where(nonzero, sn / n, 0.5 * rate)  # sin(φ/2)/|L|
    if increment:
        w = jnp.where(nonzero, -sn * sn / (1.0 + c), 0.0)  # cos(φ/2) − 1
    else:
        w = jnp.where(nonzero, c, 1.0)
    return [w, scale * L[0], scale * L[1], scale * L[2]]


class Principal(eqx.Module):
    """The state in the principal frame: the body angular momentum `L` (principal
    components) and the attitude `quat` of the principal frame, each with the rounding
    error of its compensated sums (`L_lo`, `quat_lo`: the state is `L + L_lo`, …).

    Every flow adds a small increment to the state; summed plainly, each addition's
    rounding (half an ulp of the component) would make |L| and |q| random-walk, to about
    2e-12 after 5·10⁷ steps. Compensated, what remains is the rounding of the increments,
    smaller by their size (docs/performance.md#long-horizons)."""

    L: Float[Array, "3"]
    quat: Float[Array, "4"]
    L_lo: Float[Array, "3"]
    quat_lo: Float[Array, "4"]


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


class Stepper(eqx.Module):
    """One composed step of the splitting for the model recovered from the term: the
    model, the unit time's `t0` and `span` (`_field.unit_time`; 0 and 1 for a term in
    physical time), the direction of time, the ok flag of a guarded field (`None`: none),
    the principal frame and the exact flows to run.

    `deferred` (the torque-free body): the Casimir's flow commutes with the other flows, so
    the flows of all the steps since `sync` add up to one, `q ← q ⊗ exp(½ (t − t_sync)
    L / I_a)`, applied when a state is put out (`body`) instead of at every step. At every
    step the same |L| would give its rotation the same rounding, and |q| would drift by it
    step after step."""

    model: RigidBody
    t0: Array
    span: Array
    direction: Array
    ok: Array | None
    frame: PrincipalFrame
    scheme: Scheme = eqx.field(static=True)
    deferred: bool = eqx.field(static=True)

    def advance(self, tau, p: Principal, dtau) -> Principal:
        """The principal state `p` at the solver's time `tau` advanced by `dtau` (one
        composed step; its stages as one loop, `_composition.Scheme`)."""
        s, ds = self.direction * tau, self.direction * dtau  # the term's own time
        t, h = self.t0 + s * self.span, ds * self.span  # physical time and step
        I = split(self.frame.moments)
        inv_a = 1.0 / I[CASIMIR_AXIS]
        rates = [1.0 / I[i] - inv_a for i in range(3)]

        def run(flow, coefficient, elapsed, L, q):  # L, q: (hi, lo) pairs
            c = coefficient * h
            # The increments are computed from the leading parts: the rotation of the
            # compensation terms (`lo`, an ulp) would change them by an ulp times the angle.
            Lh, qh = [x[0] for x in L], [x[0] for x in q]
            if flow == "kick":
                dL, dq = dict(enumerate(self._kick(t + elapsed * h, Lh, qh, c))), None
            elif flow == "casimir":
                dL, dq = {}, _q_times(qh, _casimir_rotation(Lh, c * inv_a, True))
            else:
                axis = int(flow)
                dL, dq = _axis_flow(axis, Lh, qh, c * rates[axis])
            L = [_two_sum(*L[m], dL[m]) if m in dL else L[m] for m in range(3)]
            if dq is not None:
                q = [_two_sum(*q[m], dq[m]) for m in range(4)]
            return L, q

        sc = self.scheme
        edge, c = sc.edge
        g = sc.gammas
        L = list(zip(split(p.L), split(p.L_lo)))
        q = list(zip(split(p.quat), split(p.quat_lo)))
        L, q = run(edge, g[0] * c, 0.0, L, q)

        def stage(carry, x):
            L, q, elapsed = carry
            gi, following = x
            for flow, fraction in sc.middle:
                L, q = run(flow, gi * fraction, elapsed, L, q)
                if flow == sc.clock:
                    elapsed = elapsed + gi * fraction
            L, q = run(edge, (gi + following) * c, elapsed, L, q)
            return (L, q, elapsed), None

        dtype = p.L.dtype
        xs = (jnp.asarray(g, dtype), jnp.asarray((*g[1:], 0.0), dtype))
        (L, q, elapsed), _ = jax.lax.scan(stage, (L, q, jnp.zeros((), dtype)), xs, unroll=UNROLL)

        def stacked(pairs, part):
            return jnp.stack([x[part] for x in pairs], axis=-1)

        return Principal(stacked(L, 0), stacked(q, 0), stacked(L, 1), stacked(q, 1))

    def guarded(self, new, old):
        """`new`, or `old` for a trajectory flagged bad (the guarded field's dy/ds = 0)."""
        if self.ok is None:
            return new
        return jax.tree_util.tree_map(lambda a, b: jnp.where(self.ok, a, b), new, old)

    def principal(self, y: State) -> Principal:
        """The state in the principal frame: `L = I Vᵀ ω`, `q ⊗ quat`."""
        f = self.frame
        V, omega = f.axes, split(y.omega)
        L = jnp.stack(
            [
                f.moments[i] * (V[0, i] * omega[0] + V[1, i] * omega[1] + V[2, i] * omega[2])
                for i in range(3)
            ],
            axis=-1,
        )
        q = jnp.stack(_q_times(split(y.quat), split(f.quat)), axis=-1)
        return Principal(L, q, jnp.zeros_like(L), jnp.zeros_like(q))

    def body(self, p: Principal, since_sync) -> State:
        """The state in body axes, `ω = V (L / I)`, `q ⊗ conj(quat)`, at the solver time
        `since_sync` after `sync` (the deferred Casimir's flow applied)."""
        L, q = split(p.L + p.L_lo), split(p.quat + p.quat_lo)
        if self.deferred:
            elapsed = self.direction * since_sync * self.span  # physical time
            q = _q_times(q, _casimir_rotation(L, elapsed / self.frame.moments[CASIMIR_AXIS], False))
        return self._body(L, q)

    def _body(self, L, q) -> State:
        f = self.frame
        V = f.axes
        wp = [L[i] / f.moments[i] for i in range(3)]
        omega = [V[i, 0] * wp[0] + V[i, 1] * wp[1] + V[i, 2] * wp[2] for i in range(3)]
        qv = split(f.quat)
        quat = _q_times(q, [qv[0], -qv[1], -qv[2], -qv[3]])
        return State(jnp.stack(omega, axis=-1), jnp.stack(quat, axis=-1))

    def _kick(self, t, L, q, h):
        """The kick's increment `h M` of L, M the model's torque at time t in principal
        components."""
        m = self.model
        y = self._body(L, q)
        M = m.torque(m.kinematics(t, y), m.inertia)
        V, M = self.frame.axes, split(M)
        return [h * (V[0, i] * M[0] + V[1, i] * M[1] + V[2, i] * M[2]) for i in range(3)]


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


__all__ = [
    "ORDERS",
    "LiePoissonSplitting",
    "check_splittable",
    "fixed_step_controller",
    "fixed_steps",
]
