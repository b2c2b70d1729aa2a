"""The documentation site: it builds strictly, documents every public name, every `rbdyn`
subcommand and every scenario key, and its getting-started snippets run."""

import fcntl
import functools
import html
import importlib
import importlib.util
import inspect
import os
import pathlib
import re
import subprocess
import sys
import tomllib
import types

import numpy as np
import pytest

import rbdyn_jax
from rbdyn_jax import integrate, scenario

ROOT = pathlib.Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"

# The public modules documented on the API pages (`rbdyn_jax.cli` is the CLI page's).
MODULES = ("analytic", "dynamics", "frames", "identify", "inertia", "integrate",
           "invariants", "models", "rotation", "scenario", "state", "sweep", "torques")


def public_names() -> dict[str, list[str]]:
    """Public name → the reference ids that may document it: `rbdyn_jax.X` for a name
    `rbdyn_jax` exports, `rbdyn_jax.MODULE.X` for one of a module's."""
    ids: dict[str, list[str]] = {}
    top = getattr(rbdyn_jax, "__all__", None)
    if top is None:
        top = [n for n, v in vars(rbdyn_jax).items()
               if not n.startswith("_") and not isinstance(v, types.ModuleType)]
    for name in top:
        ids.setdefault(f"rbdyn_jax.{name}", []).append(f"rbdyn_jax.{name}")
    for mod_name in MODULES:
        mod = importlib.import_module(f"rbdyn_jax.{mod_name}")
        names = getattr(mod, "__all__", None)
        if names is None:  # its own public functions and classes
            names = [n for n, v in vars(mod).items() if not n.startswith("_")
                     and (inspect.isfunction(v) or inspect.isclass(v))
                     and v.__module__ == mod.__name__]
        for name in names:
            ref = f"rbdyn_jax.{mod_name}.{name}"
            ids.setdefault(ref, [ref])
            if name in top and getattr(rbdyn_jax, name) is getattr(mod, name):
                ids[ref].append(f"rbdyn_jax.{name}")
    return ids


def _build(out: pathlib.Path) -> tuple[int, str]:
    # The figures hook runs the examples as a reader does (cached while their sources stand).
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(out)],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    return proc.returncode, proc.stdout + proc.stderr


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> pathlib.Path:
    """The site built by `mkdocs build --strict` (any warning fails it: a broken link or
    anchor, a page missing from the nav, a docstring mkdocstrings cannot render). Under
    pytest-xdist the workers share one build, made by the first that needs it."""
    if os.environ.get("PYTEST_XDIST_WORKER") is None:
        out = tmp_path_factory.mktemp("site")
        code, log = _build(out)
    else:  # the session's folder, shared by its workers
        shared = tmp_path_factory.getbasetemp().parent
        out, result = shared / "docs-site", shared / "docs-site.result"
        with open(shared / "docs-site.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if not result.exists():
                code, log = _build(out)
                result.write_text(f"{code}\n{log}")
            code, log = result.read_text().split("\n", 1)
    assert int(code) == 0, log
    return out


def _page(site: pathlib.Path, name: str) -> str:
    """The built page `name` (`cli.md` → `cli.html`, or `cli/index.html`)."""
    stem = name.removesuffix(".md")
    for path in (site / f"{stem}.html", site / stem / "index.html"):
        if path.exists():
            return path.read_text()
    raise AssertionError(f"{name} was not built")


def _text(page: str) -> str:
    return html.unescape(re.sub(r"<[^>]+>", "", page))


def test_strict_build(site):
    assert (site / "index.html").exists()


def test_every_public_name_has_an_api_entry(site):
    built = "\n".join(p.read_text() for p in (site / "api").rglob("*.html"))
    ids = set(re.findall(r'id="(rbdyn_jax\.[\w.]+)"', built))
    missing = [ref for ref, accepted in public_names().items()
               if not any(a in ids for a in accepted)]
    assert not missing, f"public names with no entry in docs/api/: {missing}"


def _cli_reference():
    spec = importlib.util.spec_from_file_location("cli_reference",
                                                  DOCS / "hooks" / "cli_reference.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_cli_page_documents_every_subcommand(site):
    hook = _cli_reference()
    parser = hook.cli_parser()
    commands = hook.subcommands(parser)
    assert {"sweep", "plot", "fit", "scenarios", "demo"} <= set(commands)
    page = _page(site, "cli.md")
    text = _text(page)
    for name, (sub, _) in commands.items():
        assert f'id="rbdyn-{name}"' in page, name
        assert f"usage: rbdyn {name}" in text, name
        for action in sub._actions:  # every option, with its default
            for option in action.option_strings:
                if option not in ("-h", "--help"):
                    assert option in text, (name, option)
    assert "--version" in text


def _section(text: str, title: str, end: str) -> str:
    start = text.index(title)
    return text[start:text.index(end, start + len(title))]


def test_scenarios_page_documents_every_kind_and_key(site):
    text = _text(_page(site, "scenarios.md"))
    torques = _section(text, "Torques¶", "Frames¶")
    for kind, spec in scenario.TORQUES.items():
        assert kind in torques, kind
        for key in spec.params:
            assert key in torques, (kind, key)
    frames = _section(text, "Frames¶", "[initial]")
    for kind, spec in scenario.FRAMES.items():
        assert kind in frames, kind
        for key in spec.params:
            assert key in frames, (kind, key)
    dists = _section(text, "Quantities and distributions¶", "Top level¶")
    for name, cls in scenario.DISTRIBUTIONS.items():
        assert name in dists, name
        for field in cls.__dataclass_fields__:
            assert field in dists, (name, field)
    assert "uniform_so3" in text
    for name in [*scenario.SUMMARIES, *scenario.SOLVERS]:
        assert name in text, name
    for key in scenario.Scenario.TOP:
        assert key in text, key


def _merged(base: dict, part: dict) -> dict:
    out = dict(base)
    for key, value in part.items():
        both = isinstance(value, dict) and isinstance(base.get(key), dict)
        out[key] = _merged(base[key], value) if both else value
    return out


def test_scenarios_page_examples_validate():
    """Every scenario shown on the page loads, and so does every fragment (a torque, a
    frame, an attitude) set into a minimal scenario; the shipped example is included."""
    page = (DOCS / "scenarios.md").read_text()
    assert '--8<-- "rbdyn_jax/scenarios/torque_free_flip.toml"' in page
    minimal = {"model": {"kind": "rigid_body", "inertia": {"principal": [1.0, 2.0, 2.5]}},
               "initial": {"omega": [0.0, 0.0, 1.0]}, "time": {"t1": 1.0, "n": 11}}
    complete = 0
    for block in re.findall(r"```toml\n(.*?)```", page, re.S):
        if block.startswith("--8<--"):
            continue
        try:
            part = tomllib.loads(block)
        except tomllib.TOMLDecodeError:  # alternatives of one key, side by side
            assert "weight = 9.81" in block, block
            continue
        if "initial" in part and "model" in part:
            complete += 1
            scenario.Scenario.from_dict(part)
        elif "attitude" in part:
            scenario.Scenario.from_dict(_merged(minimal, {"initial": part}))
        else:
            scenario.Scenario.from_dict(_merged(minimal, part))
    assert complete >= 1


def test_results_table_matches_the_codes():
    page = (DOCS / "api" / "simulate.md").read_text()
    rows = re.findall(r"^\| (\d+) \| `(\w+)` \|", page, re.M)
    assert rows
    names = integrate.result_names()
    for code, name in rows:
        assert names[int(code)] == name


@functools.cache
def _python_blocks(page: pathlib.Path) -> tuple[str, ...]:
    return tuple(re.findall(r"```python\n(.*?)```", page.read_text(), re.S))


def test_getting_started_snippets_run(tmp_path, monkeypatch):
    """The snippets run in order, in one namespace, as a reader pasting them would."""
    monkeypatch.chdir(tmp_path)
    page = DOCS / "getting-started.md"
    blocks = _python_blocks(page)
    assert len(blocks) >= 5
    namespace: dict = {}
    for block in blocks:
        exec(compile(block, str(page), "exec"), namespace)  # raises on any error
    assert float(np.max(np.abs(namespace["E"] - namespace["E"][0]))) < 1e-6
    assert bool(np.all(namespace["batch"].result == rbdyn_jax.RESULTS.successful))
    assert np.all(np.isfinite(np.asarray(namespace["grad"])))
    assert namespace["stats"]["status"] == {"successful": 64}
    np.testing.assert_allclose(namespace["result"].model.inertia, namespace["J_true"],
                               atol=1e-4)


def test_home_page_snippet_runs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    page = DOCS / "index.md"
    namespace: dict = {}
    for block in _python_blocks(page):
        exec(compile(block, str(page), "exec"), namespace)
    assert namespace["traj"].result == rbdyn_jax.RESULTS.successful


def test_docstring_lists_are_set_off_from_their_label():
    """Markdown starts a list only after a blank line: a docstring whose `- item` follows a
    text line directly (`**Arguments:**` then `- x`) renders as one paragraph of hyphens."""
    import ast
    import re

    item = re.compile(r"\s*(?:[-*+]|\d+\.) ")
    bad = []
    for path in (ROOT / "rbdyn_jax").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef)):
                continue
            lines = (ast.get_docstring(node) or "").split("\n")
            code = False
            for prev, line in zip(lines, lines[1:]):
                code ^= prev.lstrip().startswith("```")
                if (not code and item.match(line) and prev.strip()
                        and not item.match(prev) and not prev.startswith(" ")):
                    bad.append(f"{path.relative_to(ROOT)}: {getattr(node, 'name', '')}")
    assert not bad, bad
