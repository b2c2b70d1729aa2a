"""The documentation site: it builds strictly, documents every public name, every `rbdyn`
subcommand and every scenario key, and its getting-started snippets run; opened from the file
system it requests nothing off the machine, and its search works there."""

import fcntl
import functools
import html
import html.parser
import importlib
import importlib.util
import inspect
import json
import os
import pathlib
import re
import subprocess
import sys
import tomllib
import types
import urllib.parse

import numpy as np
import pytest

import rbdyn_jax
from rbdyn_jax import integrate, scenario

ROOT = pathlib.Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"

# The public modules documented on the API pages (`rbdyn_jax.cli` is the CLI page's).
MODULES = (
    "analytic",
    "dynamics",
    "frames",
    "identify",
    "inertia",
    "integrate",
    "invariants",
    "models",
    "rotation",
    "scenario",
    "state",
    "sweep",
    "torques",
)


def public_names() -> dict[str, list[str]]:
    """Public name → the reference ids that may document it: `rbdyn_jax.X` for a name
    `rbdyn_jax` exports, `rbdyn_jax.MODULE.X` for one of a module's."""
    ids: dict[str, list[str]] = {}
    top = getattr(rbdyn_jax, "__all__", None)
    if top is None:
        top = [
            n
            for n, v in vars(rbdyn_jax).items()
            if not n.startswith("_") and not isinstance(v, types.ModuleType)
        ]
    for name in top:
        ids.setdefault(f"rbdyn_jax.{name}", []).append(f"rbdyn_jax.{name}")
    for mod_name in MODULES:
        mod = importlib.import_module(f"rbdyn_jax.{mod_name}")
        names = getattr(mod, "__all__", None)
        if names is None:  # its own public functions and classes
            names = [
                n
                for n, v in vars(mod).items()
                if not n.startswith("_")
                and (inspect.isfunction(v) or inspect.isclass(v))
                and v.__module__ == mod.__name__
            ]
        for name in names:
            ref = f"rbdyn_jax.{mod_name}.{name}"
            ids.setdefault(ref, [ref])
            if name in top and getattr(rbdyn_jax, name) is getattr(mod, name):
                ids[ref].append(f"rbdyn_jax.{name}")
    return ids


def _build(out: pathlib.Path) -> tuple[int, str]:
    # The figures hook runs the examples as a reader does (cached while their sources stand).
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(out)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    return proc.returncode, proc.stdout + proc.stderr


# The tests reading the built site run on one pytest-xdist worker (--dist loadgroup): a
# second worker would only wait on the lock below while the first builds.
on_the_site = pytest.mark.xdist_group("docs_site")


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


@on_the_site
def test_strict_build(site):
    assert (site / "index.html").exists()


@on_the_site
def test_every_public_name_has_an_api_entry(site):
    built = "\n".join(p.read_text() for p in (site / "api").rglob("*.html"))
    ids = set(re.findall(r'id="(rbdyn_jax\.[\w.]+)"', built))
    missing = [
        ref for ref, accepted in public_names().items() if not any(a in ids for a in accepted)
    ]
    assert not missing, f"public names with no entry in docs/api/: {missing}"


def _cli_reference():
    spec = importlib.util.spec_from_file_location(
        "cli_reference", DOCS / "hooks" / "cli_reference.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@on_the_site
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
    return text[start : text.index(end, start + len(title))]


@on_the_site
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
    minimal = {
        "model": {"kind": "rigid_body", "inertia": {"principal": [1.0, 2.0, 2.5]}},
        "initial": {"omega": [0.0, 0.0, 1.0]},
        "time": {"t1": 1.0, "n": 11},
    }
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


@on_the_site
def test_tutorials_show_their_scripts(site):
    """Each tutorial page includes the script it is about (a `--8<--` snippet), whose
    code appears on the built page."""
    pages = sorted(
        set((ROOT / "docs" / "tutorials").glob("*.md")) - {ROOT / "docs/tutorials/index.md"}
    )
    assert pages
    for md in pages:
        (script,) = re.findall(r'^--8<-- "(examples/[\w.]+)"$', md.read_text(), re.M)
        page = _text(_page(site, f"tutorials/{md.name}"))
        first = next(line for line in (ROOT / script).read_text().splitlines() if line.strip())
        assert first.strip() in page, (md.name, script)


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
    np.testing.assert_allclose(namespace["result"].model.inertia, namespace["J_true"], atol=1e-4)


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
                if (
                    not code
                    and item.match(line)
                    and prev.strip()
                    and not item.match(prev)
                    and not prev.startswith(" ")
                ):
                    bad.append(f"{path.relative_to(ROOT)}: {getattr(node, 'name', '')}")
    assert not bad, bad


# --- Offline: the built site, opened from the file system, requests nothing off the machine.

# An address off the machine: http(s), ws(s) or ftp, or protocol-relative (`//host/...`).
_REMOTE = re.compile(r"^\s*(?:(?:https?|wss?|ftp):)?//", re.I)
# In CSS: url(...) and @import of such an address (data: URIs and relative paths are local).
_CSS_REMOTE = re.compile(
    r"""(?:url\(|@import)\s*(?:url\()?\s*["']?\s*((?:(?:https?|wss?|ftp):)?//[^"')\s]*)""", re.I
)
# In JavaScript: a string literal that starts with an address off the machine.
_JS_REMOTE = re.compile(r"""["'`]((?:https?:|wss?:)?//[\w-]+(?:\.[\w-]+)+[^"'`\s]*)""")
# Elements' attributes that make the browser request their address as the page loads.
_REQUEST_ATTRS = {
    "script": ("src",),
    "img": ("src", "srcset"),
    "iframe": ("src",),
    "frame": ("src",),
    "embed": ("src",),
    "object": ("data",),
    "source": ("src", "srcset"),
    "video": ("src", "poster"),
    "audio": ("src",),
    "track": ("src",),
    "input": ("src",),
    "image": ("href", "xlink:href"),
    "use": ("href", "xlink:href"),
    "link": ("href",),
}
# Remote addresses that the site's scripts name without requesting them from these pages.
_NAMED_NOT_REQUESTED = {
    "http://www.w3.org/": "XML namespace names (KaTeX's SVG and MathML elements)",
    # Material's bundle, on conditions this site never meets:
    "https://unpkg.com/resize-observer-polyfill": "only where a browser lacks ResizeObserver "
    "(every browser since 2020 has it)",
    "https://unpkg.com/mermaid@": "only on a page with a Mermaid diagram (none: checked)",
    "https://api.github.com/": "the repository's facts, only with `repo_url` (unset: checked)",
}


class _PageScan(html.parser.HTMLParser):
    """What a built page asks the browser to load: each (tag, attribute, address) of an element
    that requests its address, the text of its inline `<style>`s, `style=""`s and
    `<script>`s, and its scripts' `src`s in order."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.requests: list[tuple[str, str, str]] = []
        self.styles: list[str] = []
        self.inline_scripts: list[str] = []
        self.scripts: list[str] = []
        self.config: dict | None = None
        self.search_form = False
        self._in: str | None = None
        self._config_next = False

    def handle_starttag(self, tag, attrs):
        a = {k: v or "" for k, v in attrs}
        for name in _REQUEST_ATTRS.get(tag, ()):
            if name not in a or (tag == "link" and a.get("rel") == "canonical"):
                continue  # a canonical link names the page, it loads nothing
            values = a[name].split(",") if name == "srcset" else [a[name]]
            for value in values:
                self.requests.append((tag, name, value.strip().split(" ")[0]))
        if "style" in a:
            self.styles.append(a["style"])
        if tag == "script" and "src" in a:
            self.scripts.append(a["src"])
        if tag == "form" and a.get("name") == "search":
            self.search_form = True
        self._in = tag if tag in ("style", "script") else None
        self._config_next = tag == "script" and a.get("id") == "__config"

    def handle_endtag(self, tag):
        self._in = None

    def handle_data(self, data):
        if self._in == "style":
            self.styles.append(data)
        elif self._in == "script" and data.strip():
            self.inline_scripts.append(data)
            if self._config_next:
                self.config = json.loads(data)


@functools.cache
def _scan_site(site: pathlib.Path) -> dict[pathlib.Path, _PageScan]:
    scans = {}
    for path in sorted(site.rglob("*.html")):
        scan = _PageScan()
        scan.feed(path.read_text())
        scans[path] = scan
    return scans


def _remote_literals(text: str) -> list[str]:
    return [
        url
        for url in _JS_REMOTE.findall(text)
        if not any(url.startswith(known) for known in _NAMED_NOT_REQUESTED)
    ]


@on_the_site
def test_site_requests_nothing_off_the_machine(site):
    """No page or asset of the built site makes a request off the machine: no script, style
    sheet, font, image or frame from a CDN or Google Fonts (`theme.font: false`; the search's
    Web Worker shim bundled), no CSS `url()` or `@import` of one, no script that loads one.
    Plain `<a href>` links to other sites are links, not requests, and are not looked at."""
    scans = _scan_site(site)
    assert len(scans) > 20
    found = []
    for path, scan in scans.items():
        page = path.relative_to(site)
        found += [
            f"{page}: <{tag} {name}={url!r}>"
            for tag, name, url in scan.requests
            if _REMOTE.match(url)
        ]
        found += [
            f"{page}: inline CSS {url!r}"
            for style in scan.styles
            for url in _CSS_REMOTE.findall(style)
        ]
        found += [
            f"{page}: inline script {url!r}"
            for text in scan.inline_scripts
            for url in _remote_literals(text)
        ]
    for path in sorted(site.rglob("*.css")):
        found += [
            f"{path.relative_to(site)}: {url!r}" for url in _CSS_REMOTE.findall(path.read_text())
        ]
    for path in sorted(site.rglob("*.js")):
        if path.relative_to(site).as_posix() == "search/search_index.js":
            continue  # the search index: data (the pages' text), checked below as such
        found += [
            f"{path.relative_to(site)}: {url!r}" for url in _remote_literals(path.read_text())
        ]
    assert not found, "requests off the machine:\n" + "\n".join(found)
    # The conditions on which Material's bundle would load what it names.
    pages = "".join(path.read_text() for path in scans)
    assert 'class="mermaid"' not in pages
    assert 'data-md-component="source"' not in pages


def _local_file(page: pathlib.Path, site: pathlib.Path, address: str) -> pathlib.Path:
    """The file of the site that `address`, relative to `page`, names."""
    assert not _REMOTE.match(address) and not address.startswith("/"), address
    path = (page.parent / urllib.parse.urlsplit(address).path).resolve()
    assert path.is_relative_to(site.resolve()) and path.is_file(), (page, address)
    return path


@on_the_site
def test_search_works_from_the_file_system(site):
    """A page opened from file:// may neither fetch a file nor start a Web Worker. Material's
    search then reads its index from search/search_index.js, which the offline plugin writes
    (the index as a script: `var __index = {...}`), and runs its worker in an iframe through
    the iframe-worker shim, which each page loads from the site itself before Material's
    bundle. (The 404 page, served by a web server only, links the site's root.)"""
    index = json.loads((site / "search" / "search_index.json").read_text())
    script = (site / "search" / "search_index.js").read_text()
    assert script.startswith("var __index = ")
    assert json.loads(script.removeprefix("var __index = ")) == index
    assert len(index["docs"]) > 50
    # Material's bundle: from file:, the index by a script, not a fetch.
    (bundle,) = (site / "assets" / "javascripts").glob("bundle.*.min.js")
    code = bundle.read_text()
    assert 'location.protocol==="file:"' in code and "search/search_index.js" in code
    assert "__index" in code
    for path, scan in _scan_site(site).items():
        if path.name == "404.html":
            continue
        assert scan.search_form, path
        shims = [s for s in scan.scripts if "iframe-worker" in s]
        bundles = [s for s in scan.scripts if re.search(r"/bundle\.\w+\.min\.js$", "/" + s)]
        assert len(shims) == 1 and len(bundles) == 1, (path, scan.scripts)
        assert scan.scripts.index(shims[0]) < scan.scripts.index(bundles[0]), path
        shim = _local_file(path, site, shims[0]).read_text()
        assert 'location.protocol==="file:"&&(window.Worker=' in shim, path
        _local_file(path, site, scan.config["search"])  # the search worker, in the site
        _local_file(path, site, f"{scan.config['base']}/search/search_index.js")


@on_the_site
def test_wide_tables_and_equations_scroll_in_their_column(site):
    """A table or display equation wider than the text column scrolls inside it (and shows it
    does), rather than running past the column's edge, where it is cut off: the performance
    page's tables, the physics guide's long equations. The rules are in
    docs/assets/stylesheets/overflow.css, which every page loads after Material's."""
    sheet = site / "assets" / "stylesheets" / "overflow.css"
    assert sheet.is_file(), "docs/assets/stylesheets/overflow.css was not built"
    css = sheet.read_text()
    rules: dict[str, str] = {}
    for selectors, body in re.findall(
        r"([^{}]+)\{([^{}]*)\}", re.sub(r"/\*.*?\*/", "", css, flags=re.S)
    ):
        for selector in selectors.split(","):
            rules[" ".join(selector.split())] = rules.get(" ".join(selector.split()), "") + body
    for selector in (".md-typeset table:not([class])", ".md-typeset .arithmatex .katex-display"):
        body = re.sub(r"\s+", "", rules.get(selector, ""))
        assert "max-width:100%" in body and "overflow-x:auto" in body, selector
    assert "max-width:100%" in rules.get(".md-typeset__table", "").replace(" ", "")
    for path, scan in _scan_site(site).items():
        if path.name == "404.html":
            continue
        sheets = [url for tag, name, url in scan.requests if tag == "link" and url.endswith(".css")]
        ours = [u for u in sheets if u.endswith("assets/stylesheets/overflow.css")]
        main = [u for u in sheets if re.search(r"stylesheets/main\.\w+\.min\.css$", u)]
        assert ours and main and sheets.index(ours[0]) > sheets.index(main[0]), (path, sheets)
        _local_file(path, site, ours[0])
    # What the rules are for: wide tables on the performance page, display math (KaTeX, in
    # div.arithmatex) on the physics guide.
    assert _page(site, "performance.md").count("<table>") >= 5
    assert _page(site, "physics.md").count('<div class="arithmatex">') >= 20
