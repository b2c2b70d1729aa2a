"""The registry of torque and frame kinds: `Param` (one key of a kind's table), `Kind` (its
class, keys and builder), `TORQUES` and `FRAMES`, and the look-up of a table's `kind`."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any

import equinox as eqx
import jax.numpy as jnp

from ..frames import CircularOrbit, ConstantRate, EulerAngleFrame, HarmonicAngles, Inertial
from ..torques import (
    BalancingTransport,
    BodyTorque,
    GravityGradient,
    InertialTorque,
    PolynomialSinPsi,
    RestoringMoment,
    UniformGravity,
)
from ._distributions import AbstractDistribution, Fixed
from ._validate import _euler_seq, _fail, _quantity, _quat_array, _table


@dataclasses.dataclass(frozen=True)
class Param:
    """One key of a kind's table. `parse(value, path)` validates it and gives a
    distribution (drawn per trajectory), or for a `static` key a plain setting fixed for the
    whole scenario (an Euler sequence: it shapes the compiled program, it is not drawn)."""

    parse: Callable[[Any, str], Any]
    required: bool = False
    static: bool = False


def _quantity_param(shape=(), *, required=False, positive=False) -> Param:
    """A number or array of `shape`, or a distribution of one."""
    return Param(lambda x, path: _quantity(x, path, shape, positive=positive), required)


def _coeffs(x, path) -> AbstractDistribution:
    n = len(x) if isinstance(x, list) else 0
    if n < 1:
        raise _fail(path, "a non-empty list of numbers (K(τ) = Σ c_i τ^i)", x)
    return _quantity(x, path, (n,))


_UNIT_QUAT = Param(lambda x, path: Fixed(jnp.asarray(_quat_array(x, path))))


def _exactly_one(**alternatives: str) -> Callable[[dict, str], None]:
    """A check that the table has exactly one of the keys `alternatives` (key → meaning)."""
    (a, what_a), (b, what_b) = alternatives.items()

    def check(t, path):
        if (a in t) == (b in t):
            raise _fail(path, f"exactly one of `{a}` ({what_a}) or `{b}` ({what_b})", sorted(t))

    return check


@dataclasses.dataclass(frozen=True)
class Kind:
    """A torque or frame kind a scenario may name: its class `cls`, its table's keys
    `params` (name → `Param`), and `build`, which makes the object from the drawn and static
    values of the keys present (name → value); by default `cls(**values)`. `check` tests
    rules between keys (`check(table, path)` raises a `ScenarioError`); a `relative_only`
    kind needs `kind = "relative_rigid_body"`."""

    cls: type
    params: Mapping[str, Param] = dataclasses.field(default_factory=dict)
    build: Callable[[dict[str, Any]], eqx.Module] | None = None
    check: Callable[[dict, str], None] | None = None
    relative_only: bool = False

    def validate(self, x: Mapping, path: str) -> tuple[dict, dict]:
        """The table `x` at `path` (its `kind` already looked up) validated: its
        distributions and its static settings, by key."""
        required = {name for name, p in self.params.items() if p.required}
        t = _table(x, path, set(self.params) | {"kind"}, required)
        dists, static = {}, {}
        for name, p in self.params.items():
            if name in t:
                (static if p.static else dists)[name] = p.parse(t[name], f"{path}.{name}")
        if self.check is not None:
            self.check(t, path)
        return dists, static

    def make(self, values: dict[str, Any]) -> eqx.Module:
        """The torque or frame from its keys' values (name → drawn or static value)."""
        return self.cls(**values) if self.build is None else self.build(values)


def _restoring_moment(p):
    if "coeffs" in p:
        return RestoringMoment(PolynomialSinPsi(p["coeffs"], p.get("eps", jnp.asarray(1.0))))
    return RestoringMoment(p["k"], p.get("eps"))


def _restoring_moment_check(t, path):
    _exactly_one(k="constant", coeffs="K(τ) polynomial")(t, path)
    if "k" in t and "eps" in t:  # a constant k does not read τ = ε t
        raise _fail(f"{path}.eps", "only with `coeffs` (a constant `k` has no slow time)", t["eps"])


def _gravity_gradient(p):
    if "eps" in p:
        return GravityGradient(p["eps"])
    return GravityGradient.from_orbit_rate(p["orbit_rate"])


def _euler_angle_frame(p):
    angles = HarmonicAngles(**{k: v for k, v in p.items() if k != "seq"})
    return EulerAngleFrame(angles, seq=p.get("seq", "ZXZ"))


TORQUES: dict[str, Kind] = {
    "body": Kind(BodyTorque, {"moment": _quantity_param((3,), required=True)}),
    "inertial": Kind(InertialTorque, {"moment": _quantity_param((3,), required=True)}),
    "uniform_gravity": Kind(
        UniformGravity,
        {"weight": _quantity_param(required=True), "com": _quantity_param((3,), required=True)},
    ),
    "restoring_moment": Kind(
        RestoringMoment,
        {"k": _quantity_param(), "coeffs": Param(_coeffs), "eps": _quantity_param()},
        build=_restoring_moment,
        check=_restoring_moment_check,
    ),
    "gravity_gradient": Kind(
        GravityGradient,
        {"eps": _quantity_param(), "orbit_rate": _quantity_param(positive=True)},
        build=_gravity_gradient,
        check=_exactly_one(eps="3μ/R³", orbit_rate="n, ε = 3n²"),
    ),
    "balancing_transport": Kind(BalancingTransport, relative_only=True),
}
"""The registry of torque kinds for `[[model.torques]]`: kind → `Kind` (the class, the
accepted keys and their validation, the builder). `Scenario.from_dict` validates a table
with it and `Scenario.build` builds from it; a kind not in it is an error in both, never a
fallback. Adding a torque usable from TOML is the torque class plus one entry here: nothing
else to edit."""
FRAMES: dict[str, Kind] = {
    "inertial": Kind(Inertial),
    "constant_rate": Kind(
        ConstantRate, {"omega_e": _quantity_param((3,), required=True), "quat0": _UNIT_QUAT}
    ),
    "circular_orbit": Kind(
        CircularOrbit, {"n": _quantity_param(required=True), "quat0": _UNIT_QUAT}
    ),
    "euler_angles": Kind(
        EulerAngleFrame,
        {
            "seq": Param(_euler_seq, static=True),
            **{
                k: _quantity_param((3,))
                for k in ("offset", "rate", "amplitude", "frequency", "phase")
            },
        },
        build=_euler_angle_frame,
    ),
}
"""The registry of frame kinds for `[model.frame]`, as `TORQUES` is for torques: adding a
frame usable from TOML is the frame class plus one entry here."""


def _kind(registry: Mapping[str, Kind], kind: Any, path: str) -> Kind:
    """`registry[kind]`, or a `ScenarioError` at `path` listing the registered kinds."""
    if not isinstance(kind, str) or kind not in registry:
        raise _fail(path, f"one of {sorted(registry)}", kind)
    return registry[kind]


def _kinded(x, path, registry) -> tuple[str, dict, dict]:
    """A table with a `kind` from `registry`: the kind, its distributions and its static
    settings (by key)."""
    if not isinstance(x, Mapping) or "kind" not in x:
        raise _fail(f"{path}.kind", f"one of {sorted(registry)} (missing)")
    return x["kind"], *_kind(registry, x["kind"], f"{path}.kind").validate(x, path)
