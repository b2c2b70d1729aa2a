"""The optimisers `fit` runs inside its compiled program: `LevenbergMarquardt` on the residual
vector (the default) and `Optax`, any optax transformation on the loss. Each minimises an
`Objective` over the flat free parameters and returns the `Minimum` it reached."""

import abc
import math
import numbers
from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import optax
from jaxtyping import Array


class Linearisation(NamedTuple):
    """The residuals at a point and their Jacobian there."""

    jacobian: Array  # (m, P)
    residuals: Array  # (m,)


class Objective(NamedTuple):
    """What an optimiser minimises, as the compiled fit builds it: functions of the flat
    free parameters x `(P,)`."""

    linearise: Callable[[Array], Linearisation]  # r(x) and ∂r/∂x (forward mode)
    loss: Callable[[Array], Array]  # ½ Σ r(x)², differentiable in reverse mode
    inertia: Callable[[Array], Array]  # the inertia J (3, 3) at x, for the history
    num_residuals: int  # m, the length of r


class Minimum(NamedTuple):
    """Where an optimiser stopped, and how it got there."""

    x: Array  # the flat free parameters there
    at: Linearisation  # the residuals and their Jacobian there
    loss_history: Array  # (steps + 1,)
    inertia_history: Array  # (steps + 1, 3, 3)


class Iterate(NamedTuple):
    """What each optimiser step records."""

    loss: Array  # the loss at the step (LM: at the accepted point; optax: before updating)
    inertia: Array  # (3, 3), at the point after the step


def _count(steps):
    """An integer (a NumPy one included) as an int; anything else as it is, for the check."""
    if isinstance(steps, numbers.Integral) and not isinstance(steps, bool):
        return int(steps)
    return steps


class AbstractOptimizer(eqx.Module):
    """How `fit` minimises the loss: pass an instance as its `optimizer=`,
    `LevenbergMarquardt(...)` (the default) or `Optax(tx, ...)`.

    Every optimiser runs at most `steps` iterations (a positive int) inside the fit's one
    compiled program, and the fit counts as converged once the Gauss–Newton decrement
    ½ gᵀ(JᵀJ)⁻¹g at the optimum, the loss decrease a further Gauss–Newton step would
    bring, is below `tol` (≥ 0). `tol` is an input of the compiled fit: another value
    reuses it; `steps` is part of its structure.
    """

    steps: eqx.AbstractVar[int]
    tol: eqx.AbstractVar[float]

    def __check_init__(self):
        name = type(self).__name__
        if isinstance(self.steps, bool) or not isinstance(self.steps, int) or self.steps < 1:
            raise ValueError(f"{name}: `steps` must be a positive int, got {self.steps!r}.")
        if not self.tol >= 0:
            raise ValueError(f"{name}: `tol` must be ≥ 0, got {self.tol!r}.")

    @abc.abstractmethod
    def minimise(self, objective: Objective, x0: Array) -> Minimum:
        """Minimise `objective` from `x0`, traced inside the compiled fit (`tol` is then an
        array of the data's dtype)."""


class LMState(NamedTuple):
    """Levenberg–Marquardt's loop carry."""

    x: Array  # the accepted point (flat free parameters)
    r: Array  # residuals at `x`
    jacobian: Array  # their Jacobian at `x`
    loss: Array  # ½ Σ r² at `x` (inf before the first trial)
    damping: Array  # Marquardt's λ
    trial: Array  # the point the next iteration tries
    done: Array  # decrement below `tol`: the remaining iterations are skipped


class LevenbergMarquardt(AbstractOptimizer):
    """Levenberg–Marquardt on the residual vector, with Marquardt's diagonal scaling and
    the Jacobian by forward mode through the solver.

    Each iteration linearises at the trial point once (the only trace of the solve, so it
    is compiled once), accepts the point if the loss went down (dividing the damping λ by
    3, down to 1e-9) or rejects it (multiplying λ by 4), and proposes the next trial point
    from the accepted one. A trial point whose solve fails gives NaN residuals and is
    rejected, as one whose loss went up. Once the Gauss–Newton decrement at the accepted
    point is below `tol` the remaining iterations are skipped (no further solves) and the
    history repeats the optimum.

    **Arguments:**

    - `steps`: iterations, at most (default 30).
    - `tol`: the fit stops, converged, once the Gauss–Newton decrement is below it
      (default 1e-6, in units of χ²/2).
    - `damping`: Marquardt's λ at the start (default 1e-3, finite and > 0).
    """

    steps: int = eqx.field(default=30, converter=_count)
    tol: float = eqx.field(default=1e-6, converter=float)
    damping: float = eqx.field(default=1e-3, converter=float)

    def __check_init__(self):
        if not (math.isfinite(self.damping) and self.damping > 0):
            raise ValueError(
                f"LevenbergMarquardt: `damping` must be finite and positive, got {self.damping!r}."
            )

    def minimise(self, objective: Objective, x0: Array) -> Minimum:
        """`steps + 1` iterations of a `lax.scan`: entry i of the history is the accepted
        point after trial i (entry 0: `x0`); the last iteration proposes nothing, so its
        accepted point and Jacobian are the optimum."""

        def work(s: LMState, i) -> LMState:
            at_trial = objective.linearise(s.trial)
            r_try = at_trial.residuals
            f_try = 0.5 * jnp.sum(r_try * r_try)
            good = jnp.isfinite(f_try) & (f_try < s.loss)
            pick = lambda a, b: jnp.where(good, a, b)  # noqa: E731
            x, r, Jm = pick(s.trial, s.x), pick(r_try, s.r), pick(at_trial.jacobian, s.jacobian)
            f = pick(f_try, s.loss)
            lam = jnp.where(good, jnp.maximum(s.damping / 3.0, 1e-9), s.damping * 4.0)
            H = Jm.T @ Jm
            g = Jm.T @ r
            d = jnp.diag(H) + 1e-12 * jnp.max(jnp.diag(H))
            dx = -jnp.linalg.solve(H + lam * jnp.diag(d), g)
            dec = 0.5 * g @ jnp.linalg.solve(H + 1e-14 * jnp.max(d) * jnp.eye(H.shape[0]), g)
            done = jnp.isfinite(f) & (dec < self.tol)
            trial = jnp.where((i < self.steps) & ~done, x + dx, x)
            return LMState(x=x, r=r, jacobian=Jm, loss=f, damping=lam, trial=trial, done=done)

        def step(s: LMState, i):
            s = jax.lax.cond(s.done, lambda s, i: s, work, s, i)
            return s, Iterate(loss=s.loss, inertia=objective.inertia(s.x))

        m = objective.num_residuals
        init = LMState(  # NaN until a trial is accepted: a fit none of whose solves
            x=x0,  # succeeds ends with NaN residuals and loss, not converged
            r=jnp.full(m, jnp.nan, x0.dtype),
            jacobian=jnp.full((m, x0.size), jnp.nan, x0.dtype),
            loss=jnp.asarray(jnp.inf, x0.dtype),
            damping=jnp.asarray(self.damping, x0.dtype),
            trial=x0,
            done=jnp.asarray(False),
        )
        final, history = jax.lax.scan(step, init, jnp.arange(self.steps + 1))
        return Minimum(
            x=final.x,
            at=Linearisation(final.jacobian, final.r),
            loss_history=history.loss,
            inertia_history=history.inertia,
        )


class OptaxState(NamedTuple):
    """An optax optimiser's loop carry."""

    x: Array  # flat free parameters
    opt_state: optax.OptState


class Optax(AbstractOptimizer):
    """Any optax transformation run on the loss ½ Σ r² (its gradient by reverse mode through
    the solver), e.g. `Optax(optax.adam(1e-2))` or `Optax(optax.lbfgs())`. An
    `optax.GradientTransformationExtraArgs` (L-BFGS's line search) also gets the loss, its
    gradient and the loss function.

    **Arguments:**

    - `tx`: the optax `GradientTransformation`.
    - `steps`: updates (default 30), all of them run.
    - `tol`: the fit counts as converged where the Gauss–Newton decrement at the last point
      is below it (default 1e-6); it does not stop the updates.

    With JAX's persistent compilation cache configured, a later process loads the fit's
    traced program only where rbdyn_jax's cache can describe `tx` exactly (optax's own
    transformations, with arguments that are numbers); otherwise it is traced again.
    """

    tx: optax.GradientTransformation = eqx.field(static=True)
    steps: int = eqx.field(default=30, converter=_count)
    tol: float = eqx.field(default=1e-6, converter=float)

    def __check_init__(self):
        if not isinstance(self.tx, optax.GradientTransformation):
            raise ValueError(
                "Optax: `tx` must be an optax GradientTransformation, got "
                f"{type(self.tx).__name__}."
            )

    def minimise(self, objective: Objective, x0: Array) -> Minimum:
        """`steps` updates of a `lax.scan`, then the residuals and Jacobian at the last point
        (history: the loss before each update and at the end; the inertia at the start and
        after each update)."""
        opt = self.tx
        vg = jax.value_and_grad(objective.loss)

        def step(s: OptaxState, _):
            f, g = vg(s.x)
            if isinstance(opt, optax.GradientTransformationExtraArgs):
                upd, opt_state = opt.update(
                    g, s.opt_state, s.x, value=f, grad=g, value_fn=objective.loss
                )
            else:
                upd, opt_state = opt.update(g, s.opt_state, s.x)
            x_new = optax.apply_updates(s.x, upd)
            return OptaxState(x_new, opt_state), Iterate(loss=f, inertia=objective.inertia(x_new))

        final, history = jax.lax.scan(step, OptaxState(x0, opt.init(x0)), None, length=self.steps)
        x = final.x
        at_x = objective.linearise(x)
        r = at_x.residuals
        hist = jnp.concatenate([history.loss, (0.5 * jnp.sum(r * r))[None]])
        Js = jnp.concatenate([objective.inertia(x0)[None], history.inertia])
        return Minimum(x=x, at=at_x, loss_history=hist, inertia_history=Js)
