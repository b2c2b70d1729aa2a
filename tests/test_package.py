"""The installed package as a user meets it: its version in one place, and an import that
costs nothing until a name is used."""

import ast
import importlib
import importlib.metadata
import pathlib
import subprocess
import sys

import pytest

import rbdyn_jax as rb


def test_version_is_the_installed_distributions():
    assert rb.__version__ == importlib.metadata.version("rbdyn_jax")


# `rbdyn_jax/__init__.py` imports its submodules and names lazily (PEP 562): checked in
# fresh processes, since this one has imported everything.


def _fresh(code: str) -> str:
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    return run.stdout


def test_importing_the_package_imports_no_jax():
    out = _fresh(
        "import sys, rbdyn_jax\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in "
        "('jax', 'jaxlib', 'equinox', 'diffrax', 'numpy')))"
    )
    assert out.strip() == "[]"


def test_lazy_names_resolve_to_the_submodules_objects():
    _fresh(
        "import rbdyn_jax as rb\n"
        "assert rb.simulate_batch is rb.integrate.simulate_batch\n"
        "from rbdyn_jax import RigidBody, State, configure_xla\n"
        "from rbdyn_jax.models import RigidBody as R\n"
        "assert RigidBody is R and State is rb.state.State\n"
        "assert configure_xla is rb.integrate.configure_xla\n"
        "assert rb.sweep.__name__ == 'rbdyn_jax.sweep'\n"
    )
    for name in rb.__all__:
        module = importlib.import_module(f"rbdyn_jax.{rb._ORIGIN[name]}")
        assert getattr(rb, name) is getattr(module, name), name
    assert "RigidBody" in vars(rb)  # kept once resolved


def test_an_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="module 'rbdyn_jax' has no attribute 'nope'"):
        rb.nope  # noqa: B018
    with pytest.raises(ImportError):
        exec("from rbdyn_jax import nope", {})
    assert not hasattr(rb, "nope")


def test_dir_lists_every_public_name_and_submodule():
    listed = _fresh("import rbdyn_jax as rb; print(' '.join(dir(rb)))").split()
    assert set(rb.__all__) <= set(listed)
    assert set(rb._SUBMODULES) <= set(listed) and "__version__" in listed
    assert listed == sorted(listed)


def _type_checking_imports() -> tuple[set[str], dict[str, set[str]]]:
    """The submodules and `{module: names}` that `__init__.py` imports for type checkers."""
    tree = ast.parse(pathlib.Path(rb.__file__).read_text())
    block = next(
        node
        for node in tree.body
        if isinstance(node, ast.If) and ast.unparse(node.test) == "TYPE_CHECKING"
    )
    modules, names = set(), {}
    for node in block.body:
        assert isinstance(node, ast.ImportFrom) and node.level == 1, ast.unparse(node)
        assert all(a.asname == a.name for a in node.names)  # `X as X`: a re-export
        if node.module is None:
            modules |= {a.name for a in node.names}
        else:
            names[node.module] = {a.name for a in node.names}
    return modules, names


def test_the_type_checking_block_names_what_the_lazy_table_does():
    """Type checkers and IDEs read the `if TYPE_CHECKING:` imports; the interpreter reads
    `_SUBMODULES` and `_EXPORTS`: the same modules and names."""
    modules, names = _type_checking_imports()
    assert modules == set(rb._SUBMODULES)
    assert names == {m: set(v) for m, v in rb._EXPORTS.items()}
    assert sorted(rb.__all__) == sorted(n for v in names.values() for n in v)
