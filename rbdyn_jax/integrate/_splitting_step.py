"""`Stepper`: one composed step of the splitting in the principal frame, its stages as one
loop (`_composition.Scheme`) of the exact flows and kicks, with the split of the kinetic
energy it runs (which principal axis carries the Casimir's term), and the conversions of
the state between body axes and the principal frame.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from .._vector import split
from ..models import RigidBody
from ..state import State
from ._composition import Scheme
from ._exact_flows import (
    Principal,
    PrincipalFrame,
    _axis_flow,
    _casimir_rotation,
    _q_times,
    _two_sum,
)

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
