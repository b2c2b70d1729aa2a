"""Summaries: per-trajectory scalars computed in the compiled sweep from the saved states
(`Summary`, `SUMMARIES`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax.numpy as jnp

from .. import invariants


def _nutation(quat):
    """Angle between the body z-axis and the parent z-axis: arccos R33, R33 = 1 − 2(x²+y²)."""
    c = 1.0 - 2.0 * (quat[..., 1] ** 2 + quat[..., 2] ** 2)
    return jnp.arccos(jnp.clip(c, -1.0, 1.0))


def _first_flip(ts, omega, J):
    """First time the body rate along the intermediate principal axis of J changes sign
    (linear interpolation between output times), NaN if it never does within `ts`. For a
    spin started near the intermediate axis this is the first intermediate-axis flip."""
    _, axes = jnp.linalg.eigh(J)
    s = omega @ axes[:, 1]
    crossed = jnp.sign(s[1:]) * jnp.sign(s[0]) < 0
    k = jnp.argmax(crossed)
    frac = s[k] / (s[k] - s[k + 1])
    return jnp.where(jnp.any(crossed) & (s[0] != 0), ts[k] + frac * (ts[k + 1] - ts[k]), jnp.nan)


def _relative_drift(x):
    return jnp.max(jnp.abs(x - x[0])) / jnp.abs(x[0])


class Summary(NamedTuple):
    """A per-trajectory summary a scenario may keep: what it is, its units (UDUNITS, as the
    store's `units` attribute) and the function of `(model, trajectory)` computing it."""

    description: str
    units: str
    fn: Callable


SUMMARIES: dict[str, Summary] = {
    "max_nutation": Summary(
        "largest angle between body z and parent z over the output times",
        "rad",
        lambda m, tr: jnp.max(_nutation(tr.ys.quat)),
    ),
    "final_nutation": Summary(
        "angle between body z and parent z at the last output time",
        "rad",
        lambda m, tr: _nutation(tr.ys.quat[-1]),
    ),
    "energy_drift": Summary(
        "max |E - E0| / |E0| over the output times (conservative models)",
        "1",
        lambda m, tr: _relative_drift(invariants.energy(m, tr)),
    ),
    "relative_energy_drift": Summary(
        "max |T_r - T_r0| / T_r0 of the relative kinetic energy "
        "(docs/physics.md#balancing-transport-moment)",
        "1",
        lambda m, tr: _relative_drift(invariants.relative_kinetic_energy(m, tr)),
    ),
    "first_flip_time": Summary(
        "first sign change of omega along the intermediate principal axis (NaN: none)",
        "s",
        lambda m, tr: _first_flip(tr.ts, tr.ys.omega, m.inertia),
    ),
    "min_abs_omega": Summary(
        "smallest |omega| (|omega_r| in relative models) over the output times",
        "rad/s",
        lambda m, tr: jnp.min(jnp.linalg.norm(tr.ys.omega, axis=-1)),
    ),
    "max_abs_omega": Summary(
        "largest |omega| (|omega_r| in relative models) over the output times",
        "rad/s",
        lambda m, tr: jnp.max(jnp.linalg.norm(tr.ys.omega, axis=-1)),
    ),
}
