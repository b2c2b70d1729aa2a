"""Inertia tensors: construction, planar tensor, principal axes, physical checks.

See the physics guide, docs/physics.md#inertia.

Pure, batch-agnostic functions: every argument may carry leading `*batch` axes, which broadcast
against each other (also under `jax_numpy_rank_promotion="raise"`). All arrays are in body
components about the same point O. The physical condition used throughout
(docs/physics.md#physical-consistency): `J` belongs to a real mass distribution iff its planar
inertia tensor `J' = ½ tr(J) I − J` is positive semidefinite, i.e. iff the principal moments
satisfy the triangle inequalities `A + B ≥ C`, `B + C ≥ A`, `C + A ≥ B` (which imply they are
non-negative). Value checks use the relative tolerance `√eps` of the dtype.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._checks import check_batch, check_trailing, holds_now, sqrt_eps
from ._custom_types import BoolArray, Matrix, MatrixLike, Scalar, Vector, VectorLike
from ._program.xla import jit
from ._vector import HIGHEST

LogCholesky = Float[Array, "*batch 6"]
LogCholeskyLike = Float[ArrayLike, "*batch 6"]

_NOT_PHYSICAL = (
    "is not physical (planar inertia J' must be positive semidefinite: the principal moments "
    "must satisfy A + B ≥ C, B + C ≥ A, C + A ≥ B; docs/physics.md#physical-consistency)."
)


def _transpose(m: Array, xp=jnp) -> Array:
    return xp.swapaxes(m, -1, -2)


def _align(x: Array, ndim: int) -> Array:
    """`x` with leading unit axes up to `ndim` axes: explicit ranks for broadcasting."""
    return jnp.reshape(x, (1,) * (ndim - x.ndim) + x.shape)


def _eye_like(m: Array, xp=jnp) -> Array:
    """The identity broadcast to the shape of the `(*batch, 3, 3)` array `m` (explicit ranks)."""
    return xp.broadcast_to(xp.eye(3, dtype=m.dtype), m.shape)


def _trace(m: Array, xp=jnp) -> Array:
    return xp.trace(m, axis1=-2, axis2=-1)


def _max_abs(m: Array, xp=jnp) -> Array:
    return xp.max(xp.abs(m), axis=(-2, -1))


def _planar(J: Array, xp=jnp) -> Array:
    return 0.5 * _trace(J, xp)[..., None, None] * _eye_like(J, xp) - J


# The value checks take the array namespace `xp`: jax.numpy in a program, NumPy for a concrete
# J (`holds_now`), so that checking a model's inertia compiles nothing.


def _is_symmetric(J: Array, xp=jnp) -> Array:
    """`max|J − Jᵀ| ≤ √eps · max|J|` (non-finite entries fail)."""
    finite = xp.all(xp.isfinite(J), axis=(-2, -1))
    return finite & (_max_abs(J - _transpose(J, xp), xp) <= sqrt_eps(J.dtype) * _max_abs(J, xp))


def _planar_psd(J: Array, xp=jnp) -> Array:
    """Smallest eigenvalue of J' (of the symmetric part of `J`) ≥ −√eps · max|J|."""
    Jp = _planar(0.5 * (J + _transpose(J, xp)), xp)
    return xp.linalg.eigvalsh(Jp)[..., 0] >= -sqrt_eps(J.dtype) * _max_abs(J, xp)


def _physical(J: Array, xp=jnp) -> Array:
    return _is_symmetric(J, xp) & _planar_psd(J, xp)


def _now_or_traced(program, x):
    """`program(x)` (a jitted function): part of the caller's program for a traced `x`;
    for a concrete one computed now, also inside a caller's trace, by the same compiled
    arithmetic (not NumPy, nor JAX operation by operation), so that eager and traced
    calls agree bit for bit."""
    if isinstance(x, jax.core.Tracer):
        return program(x)
    with jax.ensure_compile_time_eval():
        return program(x)


def from_principal(moments: VectorLike, axes: MatrixLike | None = None) -> Matrix:
    """Inertia tensor from principal moments and axes, `J = C diag(moments) Cᵀ`.

    docs/physics.md#principal-axes.

    **Arguments:**

    - `moments`: principal moments `(A, B, C)`, shape `(*batch, 3)`, in any order. They must
        satisfy the triangle inequalities `A + B ≥ C`, `B + C ≥ A`, `C + A ≥ B` (hence be
        non-negative) within `√eps · max|moments|`; otherwise a runtime error
        (`eqx.error_if`). A zero moment (a thin rod) is the physical limit and is accepted.
    - `axes`: the matrix `C` whose columns are the principal axes in body components, shape
        `(*batch, 3, 3)`; must be orthonormal within `√eps` (runtime error otherwise).
        Default: the identity (body axes are principal).

    **Returns:**

    The inertia tensor `J`, shape `(*batch, 3, 3)`.
    """
    moments = check_trailing(moments, (3,), "moments")
    if axes is None:
        axes = jnp.broadcast_to(jnp.eye(3, dtype=moments.dtype), moments.shape + (3,))
    else:
        axes = check_trailing(axes, (3, 3), "axes")
    tol = sqrt_eps(moments.dtype)
    m = jax.lax.stop_gradient(moments)
    # Principal planar moments (B + C − A)/2, (C + A − B)/2, (A + B − C)/2
    # (docs/physics.md#planar-inertia-tensor).
    planar_moments = 0.5 * jnp.sum(m, axis=-1, keepdims=True) - m
    scale = jnp.max(jnp.abs(m), axis=-1, keepdims=True)
    bad = jnp.any(~(planar_moments >= -tol * scale), axis=-1)
    moments = eqx.error_if(moments, bad, "`moments` " + _NOT_PHYSICAL)
    c = jax.lax.stop_gradient(axes)
    not_orthonormal = ~(
        _max_abs(jnp.matmul(_transpose(c), c, precision=HIGHEST) - _eye_like(c)) <= tol
    )
    axes = eqx.error_if(axes, not_orthonormal, "`axes` must be orthonormal (CᵀC = I).")
    return jnp.einsum("...ij,...j,...kj->...ik", axes, moments, axes, precision=HIGHEST)


def from_point_masses(
    masses: Float[ArrayLike, "*batch N"],
    positions: Float[ArrayLike, "*batch N 3"],
    about: VectorLike | None = None,
) -> Matrix:
    """Inertia tensor of point masses, `J = Σ m (|r|² I − r rᵀ)`, `r = position − about`.

    docs/physics.md#inertia-tensor: `J[0, 0] = Σ m (y² + z²)`, …, `J[0, 1] = −Σ m x y`, ….
    Computed as `J = tr(J') I − J'` with the planar tensor `J' = Σ m r rᵀ`.

    **Arguments:**

    - `masses`: shape `(*batch, N)`, non-negative (runtime error otherwise).
    - `positions`: shape `(*batch, N, 3)`, body components.
    - `about`: the reference point O, shape `(*batch, 3)`. Default: the origin.

    **Returns:**

    The inertia tensor about `about`, shape `(*batch, 3, 3)`.
    """
    positions = check_trailing(positions, (3,), "positions")
    masses = check_batch(masses, "masses")
    if positions.ndim < 2:
        raise ValueError(f"`positions` must have shape (*batch, N, 3), got {positions.shape}.")
    if masses.ndim < 1 or masses.shape[-1] != positions.shape[-2]:
        raise ValueError(
            f"`masses` must have shape (*batch, N) with N = {positions.shape[-2]} as in "
            f"`positions`, got {masses.shape}."
        )
    if about is not None:
        about = check_trailing(about, (3,), "about")
        about = about[..., None, :]
        ndim = max(about.ndim, positions.ndim)
        positions = _align(positions, ndim) - _align(about, ndim)
    masses = eqx.error_if(masses, jnp.any(masses < 0, axis=-1), "`masses` must be non-negative.")
    return from_planar(
        jnp.einsum("...n,...ni,...nj->...ij", masses, positions, positions, precision=HIGHEST)
    )


def planar(J: MatrixLike) -> Matrix:
    """Planar inertia tensor `J' = ½ tr(J) I − J` (docs/physics.md#planar-inertia-tensor).

    **Arguments:**

    - `J`: inertia tensor, shape `(*batch, 3, 3)`.

    **Returns:**

    `J'`, shape `(*batch, 3, 3)`: for point masses `Σ m r rᵀ` (planar moments `Σ m x²`, … on the
    diagonal, products `Σ m x y`, … with a plus sign off it).
    """
    return _now_or_traced(_planar_program, check_trailing(J, (3, 3), "J"))


@jit
def _planar_program(J):
    """`J'` of `J`, one program (`_now_or_traced`)."""
    return _planar(J)


def from_planar(Jp: MatrixLike) -> Matrix:
    """Inertia tensor from the planar inertia tensor, `J = tr(J') I − J'`.

    docs/physics.md#planar-inertia-tensor.

    **Arguments:**

    - `Jp`: planar inertia tensor `J'`, shape `(*batch, 3, 3)`.

    **Returns:**

    `J`, shape `(*batch, 3, 3)`; the inverse of [`planar`][].
    """
    Jp = check_trailing(Jp, (3, 3), "Jp")
    return _from_planar(Jp)


def _from_planar(Jp: Array) -> Array:
    return _trace(Jp)[..., None, None] * _eye_like(Jp) - Jp


def principal_axes(J: MatrixLike) -> tuple[Vector, Matrix]:
    """Principal moments and axes, `J = C diag(moments) Cᵀ` (docs/physics.md#principal-axes).

    Eigen-decomposition (`jnp.linalg.eigh`) of the symmetric part `½ (J + Jᵀ)`. No value check:
    use [`check_inertia`][] first if `J` may be unphysical.

    The gradient of the moments is finite everywhere (where two moments coincide it is one of
    the one-sided derivatives; symmetric functions of the moments, such as their sum, are
    exact). The gradient of the **axes is undefined for degenerate moments** (a symmetric body,
    `A = B`, where any axis of the degenerate plane is principal): there it is NaN or infinite,
    and large near it.

    **Arguments:**

    - `J`: inertia tensor, shape `(*batch, 3, 3)`.

    **Returns:**

    A tuple `(moments, axes)`: `moments` ascending, shape `(*batch, 3)`; `axes` the matrix `C`
    whose columns are the unit principal axes in body components, shape `(*batch, 3, 3)`,
    right-handed (`det C = +1`; the last column is flipped where `eigh` returns `det = −1`).
    Each column's sign is otherwise arbitrary.
    """
    J = check_trailing(J, (3, 3), "J")
    moments, axes = jnp.linalg.eigh(0.5 * (J + _transpose(J)))
    sign = jnp.where(jnp.linalg.det(jax.lax.stop_gradient(axes)) < 0, -1.0, 1.0)
    sign = sign.astype(axes.dtype)[..., None, None]
    axes = jnp.concatenate([axes[..., :2], sign * axes[..., 2:]], axis=-1)
    return moments, axes


def ellipsoid_semi_axes(J: MatrixLike) -> tuple[Vector, Matrix]:
    """Semi-axes of the inertia ellipsoid `ρᵀ J ρ = 1` (docs/physics.md#inertia-tensor).

    **Arguments:**

    - `J`: inertia tensor, shape `(*batch, 3, 3)`.

    **Returns:**

    A tuple `(lengths, axes)`: `lengths = 1/√moments` (descending, since the moments ascend;
    `inf` for a zero moment, where the ellipsoid degenerates to a cylinder), shape `(*batch, 3)`,
    and the principal `axes` of [`principal_axes`][], shape `(*batch, 3, 3)`.
    """
    moments, axes = principal_axes(J)
    return 1.0 / jnp.sqrt(moments), axes


def moment_about(J: MatrixLike, axis: VectorLike) -> Scalar:
    """Moment of inertia about an axis through O, `nᵀ J n`, `n = axis / |axis|`.

    docs/physics.md#inertia-tensor.

    **Arguments:**

    - `J`: inertia tensor, shape `(*batch, 3, 3)`.
    - `axis`: direction of the axis, shape `(*batch, 3)`, any non-zero length (a zero axis is a
        runtime error).

    **Returns:**

    The moment of inertia, shape `(*batch,)`.
    """
    J = check_trailing(J, (3, 3), "J")
    axis = check_trailing(axis, (3,), "axis")
    norm = jnp.linalg.norm(axis, axis=-1, keepdims=True)
    axis = eqx.error_if(axis, norm[..., 0] == 0, "`axis` must be non-zero.")
    n = axis / norm
    return jnp.einsum("...i,...ij,...j->...", n, J, n, precision=HIGHEST)


def kinetic_energy(J: MatrixLike, omega: VectorLike) -> Scalar:
    """Rotational kinetic energy `T = ½ ωᵀ J ω` (docs/physics.md#inertia-tensor).

    **Arguments:**

    - `J`: inertia tensor, shape `(*batch, 3, 3)`.
    - `omega`: angular velocity in body components, shape `(*batch, 3)`.

    **Returns:**

    `T`, shape `(*batch,)`.
    """
    J = check_trailing(J, (3, 3), "J")
    omega = check_trailing(omega, (3,), "omega")
    return 0.5 * jnp.einsum("...i,...ij,...j->...", omega, J, omega, precision=HIGHEST)


def angular_momentum(J: MatrixLike, omega: VectorLike) -> Vector:
    """Angular momentum about O, `L = J ω`, in body components (docs/physics.md#inertia-tensor).

    **Arguments:**

    - `J`: inertia tensor, shape `(*batch, 3, 3)`.
    - `omega`: angular velocity in body components, shape `(*batch, 3)`.

    **Returns:**

    `L`, shape `(*batch, 3)`.
    """
    J = check_trailing(J, (3, 3), "J")
    omega = check_trailing(omega, (3,), "omega")
    return jnp.einsum("...ij,...j->...i", J, omega, precision=HIGHEST)


def is_physical(J: MatrixLike) -> BoolArray:
    """Whether `J` is the inertia tensor of some real mass distribution.

    docs/physics.md#physical-consistency.

    True iff `J` is finite, symmetric within `√eps · max|J|`, and its planar tensor is positive
    semidefinite, `J' ⪰ 0` (smallest eigenvalue ≥ `−√eps · max|J|`) — equivalently, the principal
    moments satisfy `A + B ≥ C`, `B + C ≥ A`, `C + A ≥ B` (so are non-negative). Boundary cases
    are physical: a flat lamina (`A + B = C`), a thin rod (a zero moment), `J = 0`.

    **Arguments:**

    - `J`: inertia tensor, shape `(*batch, 3, 3)`.

    **Returns:**

    A boolean array of shape `(*batch,)`.
    """
    return _now_or_traced(_physical_program, check_trailing(J, (3, 3), "J"))


@jit
def _physical_program(J):
    """`is_physical` of `J` (no gradient), one program (`_now_or_traced`)."""
    return _physical(jax.lax.stop_gradient(J))


def check_inertia(J: MatrixLike, name: str = "inertia") -> Matrix:
    """Return `J` unchanged, with runtime errors if it is not symmetric or not physical.

    The conditions are those of [`is_physical`][] (docs/physics.md#physical-consistency).
    Use the returned value:
    a traced `J` comes back carrying the `eqx.error_if` checks (gradients pass through
    unchanged); a concrete one is checked at once, in NumPy.

    **Arguments:**

    - `J`: inertia tensor, shape `(*batch, 3, 3)`; a wrong shape is a `ValueError` at trace time.
    - `name`: what to call `J` in error messages.

    **Returns:**

    `J` as a float array, shape `(*batch, 3, 3)`.
    """
    J = check_trailing(J, (3, 3), name)
    if holds_now(_physical, J):
        return J  # concrete and valid: checked now, in NumPy
    Js = jax.lax.stop_gradient(J)
    symmetric = _is_symmetric(Js)
    J = eqx.error_if(J, ~symmetric, f"`{name}` is not symmetric (J must equal Jᵀ and be finite).")
    return eqx.error_if(J, symmetric & ~_planar_psd(Js), f"`{name}` " + _NOT_PHYSICAL)


def to_log_cholesky(J: MatrixLike) -> LogCholesky:
    """Log-Cholesky parameters of the planar inertia tensor, `J' = L Lᵀ`.

    docs/physics.md#log-cholesky-parametrisation.

    `L` is lower triangular with positive diagonal (`jnp.linalg.cholesky` of `J'`); the
    parameters are ordered

        theta = (log L00, log L11, log L22, L10, L20, L21).

    `J` must be strictly physical, `J' ≻ 0`: a runtime error otherwise. In particular a flat
    body or a rod (singular `J'`, some `A + B = C` or a zero moment) has no finite log-Cholesky
    parameters.

    **Arguments:**

    - `J`: inertia tensor, shape `(*batch, 3, 3)`.

    **Returns:**

    `theta`, shape `(*batch, 6)`; [`from_log_cholesky`][] is its inverse.
    """
    J = check_inertia(J, "J")
    if isinstance(J, jax.core.Tracer):
        return _checked_theta(*_log_cholesky(J))
    with jax.ensure_compile_time_eval():  # concrete, also in a caller's trace: now
        theta, bad = _log_cholesky(J)
        return theta if not np.any(bad) else _checked_theta(theta, bad)


def _checked_theta(theta, bad):
    msg = (
        "`J` is not strictly physical: its planar inertia J' is singular (a flat body or a "
        "rod), which has no finite log-Cholesky parameters."
    )
    return eqx.error_if(theta, bad, msg)


@jit
def _log_cholesky(J):
    """`theta` of `J`, and where J' has no Cholesky factor. One compiled program for a
    concrete `J` (eager JAX would compile each operation on first use, and may round
    differently from a program), part of the caller's for a traced one: the same arithmetic
    either way. The check is the caller's, outside, so that this trace holds none."""
    L = jnp.linalg.cholesky(_planar(0.5 * (J + _transpose(J))))
    d = jnp.diagonal(L, axis1=-2, axis2=-1)
    bad = ~jnp.all(jax.lax.stop_gradient(d) > 0, axis=-1)  # NaN where cholesky fails
    return jnp.concatenate([jnp.log(d), L[..., 1, :1], L[..., 2, :2]], axis=-1), bad


def from_log_cholesky(theta: LogCholeskyLike) -> Matrix:
    """Inertia tensor from log-Cholesky parameters, `J = tr(J') I − J'`, `J' = L Lᵀ`.

    docs/physics.md#log-cholesky-parametrisation. Every real `theta` gives a physical `J`
    with `J' ≻ 0`, so fitting `theta` keeps a fitted inertia physical.

    **Arguments:**

    - `theta`: shape `(*batch, 6)`, ordered `(log L00, log L11, log L22, L10, L20, L21)` with `L`
        the lower-triangular Cholesky factor of `J'`.

    **Returns:**

    `J`, shape `(*batch, 3, 3)`; [`to_log_cholesky`][] is its inverse.
    """
    return _now_or_traced(_from_log_cholesky, check_trailing(theta, (6,), "theta"))


@jit
def _from_log_cholesky(theta):
    """`J` of `theta`, one program (`_now_or_traced`)."""
    l00, l11, l22, l10, l20, l21 = jnp.moveaxis(theta, -1, 0)
    zero = jnp.zeros_like(l00)
    L = jnp.stack(
        [
            jnp.stack([jnp.exp(l00), zero, zero], axis=-1),
            jnp.stack([l10, jnp.exp(l11), zero], axis=-1),
            jnp.stack([l20, l21, jnp.exp(l22)], axis=-1),
        ],
        axis=-2,
    )
    return _from_planar(jnp.matmul(L, _transpose(L), precision=HIGHEST))
