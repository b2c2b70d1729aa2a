"""`fit`: it checks its arguments, runs the fit's compiled program (`_problem.run`) and
reads the result (`FitResult`)."""

import dataclasses
import numbers
from collections.abc import Callable, Sequence

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, PyTree

from ..integrate import make_controller
from ..models import RigidBody
from ..state import State
from ._observations import Observations
from ._optimizers import AbstractOptimizer, LevenbergMarquardt
from ._problem import Config, Optimum, parameter_labels, run
from ._residuals import DEFAULT_TOL
from ._scale import AbstractScale


class FitResult(eqx.Module):
    """The outcome of `fit`.

    **Fields:**

    - `model`: the fitted model; `y0`: fitted initial states (`State`, leading K axis).
    - `loss`: final ½ Σ r²; `loss_history`: `(steps + 1,)` loss before each step and at the
      end; `inertia_history`: `(steps + 1, 3, 3)` the inertia at each iterate (all physical).
    - `grad_norm`: |∇ loss| at the optimum over the free parameters.
    - `decrement`: ½ gᵀ(JᵀJ)⁻¹g at the optimum, the loss decrease a further Gauss–Newton step
      would bring (in units of χ²/2); `converged`: `decrement` below the optimiser's `tol`
      and everything finite.
    - `covariance`: `(P, P)` Gauss–Newton covariance `(JᵀJ)⁻¹` of the flat free parameters
      (noise levels taken as given, not rescaled by χ²), `labels`: their P names.
    - `stderr`: dict shaped like what it describes: `"inertia"` `(3, 3)` (delta method through
      `from_log_cholesky`), `"torque"` (the torque's free leaves), `"omega0"` `(K, 3)`,
      `"quat0"` `(K, 3)` (rotation vector, radians).
    - `scale_identified`: `False` when the data leave the scale of J undetermined (no torque
      and no `scale` fix, `TraceScale` or `MomentScale`); the inertia stderr is then `inf`.
    - `ill_determined`: number of directions of `JᵀJ` with eigenvalue below `rcond` × largest.
    - `notes`: tuple of sentences on identifiability and convergence.
    """

    model: RigidBody
    y0: State
    loss: Array
    loss_history: Array
    inertia_history: Array
    grad_norm: Array
    decrement: Array
    converged: bool
    covariance: Array
    labels: tuple[str, ...] = eqx.field(static=True)
    stderr: dict
    scale_identified: bool
    ill_determined: int
    notes: tuple[str, ...] = eqx.field(static=True)


PARAMS = ("inertia", "torque", "initial_conditions")


def fit(
    model: RigidBody,
    data: Observations,
    *,
    params: Sequence[str] = ("inertia", "initial_conditions"),
    torque_where: Callable | None = None,
    y0: State | None = None,
    scale: AbstractScale | None = None,
    optimizer: AbstractOptimizer = LevenbergMarquardt(),
    rcond: float = 1e-9,
    solver: diffrax.AbstractSolver = diffrax.Tsit5(),
    stepsize_controller: diffrax.AbstractStepSizeController | None = None,
    rtol: float | None = None,
    atol: float | None = None,
    max_steps: int = 4096,
    horizons: Sequence[float] | None = None,
) -> FitResult:
    """Fit the free parameters of `model` (and the initial states) to `data`.

    **Arguments:**

    - `model`: a `RigidBody` (absolute motion, docs/physics.md#eulers-equations) giving
      the structure and the initial guess (its inertia must be strictly physical, J' ≻ 0).
    - `data`: `Observations` of K trajectories.
    - `params`: which parts are free, any of `"inertia"` (log-Cholesky θ of J',
      docs/physics.md#log-cholesky-parametrisation),
      `"torque"` (the array leaves of `model.torque`, or those `torque_where(torque)` picks,
      as the `where` of `eqx.tree_at`), `"initial_conditions"` (ω0 and a rotation-vector
      correction δ of q0 = q0_guess ⊗ exp(δ), per trajectory), or one such name alone.
      Not free: held at the guess.
    - `y0`: initial guesses `State(omega (K, 3), quat (K, 4))` at `data.ts[:, 0]`; default:
      the first observed ω (zeros when ω is not observed) and the first observed attitude
      (identity when attitude is not observed), of each trajectory.
    - `scale`: fix the scale of J (an `AbstractScale`): `TraceScale(value)` (tr J = value) or
      `MomentScale(axis, value)` (the moment of inertia about `axis`, an index 0–2 or a
      3-vector); `None` (default): not fixed. Needed when the model has no torque (see
      `rbdyn_jax.identify`).
    - `optimizer`: an `AbstractOptimizer`: `LevenbergMarquardt(steps=30, tol=1e-6,
      damping=1e-3)` (default) on the residual vector (Jacobian by forward mode), or
      `Optax(tx, steps=30, tol=1e-6)`, an optax transformation (e.g. `optax.adam(1e-2)` or
      `optax.lbfgs()`) run `steps` times on the loss. Its `tol` is the convergence
      threshold on the Gauss–Newton decrement (Levenberg–Marquardt stops early once it is
      reached).
    - `rcond`: eigenvalues of JᵀJ below `rcond` × the largest count as ill-determined
      directions (0 < rcond < 1).
    - `solver`, `stepsize_controller`, `max_steps`: passed to `simulate`. `rtol`, `atol`:
      shorthand for `stepsize_controller=diffrax.PIDController(rtol, atol)`, each
      defaulting to 1e-10; giving both a controller and a tolerance is a `ValueError`.
    - `horizons`: staged horizons for long or chaotic records, increasing fractions of each
      trajectory's span ending at 1, e.g. `(0.25, 0.5, 1.0)`: fit the samples up to the
      first fraction, start the next stage from that fit, and so on (the early part of a
      record constrains the parameters before errors in them have grown over the whole of
      it). Every stage masks samples of the same arrays, so all stages share one
      compilation; each runs the `optimizer` in full.

    The whole fit (starting point, optimisation loop, covariance and standard errors) is one
    compiled program (`eqx.filter_jit`, `lax.scan` over the steps); a second fit of the same
    structure and sizes reuses it, also with other values of the optimiser's `tol`, of
    Levenberg–Marquardt's `damping`, of the scale fix's `value` and of a `PIDController`'s
    tolerances (passed as arrays). With JAX's persistent compilation cache
    configured (`jax_compilation_cache_dir`), a later process loads the fit's traced and
    compiled program from it instead of tracing and compiling it again (with `Optax` only
    where the cache can describe its transformation exactly, else it is traced).
    The solves inside the fit run with their checks as NaN: a trial point whose solve fails
    is rejected, as one whose loss went up.

    **Returns:** a `FitResult`.
    """
    if not isinstance(model, RigidBody):
        raise ValueError(f"`model` must be a RigidBody, got {type(model).__name__}.")
    if not isinstance(data, Observations):
        raise ValueError(f"`data` must be Observations, got {type(data).__name__}.")
    if scale is not None and not isinstance(scale, AbstractScale):
        raise ValueError(
            "`scale` must be None, identify.TraceScale(value) or "
            f"identify.MomentScale(axis, value), got {scale!r}."
        )
    if not isinstance(optimizer, AbstractOptimizer):
        raise ValueError(
            "`optimizer` must be identify.LevenbergMarquardt(...) or "
            "identify.Optax(tx, ...) (an optax transformation wrapped), got "
            f"{type(optimizer).__name__}."
        )
    if isinstance(params, str):  # one name, not its letters
        params = (params,)
    if isinstance(rcond, bool) or not isinstance(rcond, numbers.Real) or not 0 < rcond < 1:
        raise ValueError(f"`rcond` must be a number in (0, 1), got {rcond!r}.")
    if y0 is not None and not isinstance(y0, State):
        raise ValueError(f"`y0` must be a State(omega, quat), got {type(y0).__name__}.")
    controller = make_controller(
        stepsize_controller, rtol, atol, default_tol=DEFAULT_TOL, dtype=data.ts.dtype
    )
    if horizons is not None:
        return _staged_fit(
            model,
            data,
            horizons,
            params=params,
            torque_where=torque_where,
            y0=y0,
            scale=scale,
            optimizer=optimizer,
            rcond=rcond,
            solver=solver,
            stepsize_controller=controller,
            max_steps=max_steps,
        )
    params = tuple(params)
    for p in params:
        if p not in PARAMS:
            raise ValueError(f"`params` entries must be among {PARAMS}, got {p!r}.")
    if not params:
        raise ValueError("`params` names no free parameter.")
    K = data.num_trajectories
    if y0 is not None and (jnp.shape(y0.omega) != (K, 3) or jnp.shape(y0.quat) != (K, 4)):
        raise ValueError(f"`y0` must be a State with omega ({K}, 3) and quat ({K}, 4).")
    torque_dyn, torque_static = _torque_parts(model.torque, torque_where)
    if "torque" in params and not jax.tree_util.tree_leaves(torque_dyn):
        raise ValueError("`params` names 'torque' but the model's torque has no array leaves.")

    # The optimiser's numbers and the scale fix's value are inputs of the compiled fit:
    # other values reuse it.
    dtype = data.ts.dtype
    inputs = ("tol", "damping") if isinstance(optimizer, LevenbergMarquardt) else ("tol",)
    cfg = Config(
        solver=solver,
        stepsize_controller=controller,
        max_steps=int(max_steps),
        scale=None if scale is None else _as_inputs(scale, ("value",), dtype),
        optimizer=_as_inputs(optimizer, inputs, dtype),
        torque_static=torque_static,
        params=tuple(sorted(set(params))),
    )
    out = run(model, y0, torque_dyn, data, cfg)
    return _result(out, params, scale, optimizer, rcond)


def _as_inputs(module: eqx.Module, names: tuple[str, ...], dtype) -> eqx.Module:
    """`module` with its float fields `names` as arrays of `dtype` (inputs of a compiled
    program, where floats would be part of its structure)."""
    where = lambda m: tuple(getattr(m, n) for n in names)  # noqa: E731
    return eqx.tree_at(where, module, tuple(jnp.asarray(getattr(module, n), dtype) for n in names))


def _torque_parts(torque, torque_where: Callable | None) -> tuple[PyTree, PyTree]:
    """The torque's free leaves and the rest (`eqx.partition`): its inexact arrays, or those
    `torque_where` picks."""
    if torque_where is None:
        return eqx.partition(torque, eqx.is_inexact_array)
    spec = jax.tree_util.tree_map(lambda _: False, torque)
    picked = torque_where(spec)
    replace = (True,) * len(picked) if isinstance(picked, tuple) else True
    spec = eqx.tree_at(torque_where, spec, replace=replace)
    return eqx.partition(torque, spec)


def _result(
    out: "Optimum", params, scale: AbstractScale | None, optimizer: AbstractOptimizer, rcond: float
) -> FitResult:
    """The compiled fit's output read into a `FitResult`, with its notes on identifiability
    and convergence (NumPy: no further programs to compile)."""
    labels = parameter_labels(out.params)
    evals = np.asarray(out.eigenvalues)
    ill = int(np.sum(evals < rcond * evals.max()))
    notes = []
    scale_ok = True
    if "inertia" in params and scale is None:
        # Is the scaling of J a near-null direction of JᵀJ?
        if float(out.scale_curvature) < rcond * evals.max():
            scale_ok = False
            notes.append(
                "The data fix the inertia only up to scale (J → cJ leaves the motion "
                "unchanged, as with no torque): pass scale=TraceScale(value) or "
                "scale=MomentScale(axis, value), or include a known torque in the model."
            )
    if scale is not None and "inertia" in params:
        notes.append(f"The scale of J is fixed by the user: {scale.quantity} = {scale.value:g}.")
    if ill > (0 if scale_ok and scale is None else 1):
        notes.append(
            f"{ill} direction(s) of parameter space are ill-determined (eigenvalue of JᵀJ "
            f"below {rcond:g} × the largest): their standard errors are large."
        )
    stderr = dict(out.stderr)
    if "inertia" in stderr and not scale_ok:
        stderr["inertia"] = np.full((3, 3), np.inf)
    converged = bool(np.isfinite(float(out.loss)) and float(out.decrement) < optimizer.tol)
    if not np.isfinite(float(out.loss)):
        notes.append(
            "No solve succeeded, at the starting point nor at any point tried (a solve "
            "ran out of max_steps, or met a non-finite state): raise max_steps, or check "
            "the guess and the initial states."
        )
    elif not converged:
        notes.append(
            f"Not converged after {optimizer.steps} steps: Gauss–Newton decrement "
            f"{float(out.decrement):.3g} ≥ tol = {optimizer.tol:g}."
        )
    return FitResult(
        model=out.model,
        y0=out.y0,
        loss=out.loss,
        loss_history=out.loss_history,
        inertia_history=out.inertia_history,
        grad_norm=out.grad_norm,
        decrement=out.decrement,
        converged=converged,
        covariance=out.covariance,
        labels=labels,
        stderr=stderr,
        scale_identified=scale_ok,
        ill_determined=ill,
        notes=tuple(notes),
    )


def stage_samples(ts, mask, frac: float) -> np.ndarray:
    """The samples of a staged fit's stage: those of each trajectory's record (`mask`) at
    times up to the fraction `frac` of its span, `t0 + frac (t1 − t0)`, every sample at
    `frac = 1` (a span's rounding is allowed for, whatever the times' sign)."""
    ts, mask = np.asarray(ts), np.asarray(mask)
    rows = np.arange(ts.shape[0])
    t0 = ts[rows, np.argmax(mask, axis=1)]  # each record's first and last sample
    t1 = ts[rows, ts.shape[1] - 1 - np.argmax(mask[:, ::-1], axis=1)]
    span = t1 - t0
    return ts <= (t0 + frac * span + 1e-12 * span)[:, None]


def _staged_fit(model, data: Observations, horizons, **kwargs) -> FitResult:
    h = np.asarray(horizons, dtype=float)
    if h.ndim != 1 or h.size < 1 or np.any(h <= 0) or np.any(np.diff(h) <= 0) or h[-1] != 1:
        raise ValueError(f"`horizons` must increase within (0, 1] and end at 1, got {horizons}.")
    res, y0 = None, kwargs.pop("y0")
    for frac in h:
        keep = jnp.asarray(stage_samples(data.ts, data.mask, frac))
        stage = eqx.tree_at(
            lambda d: (d.mask_omega, d.mask_quat),
            data,
            (data.mask_omega & keep, data.mask_quat & keep),
        )
        res = fit(model, stage, y0=y0, **kwargs)
        model, y0 = res.model, res.y0
    notes = (
        *res.notes,
        f"Staged horizons {tuple(float(x) for x in h)}: each stage started "
        "from the previous fit; the result is the last (full-record) stage's.",
    )
    return dataclasses.replace(res, notes=notes)


# ---------------------------------------------------------------------------------------
# The compiled fit.
