"""The package's layering: each module may import only the modules of the layers above it.

The order is the layer table of the developer docs, bottom layer first. Private helpers
(`_x.py`) sit below everything and import no public module; `__init__` only re-exports, and
nothing imports from it. `rotation/`, `integrate/`, `analytic/`, `scenario/`, `sweep/`,
`identify/`, `cli/` and the private compile layer `_program/` are packages: a package's
files import each other (their private names too: they are one module) and the layers
below it. No module imports another's private name, and diffrax is used only where its
objects are built or run (see `DIFFRAX`).
"""

import ast
import pathlib

import pytest

import rbdyn_jax

LAYERS = [
    "state",
    "rotation",
    "inertia",
    "dynamics",
    "torques",
    "frames",
    "models",
    "integrate",
    "invariants",
    "analytic",
    "scenario",
    "sweep",
    "identify",
    "cli",
]
PACKAGE = pathlib.Path(rbdyn_jax.__file__).parent
# Where diffrax may be imported: `integrate/` runs it (the only place that calls
# `diffeqsolve` or drives a solver); `identify` and `scenario` build the solver and
# step-size controller objects their callers pass through to it.
DIFFRAX = {"integrate", "identify", "scenario"}


def module_files() -> dict[str, list[pathlib.Path]]:
    """Each layer's (and private helper's) source files: a module's file, or a package's."""
    out = {}
    for p in sorted(PACKAGE.iterdir()):
        if p.suffix == ".py" and p.name != "__init__.py":
            out[p.stem] = [p]
        elif p.is_dir() and (p / "__init__.py").exists():
            out[p.name] = sorted(p.glob("*.py"))
    return out


def _top_modules() -> set[str]:
    return set(module_files())


def in_subpackage(path: pathlib.Path) -> bool:
    """Whether the file at `path` is one of a subpackage's (`integrate/_field.py`)."""
    return path.parent != PACKAGE and path.parent.parent == PACKAGE


def package_imports(path: pathlib.Path) -> set[str]:
    """The rbdyn_jax modules (top-level names) imported by the file at `path`, absolute or
    relative; `"__init__"` for a name imported from the package itself (`from . import
    __version__`), and a file inside a subpackage does not count its own package."""
    inside = in_subpackage(path)
    own = path.parent.name if inside else None
    top = _top_modules()
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            level = node.level - (1 if inside else 0)  # levels above the package root
            if node.level and level == 0 and inside:
                continue  # from ._x import y: the file's own package
            if (
                node.level
                and level == 1
                or (node.level == 0 and node.module and node.module.startswith("rbdyn_jax"))
            ):
                parts = (node.module or "").split(".")
                if node.level == 0:
                    parts = parts[1:]
                if parts and parts[0]:
                    found.add(parts[0])
                else:  # from . import x: modules, or names of the package's __init__
                    found.update(a.name if a.name in top else "__init__" for a in node.names)
        elif isinstance(node, ast.Import):
            for a in node.names:
                parts = a.name.split(".")
                if parts[0] == "rbdyn_jax" and len(parts) > 1:
                    found.add(parts[1])
    return found - ({own} if own else set())


def private_names_imported(path: pathlib.Path) -> set[str]:
    """`module._name` for every private name (not a private module) imported from another
    rbdyn_jax module. A subpackage's file may import its sibling files' private names
    (`from ._validate import _fail`: one module), not another module's."""
    modules = _top_modules() | {p.stem for p in path.parent.glob("*.py")}
    inside = in_subpackage(path)
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if inside and isinstance(node, ast.ImportFrom) and node.level == 1:
            continue  # from ._x import _y: the file's own package
        if isinstance(node, ast.ImportFrom) and (
            node.level or (node.module or "").startswith("rbdyn_jax")
        ):
            for a in node.names:
                if a.name.startswith("_") and a.name not in modules | {"__version__"}:
                    found.add(f"{node.module}.{a.name}")
    return found


def imports_diffrax(path: pathlib.Path) -> bool:
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import) and any(
            a.name.split(".")[0] == "diffrax" for a in node.names
        ):
            return True
        if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "diffrax":
            return True
    return False


def test_every_module_is_in_a_layer():
    public = {m for m in module_files() if not m.startswith("_")}
    assert public <= set(LAYERS), f"modules missing from the layers: {public - set(LAYERS)}"
    assert {"rotation", "inertia", "integrate", "scenario", "cli"} <= public


@pytest.mark.parametrize("module", [m for m in LAYERS if m in module_files()])
def test_no_module_imports_a_lower_layer(module):
    allowed = set(LAYERS[: LAYERS.index(module)])
    for path in module_files()[module]:
        imported = {m for m in package_imports(path) if not m.startswith("_")}
        assert imported <= allowed, (
            f"{path.relative_to(PACKAGE)} imports lower layer(s) {sorted(imported - allowed)}"
        )
        assert "__init__" not in imported, f"{path.name} imports from rbdyn_jax/__init__.py"


def test_private_helpers_import_no_public_module():
    for name, paths in module_files().items():
        if name.startswith("_"):
            for path in paths:
                imported = {m for m in package_imports(path) if not m.startswith("_")}
                assert not imported, f"{path.name} imports {sorted(imported)}"


def test_no_private_name_crosses_a_module():
    for paths in module_files().values():
        for path in paths:
            assert not private_names_imported(path), (
                f"{path.relative_to(PACKAGE)} imports {sorted(private_names_imported(path))}"
            )


def test_diffrax_only_where_the_layers_allow_it():
    for name, paths in module_files().items():
        for path in paths:
            if imports_diffrax(path):
                assert name in DIFFRAX or name == "_compat", f"{path.name} imports diffrax"
            if name != "integrate":
                assert "diffeqsolve(" not in path.read_text(), f"{path.name} solves"


def test_checker_sees_a_violation(tmp_path):
    """The checkers themselves: an upward import, an import from `__init__`, a private name
    and diffrax must be detected, not silently missed."""
    bad = tmp_path / "rotation.py"
    bad.write_text(
        "from .integrate import simulate\nimport rbdyn_jax.sweep\n"
        "from . import __version__\nfrom .dynamics import _matvec\n"
        "from diffrax import Tsit5\n"
    )
    assert package_imports(bad) == {"integrate", "sweep", "__init__", "dynamics"}
    assert private_names_imported(bad) == {"dynamics._matvec"}
    assert imports_diffrax(bad)


def test_checker_allows_private_names_only_between_a_packages_files(tmp_path, monkeypatch):
    """Inside a subpackage, a sibling file's private name is the package's own; another
    module's private name, absolute or relative, is still detected."""
    monkeypatch.setitem(globals(), "PACKAGE", tmp_path)  # a package of the files below
    (tmp_path / "dynamics.py").write_text("_matvec = None\n")
    (tmp_path / "_compat.py").write_text("")
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "__init__.py").write_text("")
    (tmp_path / "pkg" / "_b.py").write_text("_y = None\n")
    bad = tmp_path / "pkg" / "_a.py"
    bad.write_text(
        "from ._b import _y\nfrom ..dynamics import _matvec\n"
        "from rbdyn_jax.torques import _private\nfrom .. import _compat\n"
    )
    assert in_subpackage(bad)
    assert private_names_imported(bad) == {"dynamics._matvec", "rbdyn_jax.torques._private"}
    assert package_imports(bad) == {"dynamics", "torques", "_compat"}


@pytest.mark.parametrize(
    "init",
    [
        "__init__.py",
        "rotation/__init__.py",
        "integrate/__init__.py",
        "analytic/__init__.py",
        "scenario/__init__.py",
        "sweep/__init__.py",
        "identify/__init__.py",
        "cli/__init__.py",
        "_program/__init__.py",
    ],
)
def test_reexports_are_grouped_by_module(init):
    """One `from .x import (a as a, b as b)` per module (ruff's combine-as-imports), not a
    statement per name."""
    sources = [
        (node.level, node.module)
        for node in ast.parse((PACKAGE / init).read_text()).body
        if isinstance(node, ast.ImportFrom)
    ]
    assert len(sources) == len(set(sources)), sorted(sources)
