"""Parameter identification: fit inertia, torque parameters and initial states to observed
trajectories through the solver (DESIGN.md; PHYSICS.md §3–4, §6).

- `Observations(ts, omega=None, quat=None, sigma_omega=None, sigma_quat=None, mask=None)`:
  K trajectories of n samples (padded and masked where their lengths differ), checked once
  when built.
- `residuals(model, y0s, data, ...)`: the whitened residual vector — ω residuals divided by
  `sigma_omega`, attitude residuals as the rotation vector of `q_obs* ⊗ q_sim` (its norm is the
  geodesic angle, sign-invariant, finite gradient at zero) divided by `sigma_quat` — over all
  trajectories at once (`jax.vmap`, no Python loop over trajectories). `loss` is ½ Σ r².
- `fit(model, data, *, params=("inertia", "initial_conditions"), ...) -> FitResult`: the
  inertia free through the log-Cholesky parameters of J' (PHYSICS.md §3, every iterate is
  physical), the torque's array leaves, and the initial state of every trajectory (ω0 and a
  rotation-vector correction of q0). Levenberg–Marquardt on the residual vector (default) or
  any optax transformation, inside **one** compiled program with the Gauss–Newton covariance
  `(JᵀJ)⁻¹` at the optimum.

Identifiability: with no torque, Euler's equations `J ω' = J ω × ω` are unchanged by `J → cJ`,
so data fix J only up to scale. `fit` detects the near-null direction of `JᵀJ` along the
scaling of J and reports it (`FitResult.scale_identified = False`, inertia standard errors
`inf`); pass `scale=("trace", value)` or `scale=("moment", axis, value)` to fix the scale,
or a known torque in the model.
"""

import dataclasses
import numbers
from collections.abc import Callable, Sequence

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, ArrayLike, Bool, Float, PyTree

from . import rotation
from ._xla import filter_jit
from .inertia import from_log_cholesky, to_log_cholesky
from .integrate import RESULTS, simulate
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
            bad = m_q & ((norm == 0) | (~normalise_quat & (np.abs(norm - 1) > _UNIT_TOL)))
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


def _simulate_all(model, y0s: State, data: Observations, solver, rtol, atol, max_steps, adjoint):
    def one(y0, ts):
        return simulate(model, y0, ts, solver=solver, rtol=rtol, atol=atol,
                        max_steps=max_steps, adjoint=adjoint, throw=False)

    return jax.vmap(one)(y0s, data.ts)


def residuals(
    model: RigidBody,
    y0s: State,
    data: Observations,
    *,
    solver: diffrax.AbstractSolver = diffrax.Tsit5(),
    rtol: float = 1e-10,
    atol: float = 1e-10,
    max_steps: int = 4096,
    adjoint: diffrax.AbstractAdjoint = diffrax.RecursiveCheckpointAdjoint(),
) -> Float[Array, " m"]:
    """Whitened residual vector of `model` started at `y0s` (`State` with a leading K axis)
    against `data`: `[(ω_sim − ω_obs)/σ_ω ; rotvec(q_obs* ⊗ q_sim)/σ_q]` flattened, zero at
    masked samples (PHYSICS.md §2, §4). `|rotvec|` is the geodesic angle between observed
    and simulated attitude, invariant to the sign of either quaternion. A failed solve gives
    NaN residuals for its trajectory."""
    traj = _simulate_all(model, y0s, data, solver, rtol, atol, max_steps, adjoint)
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
      and no `scale` fix); the inertia stderr is then `inf`.
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


def _scale_fn(scale):
    """(J → scalar f(J), target) for a scale fix, or None."""
    if scale is None:
        return None
    if not isinstance(scale, tuple) or not scale or scale[0] not in ("trace", "moment"):
        raise ValueError("`scale` must be None, ('trace', value) or ('moment', axis, value).")
    if scale[0] == "trace":
        if len(scale) != 2:
            raise ValueError("`scale` must be ('trace', value).")
        value = float(scale[1])

        def f(J):
            return jnp.trace(J)
    else:
        if len(scale) != 3:
            raise ValueError("`scale` must be ('moment', axis, value).")
        axis, value = scale[1], float(scale[2])
        if isinstance(axis, numbers.Integral):
            if not 0 <= axis < 3:
                raise ValueError("`scale` axis index must be 0, 1 or 2.")
            n = np.eye(3)[axis]
        else:
            n = np.asarray(axis, float)
            if n.shape != (3,) or not np.linalg.norm(n) > 0:
                raise ValueError("`scale` axis must be an index or a non-zero 3-vector.")
            n = n / np.linalg.norm(n)

        def f(J):
            nn = jnp.asarray(n, dtype=J.dtype)
            return nn @ J @ nn
    if not value > 0:
        raise ValueError("`scale` value must be positive.")
    return f, value


def _inertia_of(theta, scale):
    J = from_log_cholesky(theta)
    if scale is not None:
        f, value = scale
        J = J * (value / f(J))
    return J


def _scale_direction(theta):
    """d theta / d log c for J → cJ: L → √c L."""
    half = jnp.full((3,), 0.5, dtype=theta.dtype)
    return jnp.concatenate([half, 0.5 * theta[3:]])


def fit(
    model: RigidBody,
    data: Observations,
    *,
    params: Sequence[str] = ("inertia", "initial_conditions"),
    torque_where: Callable | None = None,
    y0: State | None = None,
    scale: tuple | None = None,
    optimizer: optax.GradientTransformation | None = None,
    steps: int = 30,
    tol: float = 1e-6,
    rcond: float = 1e-9,
    solver: diffrax.AbstractSolver = diffrax.Tsit5(),
    rtol: float = 1e-10,
    atol: float = 1e-10,
    max_steps: int = 4096,
    horizons: Sequence[float] | None = None,
) -> FitResult:
    """Fit the free parameters of `model` (and the initial states) to `data`.

    **Arguments:**
    - `model`: a `RigidBody` (absolute motion, PHYSICS.md §4) giving the structure and the
      initial guess (its inertia must be strictly physical, J' ≻ 0).
    - `data`: `Observations` of K trajectories.
    - `params`: which parts are free, any of `"inertia"` (log-Cholesky θ of J', PHYSICS.md §3),
      `"torque"` (the array leaves of `model.torque`, or those `torque_where(torque)` picks,
      as the `where` of `eqx.tree_at`), `"initial_conditions"` (ω0 and a rotation-vector
      correction δ of q0 = q0_guess ⊗ exp(δ), per trajectory). Not free: held at the guess.
    - `y0`: initial guesses `State(omega (K, 3), quat (K, 4))` at `data.ts[:, 0]`; default:
      the first observed ω (zeros when ω is not observed) and the first observed attitude
      (identity when attitude is not observed), of each trajectory.
    - `scale`: fix the scale of J: `("trace", value)` or `("moment", axis, value)` (axis an
      index 0–2 or a 3-vector). Needed when the model has no torque (see the module docstring).
    - `optimizer`: `None` (default): Levenberg–Marquardt on the residual vector (Jacobian by
      forward mode), `steps` iterations; or an optax transformation (e.g.
      `optax.chain(optax.adam(1e-2))` or `optax.lbfgs()`) run `steps` times on the loss.
    - `tol`: convergence threshold on the Gauss–Newton decrement (Levenberg–Marquardt stops
      early once it is reached); `rcond`: eigenvalues of
      JᵀJ below `rcond` × the largest count as ill-determined directions.
    - `solver`, `rtol`, `atol`, `max_steps`: passed to `simulate`.
    - `horizons`: staged horizons for long or chaotic records, increasing fractions of each
      trajectory's span ending at 1, e.g. `(0.25, 0.5, 1.0)`: fit the samples up to the
      first fraction, start the next stage from that fit, and so on (the early part of a
      record constrains the parameters before errors in them have grown over the whole of
      it). Every stage masks samples of the same arrays, so all stages share one
      compilation.

    The whole fit (optimisation loop and covariance) is one compiled program (`eqx.filter_jit`,
    `lax.scan` over the steps); a second fit of the same structure and sizes reuses it.

    **Returns:** a `FitResult`.
    """
    if not isinstance(model, RigidBody):
        raise ValueError(f"`model` must be a RigidBody, got {type(model).__name__}.")
    if not isinstance(data, Observations):
        raise ValueError(f"`data` must be Observations, got {type(data).__name__}.")
    if horizons is not None:
        return _staged_fit(model, data, horizons, params=params, torque_where=torque_where,
                           y0=y0, scale=scale, optimizer=optimizer, steps=steps, tol=tol,
                           rcond=rcond, solver=solver, rtol=rtol, atol=atol,
                           max_steps=max_steps)
    params = tuple(params)
    for p in params:
        if p not in _PARAMS:
            raise ValueError(f"`params` entries must be among {_PARAMS}, got {p!r}.")
    if not params:
        raise ValueError("`params` names no free parameter.")
    if not isinstance(steps, numbers.Integral) or steps < 1:
        raise ValueError(f"`steps` must be a positive int, got {steps!r}.")
    scale_spec = _scale_fn(scale)
    K = data.num_trajectories

    if y0 is None:
        y0 = _initial_guess(data)
    if y0.omega.shape != (K, 3) or y0.quat.shape != (K, 4):
        raise ValueError(f"`y0` must be a State with omega ({K}, 3) and quat ({K}, 4).")
    q0_guess = rotation.quat_normalize(jnp.asarray(y0.quat))

    # Free / fixed parameters as pytrees.
    torque_dyn, torque_static = eqx.partition(model.torque, eqx.is_inexact_array)
    if torque_where is not None:
        spec = jax.tree_util.tree_map(lambda _: False, model.torque)
        picked = torque_where(spec)
        replace = (True,) * len(picked) if isinstance(picked, tuple) else True
        spec = eqx.tree_at(torque_where, spec, replace=replace)
        torque_dyn, torque_static = eqx.partition(model.torque, spec)
    free, fixed = {}, {}
    theta0 = to_log_cholesky(model.inertia)
    (free if "inertia" in params else fixed)["theta"] = theta0
    (free if "torque" in params else fixed)["torque"] = torque_dyn
    ic = {"omega0": jnp.asarray(y0.omega), "dq0": jnp.zeros((K, 3), q0_guess.dtype)}
    (free if "initial_conditions" in params else fixed).update(ic)
    if "torque" in params and not jax.tree_util.tree_leaves(torque_dyn):
        raise ValueError("`params` names 'torque' but the model's torque has no array leaves.")

    cfg = _Config(solver=solver, rtol=rtol, atol=atol, tol=tol, max_steps=int(max_steps),
                  steps=int(steps), scale=scale_spec, optimizer=optimizer,
                  torque_static=torque_static)
    out = _run(free, fixed, q0_guess, model, data, cfg)

    # Assemble the result (eager, small).
    p_opt = out["params"]
    fitted, y0_fit = _assemble(p_opt, fixed, q0_guess, model, cfg)
    flat, unravel = ravel_pytree(p_opt)
    labels = _labels(p_opt)
    it = np.array([lab.startswith("['theta']") for lab in labels])  # theta's flat indices
    cov = out["covariance"]
    evals = np.asarray(out["evals"])
    ill = int(np.sum(evals < rcond * evals.max()))
    notes = []
    scale_ok = True
    if "inertia" in params and scale_spec is None:
        # Is the scaling of J a near-null direction of JᵀJ?
        v = np.zeros(flat.size)
        v[it] = np.asarray(_scale_direction(p_opt["theta"]))
        H = np.asarray(out["H"])
        hv = v @ H @ v / (v @ v)
        if hv < rcond * evals.max():
            scale_ok = False
            notes.append(
                "The data fix the inertia only up to scale (J → cJ leaves the motion "
                "unchanged, as with no torque): pass scale=('trace', value) or "
                "scale=('moment', axis, value), or include a known torque in the model."
            )
    if scale_spec is not None and "inertia" in params:
        notes.append(f"The scale of J is fixed by the user: {scale[0]} = {scale[-1]}.")
    if ill > (0 if scale_ok and scale_spec is None else 1):
        notes.append(
            f"{ill} direction(s) of parameter space are ill-determined (eigenvalue of JᵀJ "
            f"below {rcond:g} × the largest): their standard errors are large."
        )
    stderr_flat = jnp.sqrt(jnp.diag(cov))
    se = unravel(stderr_flat)
    stderr = {}
    if "theta" in p_opt:
        D = jax.jacfwd(lambda th: _inertia_of(th, scale_spec).reshape(9))(p_opt["theta"])
        cov_t = cov[np.ix_(it, it)]
        se_J = jnp.sqrt(jnp.clip(jnp.diag(D @ cov_t @ D.T), 0.0)).reshape(3, 3)
        stderr["inertia"] = se_J if scale_ok else jnp.full((3, 3), jnp.inf)
    if "torque" in p_opt:
        stderr["torque"] = se["torque"]
    if "omega0" in p_opt:
        stderr["omega0"] = se["omega0"]
        stderr["quat0"] = se["dq0"]
    converged = bool(np.isfinite(float(out["loss"])) and float(out["decrement"]) < tol)
    if not converged:
        notes.append(
            f"Not converged after {steps} steps: Gauss–Newton decrement "
            f"{float(out['decrement']):.3g} ≥ tol = {tol:g}."
        )
    return FitResult(
        model=fitted, y0=y0_fit, loss=out["loss"], loss_history=out["loss_history"],
        inertia_history=out["inertia_history"], grad_norm=out["grad_norm"],
        decrement=out["decrement"], converged=converged, covariance=cov, labels=labels,
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
    solver: diffrax.AbstractSolver
    rtol: float
    atol: float
    tol: float
    max_steps: int = eqx.field(static=True)
    steps: int = eqx.field(static=True)
    scale: tuple | None = eqx.field(static=True)
    optimizer: optax.GradientTransformation | None = eqx.field(static=True)
    torque_static: PyTree


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


def _assemble(p, fixed, q0_guess, model, cfg):
    allp = {**fixed, **p}
    J = _inertia_of(allp["theta"], cfg.scale)
    torque = eqx.combine(allp["torque"], cfg.torque_static)
    m = eqx.tree_at(lambda x: (x.inertia, x.torque), model, (J, torque))
    quat = rotation.quat_multiply(q0_guess, rotation.quat_from_rotvec(allp["dq0"]))
    return m, State(allp["omega0"], quat)


@filter_jit
def _run(free, fixed, q0_guess, model, data, cfg: _Config):
    flat0, unravel = ravel_pytree(free)

    def res(flat, adjoint):
        m, y0s = _assemble(unravel(flat), fixed, q0_guess, model, cfg)
        return residuals(m, y0s, data, solver=cfg.solver, rtol=cfg.rtol, atol=cfg.atol,
                         max_steps=cfg.max_steps, adjoint=adjoint)

    def res_fwd(flat):
        return res(flat, diffrax.ForwardMode())

    def loss_fn(flat):
        r = res(flat, diffrax.RecursiveCheckpointAdjoint())
        return 0.5 * jnp.sum(r * r)

    def inertia(flat):
        allp = {**fixed, **unravel(flat)}
        return _inertia_of(allp["theta"], cfg.scale)

    def lin(y):
        Jm, r = jax.jacfwd(lambda z: (res_fwd(z), res_fwd(z)), has_aux=True)(y)
        return Jm, r

    if cfg.optimizer is None:
        # Levenberg–Marquardt (Marquardt's diagonal scaling). Each iteration linearises at
        # the trial point once (the only trace of the solve, so compile once), accepts it if
        # the loss went down, and proposes the next trial point from the accepted one. The
        # last iteration proposes nothing: its accepted point and Jacobian are the optimum.
        # Once the Gauss–Newton decrement ½ gᵀ(JᵀJ)⁻¹g at the accepted point is below `tol`
        # (the loss cannot fall by more), the remaining iterations are skipped (`lax.cond`:
        # no further solves) and the history repeats the optimum.
        def work(carry, i):
            x_acc, r_acc, J_acc, f_acc, lam, x_try, _ = carry
            J_try, r_try = lin(x_try)
            f_try = 0.5 * jnp.sum(r_try * r_try)
            good = jnp.isfinite(f_try) & (f_try < f_acc)
            pick = lambda a, b: jnp.where(good, a, b)  # noqa: E731
            x_acc, r_acc, J_acc = pick(x_try, x_acc), pick(r_try, r_acc), pick(J_try, J_acc)
            f_acc = pick(f_try, f_acc)
            lam = jnp.where(good, jnp.maximum(lam / 3.0, 1e-9), lam * 4.0)
            H = J_acc.T @ J_acc
            g = J_acc.T @ r_acc
            d = jnp.diag(H) + 1e-12 * jnp.max(jnp.diag(H))
            dx = -jnp.linalg.solve(H + lam * jnp.diag(d), g)
            dec = 0.5 * g @ jnp.linalg.solve(H + 1e-14 * jnp.max(d) * jnp.eye(H.shape[0]), g)
            done = jnp.isfinite(f_acc) & (dec < cfg.tol)
            x_next = jnp.where((i < cfg.steps) & ~done, x_acc + dx, x_acc)
            return (x_acc, r_acc, J_acc, f_acc, lam, x_next, done)

        def step(carry, i):
            carry = jax.lax.cond(carry[-1], lambda c, i: c, work, carry, i)
            return carry, (carry[3], inertia(carry[0]))

        m = jax.eval_shape(res_fwd, flat0).shape[0]
        init = (flat0, jnp.zeros(m, flat0.dtype), jnp.zeros((m, flat0.size), flat0.dtype),
                jnp.asarray(jnp.inf, flat0.dtype), jnp.asarray(1e-3, flat0.dtype), flat0,
                jnp.asarray(False))
        (x, r, Jm, _, _, _, _), (hist, Js) = jax.lax.scan(step, init,
                                                          jnp.arange(cfg.steps + 1))
        # entry i: the accepted point after trial i (entry 0: the initial guess)
    else:
        opt = cfg.optimizer
        vg = jax.value_and_grad(loss_fn)

        def step(carry, _):
            x, state = carry
            f, g = vg(x)
            if isinstance(opt, optax.GradientTransformationExtraArgs):
                upd, state = opt.update(g, state, x, value=f, grad=g, value_fn=loss_fn)
            else:
                upd, state = opt.update(g, state, x)
            x_new = optax.apply_updates(x, upd)
            return (x_new, state), (f, inertia(x_new))

        (x, _), (hist, Js) = jax.lax.scan(step, (flat0, opt.init(flat0)), None,
                                          length=cfg.steps)
        Jm, r = lin(x)
        hist = jnp.concatenate([hist, (0.5 * jnp.sum(r * r))[None]])
        Js = jnp.concatenate([inertia(flat0)[None], Js])

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
    return {
        "params": unravel(x),
        "loss": f,
        "loss_history": hist,
        "inertia_history": Js,
        "grad_norm": jnp.linalg.norm(g),
        "decrement": 0.5 * g @ inv @ g,
        "covariance": inv,
        "H": H,
        "evals": evals,
    }


__all__ = ["FitResult", "Observations", "fit", "loss", "residuals"]
