"""DESIGN.md layering: each module may import only the modules of the layers above it.

The order is the table of DESIGN.md, top (bottom layer) first. Private helpers (`_x.py`)
sit below everything and import no public module; `__init__` only re-exports.
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
    "sweep",
    "identify",
    "cli",
]
PACKAGE = pathlib.Path(rbdyn_jax.__file__).parent
PRESENT = [m for m in LAYERS if (PACKAGE / f"{m}.py").exists()]


def package_imports(path: pathlib.Path) -> set[str]:
    """Names of rbdyn_jax modules imported by the file at `path` (absolute or relative)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level == 1:  # from .x import y / from . import x
                if node.module:
                    found.add(node.module.split(".")[0])
                else:
                    found.update(a.name for a in node.names)
            elif node.level == 0 and node.module and node.module.startswith("rbdyn_jax"):
                parts = node.module.split(".")
                found.update(parts[1:2] or [a.name for a in node.names])
        elif isinstance(node, ast.Import):
            for a in node.names:
                parts = a.name.split(".")
                if parts[0] == "rbdyn_jax" and len(parts) > 1:
                    found.add(parts[1])
    return found


def test_every_module_is_in_a_layer():
    modules = {p.stem for p in PACKAGE.glob("*.py")}
    public = {m for m in modules if not m.startswith("_")}
    assert public <= set(LAYERS), f"modules missing from DESIGN.md layers: {public - set(LAYERS)}"
    assert {"rotation", "inertia", "cli"} <= public


@pytest.mark.parametrize("module", PRESENT)
def test_no_module_imports_a_lower_layer(module):
    path = PACKAGE / f"{module}.py"
    allowed = set(LAYERS[: LAYERS.index(module)])
    imported = {m for m in package_imports(path) if not m.startswith("_")}
    assert imported <= allowed, f"{module} imports lower layer(s) {sorted(imported - allowed)}"


def test_private_helpers_import_no_public_module():
    for path in PACKAGE.glob("_*.py"):
        if path.name == "__init__.py":
            continue
        imported = {m for m in package_imports(path) if not m.startswith("_")}
        assert not imported, f"{path.name} imports {sorted(imported)}"


def test_checker_sees_a_violation(tmp_path):
    """The checker itself: an upward import must be detected, not silently missed."""
    bad = tmp_path / "rotation.py"
    bad.write_text("from .integrate import simulate\nimport rbdyn_jax.sweep\n")
    assert package_imports(bad) == {"integrate", "sweep"}

