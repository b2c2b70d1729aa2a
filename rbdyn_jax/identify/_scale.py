"""Fixing the scale of J: data that fix the inertia only up to a factor c (no torque, or one
that scales with J) leave c to the user, who picks it with a scale gauge, `TraceScale` or
`MomentScale`. The fit then works on J rescaled onto the gauge (`inertia_of`)."""

import abc
import math
import numbers

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..inertia import from_log_cholesky


class AbstractScale(eqx.Module):
    """A fix of the scale of J: the fit holds `of(J)`, a quantity homogeneous of degree 1
    in J, at `value` (finite, > 0), by rescaling every iterate J → J · value / of(J).
    Pass an instance as `fit`'s `scale=`: `TraceScale(value)` or `MomentScale(axis,
    value)`."""

    value: eqx.AbstractVar[float]

    def __check_init__(self):
        if not (math.isfinite(self.value) and self.value > 0):
            raise ValueError(
                f"{type(self).__name__}: `value` must be finite and positive, got {self.value!r}."
            )

    @property
    @abc.abstractmethod
    def quantity(self) -> str:
        """The name of the quantity held at `value` (for `FitResult.notes`)."""

    @abc.abstractmethod
    def of(self, J: Float[Array, "3 3"]) -> Float[Array, ""]:
        """The quantity held at `value`, of the inertia `J`."""

    def rescale(self, J: Float[Array, "3 3"]) -> Float[Array, "3 3"]:
        """J rescaled onto the gauge: `J · value / of(J)`, whose `of` is `value`."""
        return J * (self.value / self.of(J))


class TraceScale(AbstractScale):
    """Fix the scale of J by its trace: the fit holds tr J = `value` (finite, > 0).

    Data that fix J only up to a factor c (no torque, or one that scales with J: see
    `rbdyn_jax.identify`) leave the choice of c to the user; `fit(...,
    scale=TraceScale(v))` makes it. `of(J)` is the quantity held at `value`.
    """

    value: float = eqx.field(converter=float)

    @property
    def quantity(self) -> str:
        """`tr J`."""
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
        raise ValueError(
            f"MomentScale: `axis` must be an index 0, 1 or 2 or a non-zero 3-vector, got {axis!r}."
        )
    return tuple(a.tolist())


class MomentScale(AbstractScale):
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
        elif len(self.axis) != 3 or not all(map(math.isfinite, self.axis)) or not any(self.axis):
            raise ValueError(
                "MomentScale: `axis` must be an index 0, 1 or 2 or a non-zero "
                f"3-vector, got {self.axis}."
            )

    @property
    def direction(self) -> np.ndarray:
        """The unit vector n."""
        n = np.eye(3)[self.axis] if isinstance(self.axis, int) else np.asarray(self.axis)
        return n / np.linalg.norm(n)

    @property
    def quantity(self) -> str:
        """`J[i, i]` for an index, `nᵀ J n (n = (…))` for a vector."""
        if isinstance(self.axis, int):
            return f"J[{self.axis}, {self.axis}]"
        return "nᵀ J n (n = ({:.4g}, {:.4g}, {:.4g}))".format(*self.direction)

    def of(self, J: Float[Array, "3 3"]) -> Float[Array, ""]:
        """nᵀ J n, n the unit `direction`."""
        n = jnp.asarray(self.direction, dtype=J.dtype)
        return n @ J @ n


def inertia_of(theta, scale: AbstractScale | None):
    """J from its log-Cholesky parameters, rescaled onto the `scale` fix if any."""
    J = from_log_cholesky(theta)
    if scale is not None:
        J = scale.rescale(J)
    return J


def scale_direction(theta):
    """d theta / d log c for J → cJ: L → √c L."""
    half = jnp.full((3,), 0.5, dtype=theta.dtype)
    return jnp.concatenate([half, 0.5 * theta[3:]])
