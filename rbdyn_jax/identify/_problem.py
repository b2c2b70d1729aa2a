"""The fit as one compiled program (`run`): from the starting point through the optimiser
to the covariance at the optimum, configured by everything but the parameters and the
data (`Config`)."""

from typing import NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, PyTree

from .. import rotation
from .._program.program import Program
from .._program.xla import QUICK_COMPILE_OPTIONS
from ..inertia import to_log_cholesky
from ..models import RigidBody
from ..state import State
from ._observations import Observations
from ._optimizers import AbstractOptimizer, Linearisation, Minimum, Objective
from ._residuals import residuals
from ._scale import AbstractScale, inertia_of, scale_direction


class Config(eqx.Module):
    """How `run` solves and optimises: everything but the parameters and the data. Array
    fields are inputs of the compiled fit (a new value reuses it); the others are part of
    its structure (a new value compiles again)."""

    solver: diffrax.AbstractSolver  # of every simulation
    stepsize_controller: diffrax.AbstractStepSizeController  # PID tolerances as arrays
    max_steps: int = eqx.field(static=True)  # solver steps per trajectory
    scale: AbstractScale | None  # the user's fix of the scale of J, if any (value an array)
    optimizer: AbstractOptimizer  # `tol` (and `damping`) as arrays of the data's dtype
    torque_static: PyTree  # the torque's parts that are not free (`eqx.partition`)
    params: tuple[str, ...] = eqx.field(static=True)  # which of `fit`'s `params` are free


# The parameters and which entry of `fit`'s `params` frees each.
_FREED_BY = {
    "theta": "inertia",
    "torque": "torque",
    "omega0": "initial_conditions",
    "dq0": "initial_conditions",
}


def _initial_guess(data: Observations) -> State:
    first = lambda m: jnp.argmax(m, axis=1)  # noqa: E731  first valid sample
    K = data.num_trajectories
    if data.omega is not None:
        omega = data.omega[jnp.arange(K), first(data.mask_omega)]
    else:
        omega = jnp.zeros((K, 3), data.ts.dtype)
    if data.quat is not None:
        quat = data.quat[jnp.arange(K), first(data.mask_quat)]
    else:
        quat = jnp.zeros((K, 4), data.ts.dtype).at[:, 0].set(1.0)
    return State(omega, quat)


def parameter_labels(p) -> tuple[str, ...]:
    """Names of the flat parameters, in `ravel_pytree` order."""
    labels = []
    for path, leaf in jax.tree_util.tree_leaves_with_path(p):
        name = jax.tree_util.keystr(path)
        labels += [name + str(list(i)) for i in np.ndindex(np.shape(leaf))]
    return tuple(labels)


class _Start(NamedTuple):
    """The starting point: the parameters, free and fixed, and the initial attitudes the
    free corrections δ rotate."""

    free: dict  # the free parameters (shaped), at the guess
    fixed: dict  # the others, held there
    q0_guess: Array  # (K, 4), unit


def _starting_point(model, y0, torque_dyn, data, cfg: Config) -> _Start:
    """The parameters at `model` and `y0` (`None`: the first observed samples)."""
    if y0 is None:
        y0 = _initial_guess(data)
    q0_guess = rotation.quat_normalize(y0.quat)
    start = {
        "theta": to_log_cholesky(model.inertia),
        "torque": torque_dyn,
        "omega0": y0.omega,
        "dq0": jnp.zeros_like(y0.omega),
    }
    free = {k: v for k, v in start.items() if _FREED_BY[k] in cfg.params}
    fixed = {k: v for k, v in start.items() if _FREED_BY[k] not in cfg.params}
    return _Start(free, fixed, q0_guess)


class _Assembled(NamedTuple):
    """A model and initial states built from the parameters."""

    model: RigidBody
    y0: State  # leading K axis


def _assemble(p, start: _Start, model, cfg: Config) -> _Assembled:
    allp = {**start.fixed, **p}
    J = inertia_of(allp["theta"], cfg.scale)
    torque = eqx.combine(allp["torque"], cfg.torque_static)
    m = eqx.tree_at(lambda x: (x.inertia, x.torque), model, (J, torque))
    quat = rotation.quat_multiply(start.q0_guess, rotation.quat_from_rotvec(allp["dq0"]))
    return _Assembled(m, State(allp["omega0"], quat))


def _objective(model, data: Observations, cfg: Config, start: _Start, unravel) -> Objective:
    """The residuals of the model and initial states the flat parameters build, their
    Jacobian by forward mode and their loss, for the optimiser."""

    def res(flat, adjoint):
        built = _assemble(unravel(flat), start, model, cfg)
        return residuals(
            built.model,
            built.y0,
            data,
            solver=cfg.solver,
            stepsize_controller=cfg.stepsize_controller,
            max_steps=cfg.max_steps,
            adjoint=adjoint,
        )

    def linearise(y) -> Linearisation:
        def both(z):
            r = res(z, diffrax.ForwardMode())
            return r, r

        Jm, r = jax.jacfwd(both, has_aux=True)(y)
        return Linearisation(Jm, r)

    def loss_fn(flat):
        r = res(flat, diffrax.RecursiveCheckpointAdjoint())
        return 0.5 * jnp.sum(r * r)

    def inertia(flat):
        allp = {**start.fixed, **unravel(flat)}
        return inertia_of(allp["theta"], cfg.scale)

    # the residuals' count: 3 a sample for ω and 3 for the attitude, where observed
    m = data.ts.size * 3 * ((data.omega is not None) + (data.quat is not None))
    return Objective(linearise=linearise, loss=loss_fn, inertia=inertia, num_residuals=m)


class Optimum(NamedTuple):
    """What the compiled fit returns."""

    params: dict  # the free parameters at the optimum, shaped like `free`
    model: RigidBody  # the fitted model
    y0: State  # the fitted initial states (leading K axis)
    stderr: dict  # as `FitResult.stderr` (the inertia's before the scale check)
    scale_curvature: Array  # vᵀ(JᵀJ)v/vᵀv along the scaling of J, v (0 if J is not free)
    loss: Array  # ½ Σ r² there
    loss_history: Array  # (steps + 1,)
    inertia_history: Array  # (steps + 1, 3, 3)
    grad_norm: Array  # |Jᵀr|
    decrement: Array  # ½ gᵀ (JᵀJ)⁻¹ g
    covariance: Array  # (JᵀJ)⁻¹ (a pseudo-inverse along a scale fix's gauge direction)
    eigenvalues: Array  # of JᵀJ, ascending


def _fit_program(model, y0, torque_dyn, data, cfg: Config) -> Optimum:
    """The whole fit: the starting point from `model` and `y0` (`None`: the first observed
    samples), the optimisation, and what `fit` reports at the optimum."""
    start = _starting_point(model, y0, torque_dyn, data, cfg)
    flat0, unravel = ravel_pytree(start.free)
    found = cfg.optimizer.minimise(_objective(model, data, cfg, start, unravel), flat0)
    return _at_optimum(found, start, unravel, model, cfg)


def _covariance(H, scale: AbstractScale | None):
    """The eigenvalues of JᵀJ `H` and the covariance `(JᵀJ)⁻¹`."""
    evals, evecs = jnp.linalg.eigh(H)
    floor = 1e-300 + 1e-15 * jnp.max(evals)
    if scale is None:  # an undetermined direction gets a huge (not a hidden) variance
        inv_evals = 1.0 / jnp.maximum(evals, floor)
    else:  # the scale fix leaves one exact gauge direction (J unchanged): pseudo-inverse
        inv_evals = jnp.where(evals > 1e-13 * jnp.max(evals), 1.0 / jnp.maximum(evals, floor), 0.0)
    return evals, evecs @ jnp.diag(inv_evals) @ evecs.T


def _at_optimum(found: Minimum, start: _Start, unravel, model, cfg: Config) -> Optimum:
    """The fitted model and initial states, the covariance and the standard errors where
    the optimiser stopped."""
    x, Jm, r = found.x, found.at.jacobian, found.at.residuals
    f = 0.5 * jnp.sum(r * r)
    H = Jm.T @ Jm
    g = Jm.T @ r
    evals, inv = _covariance(H, cfg.scale)
    p_opt = unravel(x)
    fitted = _assemble(p_opt, start, model, cfg)
    se = unravel(jnp.sqrt(jnp.diag(inv)))
    stderr, curvature = {}, jnp.zeros((), x.dtype)
    if "theta" in p_opt:  # the inertia's, by the delta method; the curvature along J → cJ
        it = np.array([lab.startswith("['theta']") for lab in parameter_labels(p_opt)])
        D = jax.jacfwd(lambda th: inertia_of(th, cfg.scale).reshape(9))(p_opt["theta"])
        cov_t = inv[np.ix_(it, it)]
        stderr["inertia"] = jnp.sqrt(jnp.clip(jnp.diag(D @ cov_t @ D.T), 0.0)).reshape(3, 3)
        v = jnp.zeros_like(x).at[np.flatnonzero(it)].set(scale_direction(p_opt["theta"]))
        curvature = v @ H @ v / (v @ v)
    if "torque" in p_opt:
        stderr["torque"] = se["torque"]
    if "omega0" in p_opt:
        stderr["omega0"] = se["omega0"]
        stderr["quat0"] = se["dq0"]
    return Optimum(
        params=p_opt,
        model=fitted.model,
        y0=fitted.y0,
        stderr=stderr,
        scale_curvature=curvature,
        loss=f,
        loss_history=found.loss_history,
        inertia_history=found.inertia_history,
        grad_norm=jnp.linalg.norm(g),
        decrement=0.5 * g @ inv @ g,
        covariance=inv,
        eigenvalues=evals,
    )


def _fit_at_full_precision(*args) -> Optimum:
    """`_fit_program` with its matrix products (the Gauss–Newton normal equations, the
    covariance) traced at full precision: at JAX's default a GPU multiplies float32 in
    TF32."""
    with jax.default_matmul_precision("highest"):
        return _fit_program(*args)


# The whole fit, one compiled program, compiled for a short first call
# (`QUICK_COMPILE_OPTIONS`). `fit` has validated its inputs, so the program is traced with
# the solves' checks as NaN: a trial point whose solve fails gives NaN residuals, which
# Levenberg–Marquardt rejects, and the program, holding no host callback, is stored by the
# caches (a later process with the cache configured loads it instead of tracing the fit).
run = Program(_fit_at_full_precision, options=QUICK_COMPILE_OPTIONS)
