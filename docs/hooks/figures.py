"""MkDocs hook: the figures of the site, made from the shipped scripts when the site is built.

Nothing generated is committed. At each build:

- every example script `examples/<name>.py` is run as a reader runs it, when its cached
  output is missing or older than the script, this hook or any source file of `rbdyn_jax`,
  with `--out-dir` into `results/docs/figures/<name>/` (under the git-ignored `results/`),
  and its PNG is added
  to the site as `tutorials/figures/<name>.png` and what it printed is kept beside it;
- the plots of the performance page (`PERF_PLOTS`: work–precision, long horizons) are drawn
  from the committed results `docs/performance/<name>.json` by `benchmarks/<name>.py`'s own
  `plot`, into `results/docs/figures/performance/<name>/`, and added as
  `performance/<name>.png`.

Pages reference the figures by those paths (`figures/<name>.png` from a tutorial), so
`mkdocs build --strict` checks the links as for any other file. A marker line
`<!-- example-output: <name> -->` in a page is replaced by what the example printed, as a
code block (its output paths shown as the script's default, `results/examples`).

The scripts share JAX's persistent compilation cache in
`results/docs/jax-cache/` (unless `JAX_COMPILATION_CACHE_DIR` is set), so a rerun after an
edit recompiles only what changed.

Scripts run in parallel, `RBDYN_DOCS_JOBS` at a time (default: the number of cores). A script
that fails stops the build with its output; no figure is ever replaced by a placeholder.
Figures are written into a temporary folder and moved into the cache only when the script
succeeded.
"""

from __future__ import annotations

import concurrent.futures
import logging
import os
import pathlib
import re
import shutil
import subprocess
import sys
import time

from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File, Files

log = logging.getLogger("mkdocs.hooks.figures")

ROOT = pathlib.Path(__file__).resolve().parents[2]
EXAMPLES_DIR = ROOT / "examples"
LIBRARY_DIR = ROOT / "rbdyn_jax"
CACHE = ROOT / "results" / "docs" / "figures"
JAX_CACHE = ROOT / "results" / "docs" / "jax-cache"
HOOK = pathlib.Path(__file__).resolve()  # a change to this hook reruns the examples
DEFAULT_OUT = "results/examples"  # the examples' own default --out-dir, shown in printouts

EXAMPLES = (
    "torque_free_flip",
    "lagrange_top",
    "gg_integrable",
    "satellite_pitch",
    "rotating_platform",
    "long_horizon_sweep",
    "identify_inertia",
    "identify_restoring_moment",
)

# The performance page's plots: `plot(rows, path)` of each benchmark script named here,
# drawn from its committed JSON.
PERF_PLOTS = ("work_precision", "long_horizon")
_RUN_PLOT = """\
import importlib, json, pathlib, sys
sys.path.insert(0, str(pathlib.Path(sys.argv[1]).parent))
script = importlib.import_module(pathlib.Path(sys.argv[1]).stem)
script.plot(json.loads(pathlib.Path(sys.argv[2]).read_text())["rows"], sys.argv[3])
"""

_OUTPUT_MARKER = re.compile(r"^<!-- example-output: (\w+) -->$", re.MULTILINE)
_FOLDERS: dict[str, pathlib.Path] = {}  # example -> its cache folder in this build


def _library_mtime() -> float:
    return max(p.stat().st_mtime for p in LIBRARY_DIR.rglob("*.py"))


def _stale(outputs: list[pathlib.Path], sources: list[pathlib.Path], newest: float) -> bool:
    if not all(p.is_file() for p in outputs):
        return True
    oldest = min(p.stat().st_mtime for p in outputs)
    return oldest < max([newest] + [p.stat().st_mtime for p in sources])


def _env() -> dict:
    env = dict(os.environ, MPLBACKEND="Agg")
    # JAX's persistent compilation cache (and rbdyn_jax's trace cache inside it), shared by
    # the scripts' runs: a rerun after an edit recompiles only the programs that changed.
    env.setdefault("JAX_COMPILATION_CACHE_DIR", str(JAX_CACHE))
    env.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    return env


def _run(name: str, command: list[str], dest: pathlib.Path, expected: list[str]) -> float:
    """Run `command` (which writes into the temporary folder `dest`.tmp), keep its output in
    `dest`/output.txt and move the folder into place. Returns the wall time."""
    tmp = dest.with_name(f"{dest.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    command = [a.replace("{out}", str(tmp)) for a in command]
    started, t0 = time.time(), time.perf_counter()
    proc = subprocess.run(command, cwd=ROOT, env=_env(), capture_output=True, text=True)
    wall = time.perf_counter() - t0
    missing = [f for f in expected if not (tmp / f).is_file()]
    if proc.returncode != 0 or missing:
        shutil.rmtree(tmp, ignore_errors=True)
        raise PluginError(
            f"figures: {name} failed (exit status {proc.returncode}"
            + (f", did not write {', '.join(missing)}" if missing else "")
            + f"): {' '.join(command)}\n{proc.stdout[-3000:]}{proc.stderr[-3000:]}"
        )
    printed = proc.stdout.replace(str(tmp), DEFAULT_OUT)
    (tmp / "output.txt").write_text(printed)
    for f in tmp.iterdir():  # dated by the start: a source edited during the run is newer
        os.utime(f, (started, started))
    shutil.rmtree(dest, ignore_errors=True)
    try:
        tmp.rename(dest)
    except OSError:  # a concurrent build has just put its own, equally fresh, copy there
        shutil.rmtree(tmp, ignore_errors=True)
    return wall


def on_files(files: Files, config) -> Files:
    library = _library_mtime()
    jobs = {}  # name -> (command, dest, expected files)
    for name in EXAMPLES:
        script, dest = EXAMPLES_DIR / f"{name}.py", CACHE / name
        command = [sys.executable, str(script), "--out-dir", "{out}"]
        expected = [f"{name}.png"]
        if _stale([dest / f for f in expected + ["output.txt"]], [script, HOOK], library):
            jobs[name] = (command, dest, expected)
    for plot in PERF_PLOTS:
        script = ROOT / "benchmarks" / f"{plot}.py"
        result = ROOT / "docs" / "performance" / f"{plot}.json"
        dest = CACHE / "performance" / plot
        if _stale([dest / f"{plot}.png"], [script, result], library):
            jobs[f"{plot} plot"] = (
                [sys.executable, "-c", _RUN_PLOT, str(script), str(result), f"{{out}}/{plot}.png"],
                dest,
                [f"{plot}.png"],
            )

    if jobs:
        workers = int(os.environ.get("RBDYN_DOCS_JOBS", os.cpu_count() or 1))
        log.info(f"figures: running {len(jobs)} script(s), {workers} at a time: {', '.join(jobs)}")
        t0 = time.perf_counter()
        with concurrent.futures.ThreadPoolExecutor(max_workers=workers) as pool:
            # the identification examples take longest: start them first
            order = sorted(jobs, key=lambda n: not n.startswith("identify"))
            futures = {n: pool.submit(_run, n, *jobs[n]) for n in order}
            walls = {n: f.result() for n, f in futures.items()}
        log.info(
            "figures: "
            + ", ".join(f"{n} {w:.1f} s" for n, w in walls.items())
            + f"; {time.perf_counter() - t0:.1f} s in all"
        )

    # Hook modules (docs/hooks/*.py) are build code, not pages or assets of the site.
    for f in [f for f in files if f.src_uri.startswith("hooks/")]:
        files.remove(f)

    def add(uri: str, path: pathlib.Path) -> None:
        stale = files.get_file_from_path(uri)  # e.g. a stray copy under docs/
        if stale is not None:
            files.remove(stale)
        files.append(File.generated(config, uri, abs_src_path=str(path)))

    for name in EXAMPLES:
        add(f"tutorials/figures/{name}.png", CACHE / name / f"{name}.png")
        _FOLDERS[name] = CACHE / name
    for plot in PERF_PLOTS:
        add(f"performance/{plot}.png", CACHE / "performance" / plot / f"{plot}.png")
    return files


def on_page_markdown(markdown: str, page, config, files) -> str:
    def output(match):
        name = match.group(1)
        folder = _FOLDERS.get(name)
        if folder is None:
            raise PluginError(f"{page.file.src_uri}: no example named {name!r}.")
        return "```text\n" + (folder / "output.txt").read_text().rstrip() + "\n```"

    return _OUTPUT_MARKER.sub(output, markdown)
