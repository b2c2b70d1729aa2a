"""Transport frames O1: how the parent frame of a relative model moves.

See the physics guide, docs/physics.md#transport-frame.

A frame gives, at time t, its attitude relative to O0 (a quaternion, O1 → O0 components)
and its absolute angular velocity and acceleration **in O1 components**, ω_e¹ and dω_e¹/dt.
(Because O1 turns with ω_e, the derivative of its O1 components equals that of its O0
components expressed in O1.) `Inertial`, `ConstantRate` and `CircularOrbit` coincide with
O0 at t = 0 unless given `quat0` (normalised); an `EulerAngleFrame` starts at the attitude
of its angles at t = 0 (times `quat0` if given).
"""

import abc
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from . import rotation
from ._checks import check_scalar, check_trailing
from ._vector import parse_seq


def _quat0(quat0, dtype=None) -> Array:
    if quat0 is None:
        return jnp.array([1.0, 0.0, 0.0, 0.0], dtype=dtype)
    return rotation.quat_normalize(check_trailing(quat0, (4,), "quat0"))


class AbstractFrame(eqx.Module):
    """A transport frame: `frame(t) -> (quat, omega_e, eps_e)` (see module docstring)."""

    @abc.abstractmethod
    def __call__(
        self, t: Float[Array, ""]
    ) -> tuple[Float[Array, "4"], Float[Array, "3"], Float[Array, "3"]]:
        """(attitude O1 → O0, ω_e in O1 components, dω_e/dt in O1 components) at `t`."""


class Inertial(AbstractFrame):
    """O1 = O0 (a relative model in this frame is an absolute one)."""

    def __call__(self, t):
        t = jnp.asarray(t)
        zero = jnp.zeros(3, dtype=t.dtype)
        return jnp.array([1.0, 0.0, 0.0, 0.0], dtype=t.dtype), zero, zero


class ConstantRate(AbstractFrame):
    """O1 turning at a constant rate `omega_e`, given in O1 components (so also constant
    in O0): attitude `quat0 ⊗ exp(ω_e t)`, zero angular acceleration."""

    omega_e: Float[Array, "3"]
    quat0: Float[Array, "4"]

    def __init__(self, omega_e: Float[ArrayLike, "3"], quat0: Float[ArrayLike, "4"] | None = None):
        self.omega_e = check_trailing(omega_e, (3,), "omega_e")
        self.quat0 = _quat0(quat0, self.omega_e.dtype)

    def __call__(self, t):
        q = rotation.quat_multiply(self.quat0, rotation.quat_from_rotvec(t * self.omega_e))
        return q, self.omega_e, jnp.zeros_like(self.omega_e)


class EulerAngleFrame(AbstractFrame):
    """O1 given by its Euler angles relative to O0 as a function of time.

    Mukhametzyanov (2009), eq. (14); docs/physics.md#euler-angle-frames.

    `angles_fn(t) -> (3,)` angles of `seq` (default "ZXZ" = (ψ_e, θ_e, φ_e)); its rates and
    second derivatives come from forward-mode autodiff, and ω_e¹ from the kinematic map of
    docs/physics.md#euler-angle-rates (`rotation.euler_rates_to_omega`). `angles_fn` may be
    an `eqx.Module` whose coefficients are leaves. A constant `quat0` pre-multiplies the
    attitude.
    """

    angles_fn: Callable
    seq: str = eqx.field(static=True, default="ZXZ")
    quat0: Float[Array, "4"] | None = None

    def __check_init__(self):
        parse_seq(self.seq)  # ValueError naming `seq` for a bad string
        if self.quat0 is not None and jnp.shape(self.quat0)[-1:] != (4,):
            raise ValueError(f"`quat0` must have shape (4,), got {jnp.shape(self.quat0)}.")
        if not callable(self.angles_fn):
            raise ValueError("`angles_fn` must be a callable t -> (3,) angles.")

    def __call__(self, t):
        t = jnp.asarray(t)

        def omega_of(s):
            angles, rates = jax.jvp(self.angles_fn, (s,), (jnp.ones_like(s),))
            return rotation.euler_rates_to_omega(angles, rates, self.seq)

        omega_e, eps_e = jax.jvp(omega_of, (t,), (jnp.ones_like(t),))
        q = rotation.euler_to_quat(self.angles_fn(t), self.seq)
        if self.quat0 is not None:
            q = rotation.quat_multiply(rotation.quat_normalize(self.quat0), q)
        return q, omega_e, eps_e


class HarmonicAngles(eqx.Module):
    """Euler angles `offset + rate·t + amplitude·sin(frequency·t + phase)` (componentwise),
    an `angles_fn` for `EulerAngleFrame` whose coefficients are leaves (sweeps disperse
    them; a platform turning at a constant rate with a nodding axis,
    docs/physics.md#euler-angle-frames)."""

    offset: Float[Array, "3"]
    rate: Float[Array, "3"]
    amplitude: Float[Array, "3"]
    frequency: Float[Array, "3"]
    phase: Float[Array, "3"]

    def __init__(self, offset=None, rate=None, amplitude=None, frequency=None, phase=None):
        vals = [
            jnp.zeros(3) if v is None else check_trailing(v, (3,), name)
            for v, name in (
                (offset, "offset"),
                (rate, "rate"),
                (amplitude, "amplitude"),
                (frequency, "frequency"),
                (phase, "phase"),
            )
        ]
        self.offset, self.rate, self.amplitude, self.frequency, self.phase = vals

    def __call__(self, t):
        return (
            self.offset + self.rate * t + self.amplitude * jnp.sin(self.frequency * t + self.phase)
        )


class CircularOrbit(AbstractFrame):
    """Orbital (LVLH) frame of a circular orbit of rate `n` (docs/physics.md#circular-orbit):
    x1 along-track, y1 = −orbit normal, z1 = nadir; it turns about the orbit normal,
    `ω_e¹ = (0, −n, 0)`. O0 is the orbital frame at t = 0 (or `quat0` relative to it)."""

    n: Float[Array, ""]
    quat0: Float[Array, "4"]

    def __init__(self, n: Float[ArrayLike, ""], quat0: Float[ArrayLike, "4"] | None = None):
        self.n = check_scalar(n, "n")
        self.quat0 = _quat0(quat0, self.n.dtype)

    def __call__(self, t):
        zero = jnp.zeros_like(self.n)
        omega_e = jnp.stack([zero, -self.n, zero])
        q = rotation.quat_multiply(self.quat0, rotation.quat_from_rotvec(t * omega_e))
        return q, omega_e, jnp.zeros_like(omega_e)


__all__ = [
    "AbstractFrame",
    "CircularOrbit",
    "ConstantRate",
    "EulerAngleFrame",
    "HarmonicAngles",
    "Inertial",
]
