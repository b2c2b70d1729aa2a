"""Every `eqx.Module` of rbdyn_jax is abstract or final (equinox's pattern).

- A class named `Abstract…` is abstract: it has an abstract method or attribute, so it
  cannot be built; every other class is final: nothing of rbdyn_jax subclasses it.
- A concrete method of an abstract class is never overridden below it: a subclass fills in
  what is abstract and adds its own, so a call means one thing up the whole hierarchy.
- An abstract class declares no field (only `eqx.AbstractVar`s) and writes no `__init__`:
  a final class's fields and initialisation are all in one place.
- A dependency's module is subclassed only where it is abstract (diffrax's
  `AbstractSolver`, …).
"""

import abc
import importlib
import inspect
import pkgutil

import equinox as eqx
import pytest

import rbdyn_jax


def rbdyn_modules() -> list[type]:
    """Every `eqx.Module` subclass defined in rbdyn_jax (all its modules imported)."""
    found = {}
    for info in pkgutil.walk_packages(rbdyn_jax.__path__, "rbdyn_jax."):
        if info.name.endswith("__main__"):
            continue
        for c in vars(importlib.import_module(info.name)).values():
            if (
                inspect.isclass(c)
                and issubclass(c, eqx.Module)
                and c.__module__.startswith("rbdyn_jax")
            ):
                found[c.__module__, c.__qualname__] = c
    return list(found.values())


def is_abstract(c: type) -> bool:
    return bool(
        getattr(c, "__abstractmethods__", ())
        or getattr(c, "__abstractvars__", ())
        or getattr(c, "__abstractclassvars__", ())
    )


def written_init(c: type) -> bool:
    """Whether `c` writes its own `__init__` (not the one its dataclass generates)."""
    init = vars(c).get("__init__")
    return (
        init is not None
        and getattr(init, "__code__", None) is not None
        and (init.__code__.co_filename != "<string>")
    )


def violations(classes: list[type]) -> list[str]:
    """What breaks the abstract-or-final pattern among `classes`."""
    out = []
    for c in classes:
        below = [s for s in classes if s is not c and c in s.__mro__]
        abstract = is_abstract(c)
        if c.__name__.startswith("Abstract") and not abstract:
            out.append(f"{c.__name__} is named abstract but can be built")
        if not c.__name__.startswith("Abstract") and abstract:
            out.append(f"{c.__name__} is abstract but not named Abstract…")
        if below and not abstract:
            out.append(f"{c.__name__} is concrete and subclassed by {[s.__name__ for s in below]}")
        for base in c.__mro__[1:]:
            outside = base not in classes  # a dependency's (diffrax's solver, …)
            if outside and issubclass(base, eqx.Module) and base is not eqx.Module:
                if not is_abstract(base):
                    out.append(f"{c.__name__} subclasses the concrete {base.__name__}")
        if not abstract:
            continue
        annotations = vars(c).get("__annotations__", {})
        fields = {
            name
            for name, kind in annotations.items()
            if "AbstractVar" not in str(kind) and "ClassVar" not in str(kind)
        }
        if fields:
            out.append(f"{c.__name__} is abstract and declares fields {sorted(fields)}")
        if written_init(c):
            out.append(f"{c.__name__} is abstract and writes an __init__")
        for name, v in vars(c).items():
            if name in _RUN_BY_EVERY_CLASS or (name.startswith("__") and name != "__call__"):
                continue
            method = isinstance(v, property | classmethod | staticmethod) or callable(v)
            if not method or getattr(v, "__isabstractmethod__", False):
                continue
            over = [s.__name__ for s in below if name in vars(s)]
            if over:
                out.append(f"{c.__name__}.{name} is concrete and overridden by {over}")
    return out


# Equinox runs every class's `__check_init__` up the hierarchy: a subclass's adds checks,
# it does not replace its parent's.
_RUN_BY_EVERY_CLASS = {"__check_init__"}


def test_every_module_is_abstract_or_final():
    classes = rbdyn_modules()
    # The hierarchies the pattern is about are all found (a broken walk would pass vacuously).
    names = {c.__name__ for c in classes}
    for expected in (
        "AbstractRigidBody",
        "AbstractFrame",
        "AbstractTorque",
        "AbstractConservativeTorque",
        "AbstractDistribution",
        "AbstractBatching",
        "AbstractOptimizer",
        "AbstractScale",
        "RigidBody",
        "CircularOrbit",
        "Lanes",
        "Kernel",
        "LevenbergMarquardt",
    ):
        assert expected in names
    assert violations(classes) == []


@pytest.mark.parametrize(
    "case",
    [
        "concrete subclassed",
        "abstract named concrete",
        "override",
        "property override",
        "abstract field",
        "init",
        "dependency's concrete",
    ],
)
def test_violations_are_found(case):
    """The checker itself: each way of breaking the pattern is reported."""

    class AbstractBase(eqx.Module):
        @abc.abstractmethod
        def f(self): ...

        def g(self):
            return 1

    if case == "concrete subclassed":

        class Final(AbstractBase):
            def f(self):
                return 0

        class Below(Final):
            pass

        classes = [AbstractBase, Final, Below]
    elif case == "abstract named concrete":

        class Base(eqx.Module):
            @abc.abstractmethod
            def f(self): ...

        classes = [Base]
    elif case == "override":

        class Overrides(AbstractBase):
            def f(self):
                return 0

            def g(self):
                return 2

        classes = [AbstractBase, Overrides]
    elif case == "property override":

        class AbstractWithProperty(eqx.Module):
            @abc.abstractmethod
            def f(self): ...

            @property
            def p(self):
                return 1

        class Overrides(AbstractWithProperty):
            def f(self):
                return 0

            @property
            def p(self):
                return 2

        classes = [AbstractWithProperty, Overrides]
    elif case == "abstract field":

        class AbstractWithField(eqx.Module):
            x: float

            @abc.abstractmethod
            def f(self): ...

        classes = [AbstractWithField]
    elif case == "dependency's concrete":

        class Wider(eqx.nn.Identity):
            pass

        classes = [Wider]
    else:

        class AbstractWithInit(eqx.Module):
            def __init__(self):
                pass

            @abc.abstractmethod
            def f(self): ...

        classes = [AbstractWithInit]
    assert len(violations(classes)) == 1
