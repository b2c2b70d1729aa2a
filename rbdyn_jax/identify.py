"""Parameter identification: fit inertia, torque parameters and initial states to observed
trajectories through the solver (docs/physics.md#inertia, docs/physics.md#absolute-motion,
docs/physics.md#restoring-moment).

- `Observations(ts, omega=None, quat=None, sigma_omega=None, sigma_quat=None, mask=None)`:
  K trajectories of n samples (padded and masked where their lengths differ), checked once
  when built.
- `residuals(model, y0s, data, ...)`: the whitened residual vector — ω residuals divided by
  `sigma_omega`, attitude residuals as the rotation vector of `q_obs* ⊗ q_sim` (its norm is the
  geodesic angle, sign-invariant, finite gradient at zero) divided by `sigma_quat` — over all
  trajectories at once (`jax.vmap`, no Python loop over trajectories). `loss` is ½ Σ r².
- `fit(model, data, *, params=("inertia", "initial_conditions"), ...) -> FitResult`: the
  inertia free through the log-Cholesky parameters of J'
  (docs/physics.md#log-cholesky-parametrisation, every iterate is physical), the torque's
  array leaves, and the initial state of every trajectory (ω0 and a rotation-vector
  correction of q0). Levenberg–Marquardt on the residual vector (default) or
  any optax transformation, inside **one** compiled program with the Gauss–Newton covariance
  `(JᵀJ)⁻¹` at the optimum. Step-size control is a diffrax controller passed through to
  `simulate` (`stepsize_controller=`; `rtol=`/`atol=` are shorthand for a `PIDController`).

Identifiability: with no torque, Euler's equations `J ω' = J ω × ω` are unchanged by `J → cJ`,
so data fix J only up to scale. `fit` detects the near-null direction of `JᵀJ` along the
scaling of J and reports it (`FitResult.scale_identified = False`, inertia standard errors
`inf`); pass `scale=TraceScale(value)` (tr J = value) or `scale=MomentScale(axis, value)`
(the moment of inertia about `axis`) to fix the scale, or a known torque in the model.
"""

import dataclasses
import math
import numbers
from collections.abc import Callable, Sequence
from typing import NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, ArrayLike, Bool, Float, PyTree

from . import rotation
from ._program.program import Program
from ._program.xla import QUICK_COMPILE_OPTIONS
from .inertia import from_log_cholesky, to_log_cholesky
from .integrate import RESULTS, make_controller, simulate
from .models import RigidBody
from .state import State

_UNIT_TOL = 1e-6  # |q| within this of 1: renormalised silently


def _as_np(x, name):
    try:
        a = np.asarray(x, dtype=float)
    except (TypeError, ValueError) as e:
        raise ValueError(f"`{name}` must be a real array, got {type(x).__name__}.") from e
    return a


def _fill_times(t: np.ndarray, valid: np.ndarray, k: int) -> np.ndarray:
    """Replace the times of masked samples so the row is strictly increasing (the solver
    saves there; their residuals are masked out)."""
    idx = np.flatnonzero(valid)
    if idx.size < 2:
        raise ValueError(f"`ts`: trajectory {k} has fewer than 2 unmasked samples.")
    tv = t[idx]
    if not np.all(np.isfinite(tv)):
        raise ValueError(f"`ts`: trajectory {k} has a non-finite time at an unmasked sample.")
    if np.any(np.diff(tv) <= 0):
        raise ValueError(f"`ts` must be strictly increasing; trajectory {k} is not.")
    out = np.interp(np.arange(t.size), idx, tv)  # interior gaps: linear in the index
    span = tv[-1] - tv[0]
    delta = 1e-9 * span
    before, after = np.arange(t.size) < idx[0], np.arange(t.size) > idx[-1]
    out[before] = tv[0] - delta * (idx[0] - np.flatnonzero(before))
    out[after] = tv[-1] + delta * (np.flatnonzero(after) - idx[-1])
    return out


def _sigma(s, shape, name):
    if s is None:
        return np.ones(shape)
    a = _as_np(s, name)
    try:
        a = np.broadcast_to(a, shape)
    except ValueError as e:
        raise ValueError(f"`{name}` of shape {a.shape} does not broadcast to {shape}.") from e
    if not np.all(np.isfinite(a) & (a > 0)):
        raise ValueError(f"`{name}` must be finite and positive.")
    return np.array(a)


class Observations(eqx.Module):
    """Observed records of K trajectories, n samples each (checked eagerly, in NumPy).

    **Arguments:**

    - `ts`: `(n,)` times shared by every trajectory, or `(K, n)` per trajectory. Over the
      unmasked samples of each trajectory they must be finite and strictly increasing
      (`ValueError` otherwise). Times of masked samples are ignored and replaced (interior:
      linear interpolation in the sample index; padding before/after: 1e-9 × span apart) so
      that the solver can save there.
    - `omega`: `(K, n, 3)` observed body angular velocity, or `None`.
    - `quat`: `(K, n, 4)` observed attitude body → parent, scalar first, or `None`. Sign is
      irrelevant. Quaternions whose norm is within 1e-6 of 1 are renormalised; any other
      norm (zero included) at an unmasked sample is a `ValueError`, unless
      `normalise_quat=True`, which renormalises every non-zero quaternion.
    - `sigma_omega`: noise standard deviation of each ω component, broadcast to `(K, n, 3)`
      (default 1).
    - `sigma_quat`: noise standard deviation (radians) of each component of the attitude
      error's rotation vector, broadcast to `(K, n)` (default 1).
    - `mask`: `(K, n)` booleans, `False` for padding (trajectories of different lengths);
      default all `True`.
    - `euler`, `seq`, `degrees`: the attitude as Euler angles `(K, n, 3)` of sequence `seq`
      (scipy conventions, default "ZXZ" = (ψ, θ, φ)) instead of `quat`; converted to unit
      quaternions (the residual is the same geodesic angle, free of the angles'
      singularities).
    - `nan_policy`: `"raise"` (default): a NaN/inf sample at an unmasked position is a
      `ValueError` naming the field; `"mask"`: such a sample is masked for that field only.

    At least one of `omega` and `quat` must be given. **Fields:** `ts` `(K, n)`, `omega`,
    `quat`, `sigma_omega`, `sigma_quat` (broadcast, `None` where not observed), `mask`,
    and the per-field masks `mask_omega`, `mask_quat` `(K, n)` used by the loss. Masked
    samples are stored as zeros / the identity quaternion.
    """

    ts: Float[Array, "K n"]
    omega: Float[Array, "K n 3"] | None
    quat: Float[Array, "K n 4"] | None
    sigma_omega: Float[Array, "K n 3"] | None
    sigma_quat: Float[Array, "K n"] | None
    mask: Bool[Array, "K n"]
    mask_omega: Bool[Array, "K n"]
    mask_quat: Bool[Array, "K n"]

    def __init__(
        self,
        ts: Float[ArrayLike, "*K n"],
        omega: Float[ArrayLike, "K n 3"] | None = None,
        quat: Float[ArrayLike, "K n 4"] | None = None,
        sigma_omega: Float[ArrayLike, "..."] | None = None,
        sigma_quat: Float[ArrayLike, "..."] | None = None,
        mask: Bool[ArrayLike, "K n"] | None = None,
        *,
        euler: Float[ArrayLike, "K n 3"] | None = None,
        seq: str = "ZXZ",
        degrees: bool = False,
        nan_policy: str = "raise",
        normalise_quat: bool = False,
    ):
        if euler is not None:
            if quat is not None:
                raise ValueError("Give the attitude as `quat` or as `euler`, not both.")
            angles = _as_np(euler, "euler")
            if angles.ndim != 3 or angles.shape[-1] != 3:
                raise ValueError(f"`euler` must have shape (K, n, 3), got {angles.shape}.")
            if degrees:
                angles = np.radians(angles)
            quat = np.asarray(rotation.euler_to_quat(jnp.asarray(angles), seq))
        if omega is None and quat is None:
            raise ValueError("Give at least one of `omega` and `quat` (or `euler`).")
        if nan_policy not in ("raise", "mask"):
            raise ValueError(f"`nan_policy` must be 'raise' or 'mask', got {nan_policy!r}.")
        first = omega if omega is not None else quat
        first_name = "omega" if omega is not None else "quat"
        first = _as_np(first, first_name)
        if first.ndim != 3:
            raise ValueError(f"`{first_name}` must have shape (K, n, …), got {first.shape}.")
        K, n = first.shape[:2]
        t = _as_np(ts, "ts")
        if t.ndim == 1:
            t = np.broadcast_to(t, (K, n)) if t.shape == (n,) else t
        if t.shape != (K, n):
            raise ValueError(f"`ts` must have shape ({n},) or ({K}, {n}), got {t.shape}.")
        m = np.ones((K, n), bool) if mask is None else np.asarray(mask)
        if m.shape != (K, n) or m.dtype != bool:
            raise ValueError(f"`mask` must be a boolean array of shape ({K}, {n}).")

        def field(x, name, width):
            if x is None:
                return None, np.zeros((K, n), bool)
            a = _as_np(x, name)
            if a.shape != (K, n, width):
                raise ValueError(f"`{name}` must have shape ({K}, {n}, {width}), got {a.shape}.")
            finite = np.all(np.isfinite(a), axis=-1)
            if nan_policy == "raise" and np.any(m & ~finite):
                k, i = np.argwhere(m & ~finite)[0]
                raise ValueError(
                    f"`{name}` has a non-finite sample (trajectory {k}, sample {i}); mask it "
                    "or pass `nan_policy='mask'`."
                )
            fm = m & finite
            return np.where(fm[..., None], a, 0.0), fm

        w, m_w = field(omega, "omega", 3)
        q, m_q = field(quat, "quat", 4)
        if q is not None:
            norm = np.linalg.norm(q, axis=-1)
            bad = m_q & ((norm == 0) | ((not normalise_quat) & (np.abs(norm - 1) > _UNIT_TOL)))
            if np.any(bad):
                k, i = np.argwhere(bad)[0]
                raise ValueError(
                    f"`quat` is not a unit quaternion at trajectory {k}, sample {i} "
                    f"(norm {norm[k, i]:.6g}); pass `normalise_quat=True` to renormalise."
                )
            ident = np.array([1.0, 0.0, 0.0, 0.0])
            q = np.where(m_q[..., None], q / np.where(m_q, norm, 1.0)[..., None], ident)
        valid = m_w | m_q
        t = np.stack([_fill_times(t[k], valid[k], k) for k in range(K)])
        self.ts = jnp.asarray(t)
        self.omega = None if w is None else jnp.asarray(w)
        self.quat = None if q is None else jnp.asarray(q)
        self.sigma_omega = None if w is None else jnp.asarray(_sigma(sigma_omega, (K, n, 3),
                                                                     "sigma_omega"))
        self.sigma_quat = None if q is None else jnp.asarray(_sigma(sigma_quat, (K, n),
                                                                    "sigma_quat"))
        self.mask = jnp.asarray(m)
        self.mask_omega = jnp.asarray(m_w)
        self.mask_quat = jnp.asarray(m_q)

    @property
    def num_trajectories(self) -> int:
        return self.ts.shape[0]


# ---------------------------------------------------------------------------------------
# Residuals and loss.

_TOL = 1e-10  # identify's default rtol and atol: solve errors far below the noise


def _simulate_all(model, y0s: State, data: Observations, solver, stepsize_controller,
                  max_steps, adjoint):
    def one(y0, ts):
        return simulate(model, y0, ts, solver=solver, stepsize_controller=stepsize_controller,
                        max_steps=max_steps, adjoint=adjoint, throw=False)

    return jax.vmap(one)(y0s, data.ts)


def residuals(
    model: RigidBody,
    y0s: State,
    data: Observations,
    *,
    solver: diffrax.AbstractSolver = diffrax.Tsit5(),
    stepsize_controller: diffrax.AbstractStepSizeController | None = None,
    rtol: float | None = None,
    atol: float | None = None,
    max_steps: int = 4096,
    adjoint: diffrax.AbstractAdjoint = diffrax.RecursiveCheckpointAdjoint(),
) -> Float[Array, " m"]:
    """Whitened residual vector of `model` started at `y0s` (`State` with a leading K axis)
    against `data`: `[(ω_sim − ω_obs)/σ_ω ; rotvec(q_obs* ⊗ q_sim)/σ_q]` flattened, zero at
    masked samples (docs/physics.md#quaternion-kinematics,
    docs/physics.md#eulers-equations). `|rotvec|` is the geodesic angle between observed
    and simulated attitude, invariant to the sign of either quaternion. A failed solve gives
    NaN residuals for its trajectory.

    `solver`, `stepsize_controller`, `max_steps`, `adjoint` are passed to `simulate`;
    `rtol`, `atol` are shorthand for `stepsize_controller=diffrax.PIDController(rtol, atol)`,
    each defaulting to 1e-10 (giving both a controller and a tolerance is a `ValueError`)."""
    controller = make_controller(stepsize_controller, rtol, atol, default_tol=_TOL)
    traj = _simulate_all(model, y0s, data, solver, controller, max_steps, adjoint)
    ok = (traj.result == RESULTS.successful)[:, None]
    parts = []
    if data.omega is not None:
        r = (traj.ys.omega - data.omega) / data.sigma_omega
        r = jnp.where(data.mask_omega[..., None], r, 0.0)
        parts.append(jnp.where(ok[..., None], r, jnp.nan).reshape(-1))
    if data.quat is not None:
        dq = rotation.quat_multiply(rotation.quat_conjugate(data.quat), traj.ys.quat)
        r = rotation.quat_to_rotvec(dq) / data.sigma_quat[..., None]
        r = jnp.where(data.mask_quat[..., None], r, 0.0)
        parts.append(jnp.where(ok[..., None], r, jnp.nan).reshape(-1))
    return jnp.concatenate(parts)


def loss(model: RigidBody, y0s: State, data: Observations, **kwargs) -> Float[Array, ""]:
    """½ Σ r² of `residuals` (the negative log-likelihood under Gaussian noise, up to a
    constant). Keyword arguments as `residuals`."""
    r = residuals(model, y0s, data, **kwargs)
    return 0.5 * jnp.sum(r * r)


# ---------------------------------------------------------------------------------------
# Fixing the scale of J.


def _check_scale_value(cls: str, value: float):
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{cls}: `value` must be finite and positive, got {value!r}.")


class TraceScale(eqx.Module):
    """Fix the scale of J by its trace: the fit holds tr J = `value` (finite, > 0).

    Data that fix J only up to a factor c (no torque, or one that scales with J: see the
    module docstring) leave the choice of c to the user; `fit(..., scale=TraceScale(v))`
    makes it. `of(J)` is the quantity held at `value`.
    """

    value: float = eqx.field(converter=float)

    def __check_init__(self):
        _check_scale_value("TraceScale", self.value)

    @property
    def quantity(self) -> str:
        """The name of the quantity held at `value` (for `FitResult.notes`)."""
        return "tr J"

    def of(self, J: Float[Array, "3 3"]) -> Float[Array, ""]:
        """tr J."""
        return jnp.trace(J)


def _axis(axis):
    """An index stays an int; a vector becomes a tuple of floats (checked by `MomentScale`)."""
    if isinstance(axis, numbers.Integral) and not isinstance(axis, bool):
        return int(axis)
    try:
        a = np.asarray(axis, dtype=float)
    except (TypeError, ValueError):
        a = None
    if a is None or a.ndim != 1:
        raise ValueError("MomentScale: `axis` must be an index 0, 1 or 2 or a non-zero "
                         f"3-vector, got {axis!r}.")
    return tuple(a.tolist())


class MomentScale(eqx.Module):
    """Fix the scale of J by a moment of inertia: the fit holds nᵀ J n = `value` (finite,
    > 0) about the body axis n given by `axis`: an index 0, 1 or 2 (n the unit vector along
    it, so J[axis, axis] = `value`) or a non-zero 3-vector (normalised).

    For data that fix J only up to scale (see `TraceScale`); use it when one moment of
    inertia is known, e.g. measured about a symmetry axis. `of(J)` is the quantity held at
    `value`.
    """

    axis: int | tuple[float, float, float] = eqx.field(converter=_axis)
    value: float = eqx.field(converter=float)

    def __check_init__(self):
        if isinstance(self.axis, int):
            if not 0 <= self.axis < 3:
                raise ValueError(f"MomentScale: `axis` index must be 0, 1 or 2, got {self.axis}.")
        elif (len(self.axis) != 3 or not all(map(math.isfinite, self.axis))
              or not any(self.axis)):
            raise ValueError("MomentScale: `axis` must be an index 0, 1 or 2 or a non-zero "
                             f"3-vector, got {self.axis}.")
        _check_scale_value("MomentScale", self.value)

    @property
    def direction(self) -> np.ndarray:
        """The unit vector n."""
        n = np.eye(3)[self.axis] if isinstance(self.axis, int) else np.asarray(self.axis)
        return n / np.linalg.norm(n)

    @property
    def quantity(self) -> str:
        """The name of the quantity held at `value` (for `FitResult.notes`)."""
        if isinstance(self.axis, int):
            return f"J[{self.axis}, {self.axis}]"
        return "nᵀ J n (n = ({:.4g}, {:.4g}, {:.4g}))".format(*self.direction)

    def of(self, J: Float[Array, "3 3"]) -> Float[Array, ""]:
        """nᵀ J n, n the unit `direction`."""
        n = jnp.asarray(self.direction, dtype=J.dtype)
        return n @ J @ n


def _inertia_of(theta, scale: TraceScale | MomentScale | None):
    """J from its log-Cholesky parameters, rescaled onto the `scale` fix if any."""
    J = from_log_cholesky(theta)
    if scale is not None:
        J = J * (scale.value / scale.of(J))
    return J


def _scale_direction(theta):
    """d theta / d log c for J → cJ: L → √c L."""
    half = jnp.full((3,), 0.5, dtype=theta.dtype)
    return jnp.concatenate([half, 0.5 * theta[3:]])


# ---------------------------------------------------------------------------------------
# Fitting.


class FitResult(eqx.Module):
    """The outcome of `fit`.

    **Fields:**

    - `model`: the fitted model; `y0`: fitted initial states (`State`, leading K axis).
    - `loss`: final ½ Σ r²; `loss_history`: `(steps + 1,)` loss before each step and at the
      end; `inertia_history`: `(steps + 1, 3, 3)` the inertia at each iterate (all physical).
    - `grad_norm`: |∇ loss| at the optimum over the free parameters.
    - `decrement`: ½ gᵀ(JᵀJ)⁻¹g at the optimum, the loss decrease a further Gauss–Newton step
      would bring (in units of χ²/2); `converged`: `decrement < tol` and everything finite.
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


_PARAMS = ("inertia", "torque", "initial_conditions")


def fit(
    model: RigidBody,
    data: Observations,
    *,
    params: Sequence[str] = ("inertia", "initial_conditions"),
    torque_where: Callable | None = None,
    y0: State | None = None,
    scale: TraceScale | MomentScale | None = None,
    optimizer: optax.GradientTransformation | None = None,
    steps: int = 30,
    tol: float = 1e-6,
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
      correction δ of q0 = q0_guess ⊗ exp(δ), per trajectory). Not free: held at the guess.
    - `y0`: initial guesses `State(omega (K, 3), quat (K, 4))` at `data.ts[:, 0]`; default:
      the first observed ω (zeros when ω is not observed) and the first observed attitude
      (identity when attitude is not observed), of each trajectory.
    - `scale`: fix the scale of J: `TraceScale(value)` (tr J = value) or
      `MomentScale(axis, value)` (the moment of inertia about `axis`, an index 0–2 or a
      3-vector). Needed when the model has no torque (see the module docstring).
    - `optimizer`: `None` (default): Levenberg–Marquardt on the residual vector (Jacobian by
      forward mode), `steps` iterations; or an optax transformation (e.g.
      `optax.chain(optax.adam(1e-2))` or `optax.lbfgs()`) run `steps` times on the loss.
    - `tol`: convergence threshold on the Gauss–Newton decrement (Levenberg–Marquardt stops
      early once it is reached); `rcond`: eigenvalues of
      JᵀJ below `rcond` × the largest count as ill-determined directions.
    - `solver`, `stepsize_controller`, `max_steps`: passed to `simulate`. `rtol`, `atol`:
      shorthand for `stepsize_controller=diffrax.PIDController(rtol, atol)`, each
      defaulting to 1e-10; giving both a controller and a tolerance is a `ValueError`.
    - `horizons`: staged horizons for long or chaotic records, increasing fractions of each
      trajectory's span ending at 1, e.g. `(0.25, 0.5, 1.0)`: fit the samples up to the
      first fraction, start the next stage from that fit, and so on (the early part of a
      record constrains the parameters before errors in them have grown over the whole of
      it). Every stage masks samples of the same arrays, so all stages share one
      compilation.

    The whole fit (starting point, optimisation loop, covariance and standard errors) is one
    compiled program (`eqx.filter_jit`, `lax.scan` over the steps); a second fit of the same
    structure and sizes reuses it, also with other values of `tol` and of a
    `PIDController`'s tolerances (passed as arrays). With JAX's persistent compilation cache
    configured (`jax_compilation_cache_dir`), a later process loads the fit's traced and
    compiled program from it instead of tracing and compiling it again (a fit with an optax
    `optimizer` only where the cache can describe the optimizer exactly, else it is traced).
    The solves inside the fit run with their checks as NaN: a trial point whose solve fails
    is rejected, as one whose loss went up.

    **Returns:** a `FitResult`.
    """
    if not isinstance(model, RigidBody):
        raise ValueError(f"`model` must be a RigidBody, got {type(model).__name__}.")
    if not isinstance(data, Observations):
        raise ValueError(f"`data` must be Observations, got {type(data).__name__}.")
    if scale is not None and not isinstance(scale, (TraceScale, MomentScale)):
        raise ValueError("`scale` must be None, identify.TraceScale(value) or "
                         f"identify.MomentScale(axis, value), got {scale!r}.")
    controller = make_controller(stepsize_controller, rtol, atol, default_tol=_TOL,
                                 dtype=data.ts.dtype)
    if horizons is not None:
        return _staged_fit(model, data, horizons, params=params, torque_where=torque_where,
                           y0=y0, scale=scale, optimizer=optimizer, steps=steps, tol=tol,
                           rcond=rcond, solver=solver, stepsize_controller=controller,
                           max_steps=max_steps)
    params = tuple(params)
    for p in params:
        if p not in _PARAMS:
            raise ValueError(f"`params` entries must be among {_PARAMS}, got {p!r}.")
    if not params:
        raise ValueError("`params` names no free parameter.")
    if not isinstance(steps, numbers.Integral) or steps < 1:
        raise ValueError(f"`steps` must be a positive int, got {steps!r}.")
    K = data.num_trajectories

    if y0 is not None and (jnp.shape(y0.omega) != (K, 3) or jnp.shape(y0.quat) != (K, 4)):
        raise ValueError(f"`y0` must be a State with omega ({K}, 3) and quat ({K}, 4).")

    # The torque's free leaves and the rest.
    torque_dyn, torque_static = eqx.partition(model.torque, eqx.is_inexact_array)
    if torque_where is not None:
        spec = jax.tree_util.tree_map(lambda _: False, model.torque)
        picked = torque_where(spec)
        replace = (True,) * len(picked) if isinstance(picked, tuple) else True
        spec = eqx.tree_at(torque_where, spec, replace=replace)
        torque_dyn, torque_static = eqx.partition(model.torque, spec)
    if "torque" in params and not jax.tree_util.tree_leaves(torque_dyn):
        raise ValueError("`params` names 'torque' but the model's torque has no array leaves.")

    cfg = _Config(solver=solver, stepsize_controller=controller,
                  tol=jnp.asarray(tol, data.ts.dtype), max_steps=int(max_steps), steps=int(steps),
                  scale=scale, optimizer=optimizer, torque_static=torque_static,
                  params=tuple(sorted(set(params))))
    out = _run(model, y0, torque_dyn, data, cfg)

    # Read the result (NumPy: no further programs to compile).
    labels = _labels(out.params)
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
    converged = bool(np.isfinite(float(out.loss)) and float(out.decrement) < tol)
    if not converged:
        notes.append(
            f"Not converged after {steps} steps: Gauss–Newton decrement "
            f"{float(out.decrement):.3g} ≥ tol = {tol:g}."
        )
    return FitResult(
        model=out.model, y0=out.y0, loss=out.loss, loss_history=out.loss_history,
        inertia_history=out.inertia_history, grad_norm=out.grad_norm,
        decrement=out.decrement, converged=converged, covariance=out.covariance, labels=labels,
        stderr=stderr, scale_identified=scale_ok, ill_determined=ill, notes=tuple(notes),
    )


def _staged_fit(model, data: Observations, horizons, **kwargs) -> FitResult:
    h = np.asarray(horizons, dtype=float)
    if h.ndim != 1 or h.size < 1 or np.any(h <= 0) or np.any(np.diff(h) <= 0) or h[-1] != 1:
        raise ValueError(f"`horizons` must increase within (0, 1] and end at 1, got {horizons}.")
    ts = np.asarray(data.ts)
    mask = np.asarray(data.mask)
    t0 = np.array([t[m][0] for t, m in zip(ts, mask)])
    t1 = np.array([t[m][-1] for t, m in zip(ts, mask)])
    res, y0 = None, kwargs.pop("y0")
    for frac in h:
        keep = jnp.asarray(ts <= (t0 + frac * (t1 - t0))[:, None] * (1 + 1e-12))
        stage = eqx.tree_at(lambda d: (d.mask_omega, d.mask_quat), data,
                            (data.mask_omega & keep, data.mask_quat & keep))
        res = fit(model, stage, y0=y0, **kwargs)
        model, y0 = res.model, res.y0
    notes = (*res.notes, f"Staged horizons {tuple(float(x) for x in h)}: each stage started "
             "from the previous fit; the result is the last (full-record) stage's.")
    return dataclasses.replace(res, notes=notes)


class _Config(eqx.Module):
    """How `_run` solves and optimises: everything but the parameters and the data. Array
    fields are inputs of the compiled fit (a new value reuses it); the others are part of
    its structure (a new value compiles again)."""

    solver: diffrax.AbstractSolver  # of every simulation
    stepsize_controller: diffrax.AbstractStepSizeController  # PID tolerances as arrays
    tol: Float[Array, ""]  # Levenberg–Marquardt stops once the decrement is below it
    max_steps: int = eqx.field(static=True)  # solver steps per trajectory
    steps: int = eqx.field(static=True)  # optimiser iterations
    scale: TraceScale | MomentScale | None  # the user's fix of the scale of J, if any
    optimizer: optax.GradientTransformation | None = eqx.field(static=True)  # None: LM
    torque_static: PyTree  # the torque's parts that are not free (`eqx.partition`)
    params: tuple[str, ...] = eqx.field(static=True)  # which of `_PARAMS` are free


# The parameters and which entry of `fit`'s `params` frees each.
_FREED_BY = {"theta": "inertia", "torque": "torque", "omega0": "initial_conditions",
             "dq0": "initial_conditions"}


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


def _labels(p) -> tuple[str, ...]:
    """Names of the flat parameters, in `ravel_pytree` order."""
    labels = []
    for path, leaf in jax.tree_util.tree_leaves_with_path(p):
        name = jax.tree_util.keystr(path)
        labels += [name + str(list(i)) for i in np.ndindex(np.shape(leaf))]
    return tuple(labels)


class _Assembled(NamedTuple):
    """A model and initial states built from the parameters."""

    model: RigidBody
    y0: State  # leading K axis


def _assemble(p, fixed, q0_guess, model, cfg: _Config) -> _Assembled:
    allp = {**fixed, **p}
    J = _inertia_of(allp["theta"], cfg.scale)
    torque = eqx.combine(allp["torque"], cfg.torque_static)
    m = eqx.tree_at(lambda x: (x.inertia, x.torque), model, (J, torque))
    quat = rotation.quat_multiply(q0_guess, rotation.quat_from_rotvec(allp["dq0"]))
    return _Assembled(m, State(allp["omega0"], quat))


class _Linearisation(NamedTuple):
    """The residuals at a point and their Jacobian there."""

    jacobian: Array  # (m, P)
    residuals: Array  # (m,)


class _LMState(NamedTuple):
    """Levenberg–Marquardt's loop carry."""

    x: Array  # the accepted point (flat free parameters)
    r: Array  # residuals at `x`
    jacobian: Array  # their Jacobian at `x`
    loss: Array  # ½ Σ r² at `x` (inf before the first trial)
    damping: Array  # Marquardt's λ
    trial: Array  # the point the next iteration tries
    done: Array  # decrement below `tol`: the remaining iterations are skipped


class _OptaxState(NamedTuple):
    """An optax optimiser's loop carry."""

    x: Array  # flat free parameters
    opt_state: optax.OptState


class _Iterate(NamedTuple):
    """What each optimiser step records."""

    loss: Array  # the loss at the step (LM: at the accepted point; optax: before updating)
    inertia: Array  # (3, 3), at the point after the step


class _Optimum(NamedTuple):
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


def _fit_program(model, y0, torque_dyn, data, cfg: _Config) -> _Optimum:
    """The whole fit: the starting point from `model` and `y0` (`None`: the first observed
    samples), the optimisation, and what `fit` reports at the optimum."""
    if y0 is None:
        y0 = _initial_guess(data)
    q0_guess = rotation.quat_normalize(y0.quat)
    start = {"theta": to_log_cholesky(model.inertia), "torque": torque_dyn,
             "omega0": y0.omega, "dq0": jnp.zeros_like(y0.omega)}
    free = {k: v for k, v in start.items() if _FREED_BY[k] in cfg.params}
    fixed = {k: v for k, v in start.items() if _FREED_BY[k] not in cfg.params}
    flat0, unravel = ravel_pytree(free)

    def res(flat, adjoint):
        built = _assemble(unravel(flat), fixed, q0_guess, model, cfg)
        return residuals(built.model, built.y0, data, solver=cfg.solver,
                         stepsize_controller=cfg.stepsize_controller,
                         max_steps=cfg.max_steps, adjoint=adjoint)

    def res_fwd(flat):
        return res(flat, diffrax.ForwardMode())

    def loss_fn(flat):
        r = res(flat, diffrax.RecursiveCheckpointAdjoint())
        return 0.5 * jnp.sum(r * r)

    def inertia(flat):
        allp = {**fixed, **unravel(flat)}
        return _inertia_of(allp["theta"], cfg.scale)

    def lin(y) -> _Linearisation:
        def both(z):
            r = res_fwd(z)
            return r, r

        Jm, r = jax.jacfwd(both, has_aux=True)(y)
        return _Linearisation(Jm, r)

    if cfg.optimizer is None:
        # Levenberg–Marquardt (Marquardt's diagonal scaling). Each iteration linearises at
        # the trial point once (the only trace of the solve, so compile once), accepts it if
        # the loss went down, and proposes the next trial point from the accepted one. The
        # last iteration proposes nothing: its accepted point and Jacobian are the optimum.
        # Once the Gauss–Newton decrement ½ gᵀ(JᵀJ)⁻¹g at the accepted point is below `tol`
        # (the loss cannot fall by more), the remaining iterations are skipped (`lax.cond`:
        # no further solves) and the history repeats the optimum.
        def work(s: _LMState, i) -> _LMState:
            at_trial = lin(s.trial)
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
            done = jnp.isfinite(f) & (dec < cfg.tol)
            trial = jnp.where((i < cfg.steps) & ~done, x + dx, x)
            return _LMState(x=x, r=r, jacobian=Jm, loss=f, damping=lam, trial=trial, done=done)

        def step(s: _LMState, i):
            s = jax.lax.cond(s.done, lambda s, i: s, work, s, i)
            return s, _Iterate(loss=s.loss, inertia=inertia(s.x))

        # the residuals' count: 3 a sample for ω and 3 for the attitude, where observed
        m = data.ts.size * 3 * ((data.omega is not None) + (data.quat is not None))
        init = _LMState(x=flat0, r=jnp.zeros(m, flat0.dtype),
                        jacobian=jnp.zeros((m, flat0.size), flat0.dtype),
                        loss=jnp.asarray(jnp.inf, flat0.dtype),
                        damping=jnp.asarray(1e-3, flat0.dtype), trial=flat0,
                        done=jnp.asarray(False))
        final, history = jax.lax.scan(step, init, jnp.arange(cfg.steps + 1))
        # entry i: the accepted point after trial i (entry 0: the initial guess)
        x, r, Jm = final.x, final.r, final.jacobian
        hist, Js = history.loss, history.inertia
    else:
        opt = cfg.optimizer
        vg = jax.value_and_grad(loss_fn)

        def step(s: _OptaxState, _):
            f, g = vg(s.x)
            if isinstance(opt, optax.GradientTransformationExtraArgs):
                upd, opt_state = opt.update(g, s.opt_state, s.x, value=f, grad=g,
                                            value_fn=loss_fn)
            else:
                upd, opt_state = opt.update(g, s.opt_state, s.x)
            x_new = optax.apply_updates(s.x, upd)
            return _OptaxState(x_new, opt_state), _Iterate(loss=f, inertia=inertia(x_new))

        final, history = jax.lax.scan(step, _OptaxState(flat0, opt.init(flat0)), None,
                                      length=cfg.steps)
        x = final.x
        at_x = lin(x)
        Jm, r = at_x.jacobian, at_x.residuals
        hist = jnp.concatenate([history.loss, (0.5 * jnp.sum(r * r))[None]])
        Js = jnp.concatenate([inertia(flat0)[None], history.inertia])

    f = 0.5 * jnp.sum(r * r)
    H = Jm.T @ Jm
    g = Jm.T @ r
    evals, evecs = jnp.linalg.eigh(H)
    floor = 1e-300 + 1e-15 * jnp.max(evals)
    if cfg.scale is None:  # an undetermined direction gets a huge (not a hidden) variance
        inv_evals = 1.0 / jnp.maximum(evals, floor)
    else:  # the scale fix leaves one exact gauge direction (J unchanged): pseudo-inverse
        inv_evals = jnp.where(evals > 1e-13 * jnp.max(evals), 1.0 / jnp.maximum(evals, floor),
                              0.0)
    inv = evecs @ jnp.diag(inv_evals) @ evecs.T
    p_opt = unravel(x)
    fitted = _assemble(p_opt, fixed, q0_guess, model, cfg)
    se = unravel(jnp.sqrt(jnp.diag(inv)))
    stderr, curvature = {}, jnp.zeros((), x.dtype)
    if "theta" in p_opt:
        it = np.array([lab.startswith("['theta']") for lab in _labels(p_opt)])
        D = jax.jacfwd(lambda th: _inertia_of(th, cfg.scale).reshape(9))(p_opt["theta"])
        cov_t = inv[np.ix_(it, it)]
        stderr["inertia"] = jnp.sqrt(jnp.clip(jnp.diag(D @ cov_t @ D.T), 0.0)).reshape(3, 3)
        v = jnp.zeros_like(x).at[np.flatnonzero(it)].set(_scale_direction(p_opt["theta"]))
        curvature = v @ H @ v / (v @ v)
    if "torque" in p_opt:
        stderr["torque"] = se["torque"]
    if "omega0" in p_opt:
        stderr["omega0"] = se["omega0"]
        stderr["quat0"] = se["dq0"]
    return _Optimum(
        params=p_opt, model=fitted.model, y0=fitted.y0, stderr=stderr,
        scale_curvature=curvature, loss=f, loss_history=hist, inertia_history=Js,
        grad_norm=jnp.linalg.norm(g), decrement=0.5 * g @ inv @ g, covariance=inv,
        eigenvalues=evals,
    )


def _fit_at_full_precision(*args) -> _Optimum:
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
_run = Program(_fit_at_full_precision, options=QUICK_COMPILE_OPTIONS)


__all__ = ["FitResult", "MomentScale", "Observations", "TraceScale", "fit", "loss",
           "residuals"]
