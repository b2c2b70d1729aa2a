"""One trajectory's arithmetic in the unit time (`_field.unit_time`), shared by the lane
loop (`_lane_loop`) and the kernel (`_kernel_run`): the start and first step
(`lane_first`), one explicit Runge–Kutta step with its stages unrolled from the solver's
tableau (`unrolled_step`), diffrax's step-size controller on a step (`lane_control`), the
clip at t1 that `diffeqsolve` applies (`clip_floor`) and the guarded field as a diffrax
term (`guarded_term`).

The lane loop vmaps `lane_first` and `lane_control` over its lanes and runs
`unrolled_step` on its lanes-last arrays (`_lane_system.LaneField`); the kernel runs each
on rows of lanes (`_rows.rowwise`). The arithmetic per trajectory is `diffeqsolve`'s (the
unrolled stages' to round-off).
"""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

from .. import _compat
from ._field import Guarded, per_unit_time, start, where_tree
from ._lane_system import AbstractLaneSystem
from ._solution import result_code


def step_refuse(solver, controller, adjoint) -> str | None:
    """Why the lane loop and the kernel cannot run this solver, controller or adjoint, or
    `None`: they step an explicit Runge–Kutta solver by its tableau under a
    `PIDController`, and differentiate by forward sensitivities."""
    if not isinstance(solver, diffrax.AbstractERK):
        return (
            "needs an explicit Runge–Kutta solver (a `diffrax.AbstractERK`: Tsit5, "
            f"Dopri5, Dopri8, Bosh3, Heun, …), got {type(solver).__name__}"
        )
    if not isinstance(controller, diffrax.PIDController):
        return f"needs a `diffrax.PIDController`, got {type(controller).__name__}"
    if adjoint is not None:
        return (
            "differentiates by forward sensitivities and takes no `adjoint`, got "
            f"{type(adjoint).__name__}"
        )
    return None


def clip_floor(dtype) -> np.floating:
    """diffeqsolve's end-of-interval threshold (a step ending above it ends at t1) for the
    unit time's t1 = 1 (`unit_time`): 1 moved down by 100 floats, as its 100 calls of
    equinox's `prevbefore` move t1, i.e. 1 − 100·ε⁻ (ε⁻ the spacing of the floats just
    below 1; exact in the dtype). A NumPy constant."""
    dtype = np.dtype(dtype)
    return dtype.type(1) - dtype.type(100) * np.finfo(dtype).epsneg


def unrolled_step(solver, term, t0, t1, y0, args, f0):
    """One step of the explicit Runge–Kutta `solver` from `y0` at `t0` to `t1`, its stages
    unrolled from its Butcher tableau; `(y1, y_error, dense, f1)` as `solver.step` gives
    them (`f1` the FSAL stage, or `None`). `f0` is f(t0, y0) for an FSAL method.

    The arithmetic of diffrax's step (`diffrax.AbstractRungeKutta`): the increments
    kᵢ = f(tᵢ, yᵢ)·Δt with yᵢ = y0 + Σⱼ aᵢⱼ kⱼ and tᵢ = t0 + cᵢΔt (t1 where cᵢ = 1),
    y1 = y0 + Σ bⱼ kⱼ (the last stage's yᵢ for a method whose last stage is its solution),
    y_error = Σ eⱼ kⱼ, and the dense output `{y0, y1, k}` its interpolant reads. diffrax
    runs the stages as a loop over a buffer, each a dot with a row of the tableau padded
    by zeros; here each stage is a fixed sum over the stages before it, so the two round
    differently in the last bits."""
    tab = solver.tableau
    control = term.contr(t0, t1)
    dt = t1 - t0
    c = (tab.c1, *(float(x) for x in tab.c))

    def combine(out, weights, ks):  # out + Σ wⱼ kⱼ over the nonzero weights
        for w, k in zip(weights, ks):
            if w != 0:
                out = jax.tree_util.tree_map(lambda o, x, w=float(w): o + w * x, out, k)
        return out

    ks = []
    fi = None
    y_stage = y0
    for i in range(tab.num_stages):
        if i == 0 and tab.fsal:
            fi = f0
        else:
            y_stage = y0 if i == 0 else combine(y0, tab.a_lower[i - 1], ks)
            ti = t1 if c[i] == 1 else t0 + c[i] * dt
            fi = term.vf(ti, y_stage, args)
        ks.append(term.prod(fi, control))
    y1 = y_stage if tab.ssal else combine(y0, tab.b_sol, ks)
    y_error = combine(jax.tree_util.tree_map(jnp.zeros_like, y0), tab.b_error, ks)
    k = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *ks)
    return y1, y_error, dict(y0=y0, y1=y1, k=k), fi if tab.fsal else None


def guarded_term(model, t0, span):
    return _compat.wrapped_term(diffrax.ODETerm(Guarded(model, t0, span)))


def lane_first(m: AbstractLaneSystem, y0, *, controller, solver, start_time, span, dt0):
    """One trajectory's start in the unit time (`unit_time`): its `ok` flag, the state
    integrated, the first step's end, the FSAL stage f(t0, y0) in the unit time (`None`
    for a method without one), the controller's state, and how long the trajectory will
    take (|f(t0, y0)| in the controller's tolerance scale; −1 for a bad start, which goes
    first only where the rate overflowed)."""
    t0, t1 = jnp.zeros((), span.dtype), jnp.ones((), span.dtype)
    ok, y, f = start(m.model, m.primal(y0), start_time)  # f at y: the stand-in if not ok
    y_run, f_run = m.extend(ok, y, f, y0, start_time)
    term = guarded_term(m.model, start_time, span)
    tnext, cstate = controller.init(term, t0, t1, y, dt0, ok, solver.func, solver.error_order(term))
    tnext = jnp.minimum(tnext, t1)
    # An FSAL step starts from f(t0, y0), the last stage of the step before: give it
    # now, so that a refilled lane needs no extra evaluation of the field. (Another
    # method evaluates its first stage in the step.)
    sstate = per_unit_time(span, where_tree(ok, f_run, 0.0)) if solver.tableau.fsal else None
    # How long the trajectory will take: |f(t0, y0)| in the controller's tolerance
    # scale. An ordering only: no tangents through it.
    f, y_ = jax.lax.stop_gradient((f, y))
    d = sum(
        jnp.sum((a / (controller.atol + controller.rtol * jnp.abs(b))) ** 2)
        for a, b in zip(jax.tree_util.tree_leaves(f), jax.tree_util.tree_leaves(y_))
    )
    d = jnp.where(ok & ~jnp.isnan(d), d, -1.0)  # an overflow to inf goes first
    return ok, y_run, tnext, sstate, jax.tree_util.tree_map(jnp.asarray, cstate), d


def lane_control(controller, error_order, t1_floor, tprev, tnext, y, y1, y_error, cstate):
    """diffrax's step-size `controller` on one trajectory's step in the unit time: whether
    the step is kept, the next step's start and end (clipped to t1 = 1 as diffeqsolve clips
    them, `clip_floor`), the controller's state and the `RESULTS` code. A NaN error
    estimate counts as an infinite one (the step is rejected)."""
    t1 = jnp.ones((), t1_floor.dtype)
    y_error = jax.tree_util.tree_map(lambda x: jnp.where(jnp.isnan(x), jnp.inf, x), y_error)
    keep, tp, tn, _, cstate, result = controller.adapt_step_size(
        tprev, tnext, y, y1, None, y_error, error_order, cstate
    )
    tp = jnp.minimum(tp, t1)
    tn = jnp.where(tn > t1_floor, jnp.where(keep, t1, tp + 0.5 * (t1 - tp)), tn)
    cstate = jax.tree_util.tree_map(jnp.asarray, cstate)
    return keep, tp, tn, cstate, result_code(result)
