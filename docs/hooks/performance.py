"""MkDocs hook: the tables of the performance page, rendered from the committed results.

`docs/performance/*.json` are the files the benchmark scripts wrote (`--out`), copied as
they are, and `environment.json` describes the machine and the run. A marker line
`<!-- perf-table: NAME -->` in a page is replaced by the table NAME of `TABLES` below. The
build fails if a result is missing, or if the results were not all measured with the same
jax, diffrax and equinox as `environment.json` says.

To update the page: run the commands it lists, copy the JSON files here, update
`environment.json`, and rebuild.
"""

from __future__ import annotations

import json
import math
import pathlib
import re

from mkdocs.exceptions import PluginError

RESULTS = pathlib.Path(__file__).resolve().parents[1] / "performance"
_MARKER = re.compile(r"^<!-- perf-table: ([\w.]+) -->$", re.MULTILINE)


def _load(name: str) -> dict:
    path = RESULTS / f"{name}.json"
    if not path.is_file():
        raise PluginError(f"performance: {path} is missing.")
    return json.loads(path.read_text())


def _table(head: list[str], rows: list[list], align: str | None = None) -> str:
    """A Markdown table; `align` one character per column, "l" or "r" (default: the first
    column left, the others right)."""
    align = align or "l" + "r" * (len(head) - 1)
    rule = ["---" if a == "l" else "---:" for a in align]
    lines = [head, rule] + [[str(c) for c in r] for r in rows]
    return "\n".join("| " + " | ".join(line) + " |" for line in lines)


def _n(x: float) -> str:
    """A rate or count: thousands separated by a thin space."""
    return f"{x:,.0f}".replace(",", "\u2009")


def _e(x: float) -> str:
    return f"{x:.1e}"


def _environment() -> str:
    env = _load("environment")
    versions = ", ".join(f"{pkg} {v}" for pkg, v in env["versions"].items())
    return "\n".join(
        [
            f"- **Date of the run:** {env['date']}",
            f"- **CPU:** {env['cpu']}, {env['cores']} cores",
            f"- **Operating system:** {env['os']}",
            f"- **Versions:** {versions}",
        ]
    )


_MODELS = {
    "torque_free": "torque-free",
    "heavy_top": "heavy top",
    "gravity_gradient": "gravity gradient",
}


def _throughput() -> str:
    """One column per (model, N), one row per method: narrow enough for the page."""
    d = _load("throughput")
    cols = d["rows"]
    lanes = d["meta"]["lanes"]

    def rate(key):
        return [_n(r[key]["traj_per_s"]) if key in r else "—" for r in cols]

    def ratio(key):
        return [f"{r['default']['traj_per_s'] / r[key]['traj_per_s']:.2f}" for r in cols]

    rows = [
        ["default", *rate("default")],
        [f"`Lanes({lanes})`", *rate("lanes")],
        ["`Vmap()`", *rate("plain")],
        ["numba", *rate("numba")],
        ["numba, same accuracy", *rate("numba_equal")],
        ["its tolerance", *[f"{r['numba_equal']['tol']:.1e}" for r in cols]],
        ["scipy", *[f"{r['scipy']['traj_per_s']:.1f}" if "scipy" in r else "—" for r in cols]],
        ["default ÷ numba", *ratio("numba")],
        ["default ÷ numba, same accuracy", *ratio("numba_equal")],
        ["median error, default", *[_e(r["default"]["median_error"]) for r in cols]],
        ["median error, numba", *[_e(r["numba"]["median_error"]) for r in cols]],
    ]
    head = [""] + [f"{_MODELS[r['model']]}<br>N = {_n(r['batch'])}" for r in cols]
    return _table(head, rows)


def _work_precision() -> str:
    """One row per tolerance, one column per method; a cell holds µs per trajectory and the
    largest error."""
    d = _load("work_precision")
    methods = list(dict.fromkeys(r["method"] for r in d["rows"]))
    tols = sorted({r["tol"] for r in d["rows"]}, reverse=True)
    cell = {(r["method"], r["tol"]): r for r in d["rows"]}
    rows = []
    for tol in tols:
        row = [f"{tol:.0e}"]
        for m in methods:
            r = cell.get((m, tol))
            row.append("—" if r is None else f"{r['us_per_traj']:.0f} µs<br>{_e(r['max_error'])}")
        rows.append(row)
    return _table(["rtol = atol"] + methods, rows)


def _gradients() -> str:
    d = _load("gradients")
    rows = []
    for r in d["rows"]:
        if "error" in r:
            rows.append([r["method"], "failed: " + r["error"], "", "", ""])
            continue
        rows.append(
            [
                r["method"],
                f"{1e3 * r['time_s']:.2f}",
                f"{r['x_default_forward']:.2f}",
                f"{r['first_call_s']:.2f}",
                _e(r["rel_error"]),
            ]
        )
    return _table(
        ["method", "time (ms)", "× forward loss", "first call (s)", "relative error"], rows
    )


def _gradient_steps() -> str:
    d = _load("gradient_steps")
    rows = [
        [
            r["method"],
            f"{r['us_per_step']:.2f}",
            f"{r['x_forward_step']:.2f}",
            f"{r['median_us_per_step']:.2f}",
        ]
        for r in d["rows"]
    ]
    return _table(["step", "µs per step", "× forward step", "median µs per step"], rows)


_CASES = {
    "simulate": "`simulate`",
    "default": "`simulate_batch`",
    "batch": "the same, `Vmap()`",
    "lanes": "the same, `Lanes(64)`",
    "grad": "`grad`, `Vmap()`",
    "jacfwd_lanes": "`jacfwd`, `Lanes(16)`",
    "grad_lanes": "`grad`, `Lanes(16)`",
    "grad_lanes_ctor": "the same, checked model",
    "grad_lanes_ctor_nan": "the same, `EQX_ON_ERROR=nan`",
    "bare_diffrax": "bare diffrax",
}


def _compile() -> str:
    d = _load("compile")
    rows = []
    for r in d["rows"]:
        rel = f"{r['vs_bare']:.2f}" if r.get("vs_bare") else "—"
        rows.append(
            [
                _CASES.get(r["case"], r["case"]),
                f"{r['no_cache_s']:.2f}",
                rel,
                f"{r['warm_s']:.2f}",
                f"{r['speedup_warm']:.1f}",
                str(len(set(r["callback_programs"]))),
                str(r["trace_hits"]),
            ]
        )
    imports = [r["import_s"] for r in d["rows"]]
    builds = [r["build_s"] for r in d["rows"]]
    writes = [r["cold_s"] - r["no_cache_s"] for r in d["rows"]]
    return (
        _table(["case", "no cache", "÷ bare", "warm", "speed-up", "refused", "traces"], rows)
        + "\n\nWith an empty cache directory the first call took from "
        f"{min(writes):+.2f} to {max(writes):+.2f} s more than without a cache (writing "
        "the entries, within the runs' spread). Before the first call, `import jax` and "
        "`import rbdyn_jax.integrate` (the solver layer with diffrax, which `import "
        "rbdyn_jax` alone leaves to the first name used) took "
        f"{min(imports):.2f}–{max(imports):.2f} s, and building the inputs and the model "
        f"{min(builds):.2f}–{max(builds):.2f} s."
    )


def _sweep_scale() -> str:
    """One row per configuration the three parts ran (a configuration shared by two parts
    ran once)."""
    d = _load("sweep_scale")
    runs = {}
    for part in ("chunks", "devices", "memory"):
        for r in d[part]["rows"]:
            runs[(r["n"], r["chunk"], r["devices"])] = r
    rows = [
        [
            _n(r["n"]),
            _n(r["chunk"]),
            r["devices"],
            f"{r['first_chunk_s']:.2f}",
            f"{r['rest_s']:.2f}",
            _n(r["steady_traj_per_s"]),
            f"{r['peak_rss_mib']:.0f}",
        ]
        for _, r in sorted(runs.items())
    ]
    base = [r["base_rss_mib"] for r in runs.values()]
    return (
        _table(
            [
                "N",
                "chunk",
                "devices",
                "first chunk (s)",
                "the rest (s)",
                "steady traj/s",
                "peak RSS (MiB)",
            ],
            rows,
        )
        + f"\n\nRSS after importing rbdyn_jax and starting JAX: {min(base):.0f}–"
        f"{max(base):.0f} MiB. Stores of 1 and {d['devices']['rows'][-1]['devices']} devices "
        "bitwise identical: "
        + ("yes." if d["devices"]["identical"] else "**no**.")
        + ("\n\n" + _sweep_dask(d["dask"]) if "dask" in d else "")
    )


def _sweep_dask(d: dict) -> str:
    """In-process against a Dask LocalCluster: one row each, the ratio, bitwise identity."""
    rows = []
    for r in d["rows"]:
        dask = r["engine"] == "dask"
        rows.append(
            [
                r["engine"],
                r["workers"] if dask else "—",
                r["devices"],
                f"{r['cluster_start_s']:.2f}" if dask else "—",
                f"{r['first_chunk_s']:.2f}",
                f"{r['rest_s']:.2f}",
                _n(r["steady_traj_per_s"]),
                f"{r['worker_peak_rss_mib']:.0f}" if dask else "—",
            ]
        )
    return (
        f"In-process against a Dask `LocalCluster` of {d['workers']} worker processes "
        f"({d['devices_per_worker']} device each), N = {_n(d['n'])}, chunk "
        f"{_n(d['chunk'])}:\n\n"
        + _table(
            [
                "engine",
                "workers",
                "devices",
                "cluster start (s)",
                "first chunk (s)",
                "the rest (s)",
                "steady traj/s",
                "worker peak RSS (MiB)",
            ],
            rows,
        )
        + f"\n\nLocalCluster ÷ in-process, steady traj/s: {d['ratio']:.2f}. Stores "
        "bitwise identical: " + ("yes." if d["identical"] else "**no**.")
    )


def _store_write() -> str:
    """One row per layout and compressor of `store_write.py`: the write rate and the bytes
    a trajectory, each beside the store's own compressor's."""
    d = _load("store_write")
    rows = [
        [
            "every state" if r["trajectories"] == "all" else "no states",
            f"{r['compressor']}: {r['cname']} {r['clevel']}"
            if r["compressor"] == "store's"
            else f"{r['cname']} {r['clevel']}",
            _n(r["n"]),
            f"{_n(r['traj_per_s'])} ({r['speed_ratio']:.2f}×)",
            f"{r['bytes_per_traj']:,.0f} ({r['size_ratio']:.3f}×)".replace(",", "\u2009"),
        ]
        for r in d["rows"]
    ]
    head = ["store keeps", "Blosc compressor", "N", "written traj/s", "bytes a trajectory"]
    return _table(head, rows, "llrrr")


def _identify() -> str:
    d = _load("identify")
    rows = [
        [
            r["method"],
            f"{r['wall_s']:.2f}",
            f"{r['residual_evals']} / {r['jacobian_evals']}",
            _e(r["max_abs_err_J"]),
            f"{r['max_err_in_stderr']:.2f}",
            f"{r['time_ratio_scipy_over_this']:.1f}",
        ]
        for r in d["rows"]
    ]
    return _table(
        ["method", "wall (s)", "evaluations", "max \\|ΔJ\\|", "÷ std. error", "scipy ÷ this"], rows
    )


_GPU_METHODS = {
    "default": "default, float64",
    "default f32": "default, float32",
    "kernel": "`Kernel()`, float64",
    "kernel f32": "`Kernel()`, float32",
    "kernel gradient": "`Kernel()` gradient (6 parameters)",
    "lanes": "`Lanes()`, float64",
    "lanes f32": "`Lanes()`, float32",
    "lanes gradient": "`Lanes()` gradient (6 parameters)",
    "gradient": "gradient (6 parameters)",
    "lane per trajectory": "`Lanes(N)`: a lane per trajectory",
    "vmap": "`Vmap()`",
    "plain vmap": "`jax.vmap(diffeqsolve)`",
    "cuda f64": "CUDA kernel, float64",
    "cuda f32": "CUDA kernel, float32",
    # the throughput benchmark's other models, float64; ratios to the CUDA kernel's on each
    **{
        f"{kind} {model}": f"{label}, {model.replace('_', ' ')}"
        for model in ("heavy_top", "gravity_gradient")
        for kind, label in (
            ("cuda f64", "CUDA kernel"),
            ("kernel", "`Kernel()`"),
            ("lanes", "`Lanes()`"),
        )
    },
}


def _gpu_environment() -> str:
    """The GPU run's own machine and versions (`gpu.json`'s meta): the page's other tables
    come from the CPU machine of `environment.json`."""
    m = _load("gpu")["meta"]
    return (
        f"- **GPU:** {m['jax_device']} (the CUDA kernel ran on {m['cuda_device']})\n"
        f"- **Versions:** jax {m['jax']} (CUDA), diffrax {m['diffrax']}, equinox "
        f"{m['equinox']}" + (f", rbdyn_jax {m['revision']}" if "revision" in m else "")
    )


def _gpu() -> str:
    """One column per batch size, one row per method: trajectories per second and, below,
    the rate as a fraction of the float64 CUDA kernel's at that size."""
    rows_in = [r for r in _load("gpu")["rows"] if "traj_per_s" in r and r["method"] != "sweep"]
    sweeps = [r for r in _load("gpu")["rows"] if r["method"] == "sweep" and "seconds" in r]
    sizes = sorted({r["batch"] for r in rows_in})
    cell = {(r["method"], r["batch"]): r for r in rows_in}
    rows = []
    for method, label in _GPU_METHODS.items():
        if not any(m == method for m, _ in cell):  # not measured in this run
            continue
        row = [label]
        for n in sizes:
            r = cell.get((method, n))
            if r is None:
                row.append("—")
            elif "ratio_to_cuda_f64" not in r:  # the yardstick itself
                row.append(_n(r["traj_per_s"]))
            else:
                row.append(f"{_n(r['traj_per_s'])}<br>{r['ratio_to_cuda_f64']:.3f}×")
        rows.append(row)
    for method in ("gradient", "kernel gradient", "lanes gradient"):
        if any(m == method for m, _ in cell):
            rows.append(
                [
                    f"{_GPU_METHODS[method].split(' (')[0]} ÷ forward, time",
                    *[
                        f"{cell[(method, n)]['times_forward']:.2f}"
                        if "times_forward" in cell.get((method, n), {})
                        else "—"
                        for n in sizes
                    ],
                ]
            )
    rows.append(
        [
            "default ÷ `Vmap()`",
            *[
                f"{cell[('default', n)]['traj_per_s'] / cell[('vmap', n)]['traj_per_s']:.1f}"
                if ("vmap", n) in cell
                else "—"
                for n in sizes
            ],
        ]
    )
    for method, label in (
        ("default", "first call (s), default"),
        ("kernel", "first call (s), `Kernel()`"),
        ("gradient", "first call (s), gradient"),
        ("kernel gradient", "first call (s), `Kernel()` gradient"),
    ):
        if method == "default" and any(m == "kernel" for m, _ in cell):
            continue  # measured after `Kernel()`'s first call, whose program it reuses
        if any(m == method for m, _ in cell):
            rows.append(
                [
                    label,
                    *[
                        f"{cell[(method, n)]['first_call_s']:.1f}" if (method, n) in cell else "—"
                        for n in sizes
                    ],
                ]
            )
    head = [""] + [f"N = {_n(n)}" for n in sizes]
    table = _table(head, rows)
    for r in sweeps:  # the summaries-only sweep, end to end
        table += (
            f"\n\nA summaries-only sweep of {_n(r['batch'])} `torque_free_flip` "
            f"trajectories, its store written: {r['seconds']:.1f} s end to end "
            f"({_n(r['traj_per_s'])} a second)."
        )
    return table


def _gpu_accuracy() -> str:
    """Steps and errors against the elliptic solution (the first 1000 trajectories of the
    smallest batch measured), for the torque-free rows."""
    measured = [
        r
        for r in _load("gpu")["rows"]
        if "max_error" in r
        and r["method"].rsplit(" ", 1)[-1] not in ("heavy_top", "gravity_gradient")
    ]
    n = min(r["batch"] for r in measured)
    rows = [
        [
            _GPU_METHODS.get(r["method"], r["method"]),
            f"{r['mean_steps']:.0f}",
            str(r["max_steps"]),
            _e(r["median_error"]),
            _e(r["max_error"]),
        ]
        for r in measured
        if r["batch"] == n
    ]
    return _table(
        [f"method (N = {_n(n)})", "mean steps", "most steps", "median error", "largest error"], rows
    )


def _kernel_build() -> str:
    """One row per case of `kernel_build.py`: the kernel as compiled for an H100."""
    d = _load("kernel_build")
    rows = [
        [
            r["case"].replace("-", ", ") + f", block {r.get('block', 128)}",
            r["registers"],
            f"{r['spill_stores']} / {r['spill_loads']}",
            f"{r['blocks_per_sm']} ({r['resident_warps']} warps)",
            f"{r['compile_s']:.1f}",
            f"{r['coalesce_s']:.1f}",
            _n(r["ttir_ops"]),
            f"{_n(r['sass_instructions'])} ({_n(r['sass_float'])} / {r['sass_mufu']})",
        ]
        for r in d["rows"]
    ]
    head = [
        "case",
        "registers a thread",
        "spill stores / loads (B)",
        "blocks a multiprocessor",
        "Triton compile (s)",
        "of which coalescing (s)",
        "TTIR operations",
        "SASS instructions (float arithmetic / special-function)",
    ]
    return _table(head, rows)


def _power(x: float) -> str:
    """A power of ten as 10ⁿ, another number as it is."""
    n = round(math.log10(x))
    if abs(x - 10.0**n) > 1e-9 * x:
        return f"{x:g}"
    return "10" + str(n).translate(str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹"))


def _long_horizon() -> str:
    """One row per method: steps and cost per period, the energy and |L| errors over the
    horizon, the quaternion's norm, the global error at 10⁴ periods; the targets below."""
    d = _load("long_horizon")
    rows_in = [r for r in d["rows"] if r["body"] == "torque-free"]
    base = next(r for r in rows_in if r["method"] == d["meta"]["targets"]["baseline"])
    rows = []
    for r in rows_in:
        early = r["energy_10_100"]
        rows.append(
            [
                r["method"],
                f"{r['steps_per_period']:.0f}",
                f"{r['us_per_period']:.0f}",
                f"{r['us_per_period'] / base['us_per_period']:.2f}",
                _e(r["energy_max"]),
                "—" if early is None else _e(early),
                _e(r["energy_last_decade"]),
                _e(r["L_max"]),
                _e(r["quat_norm_drift"]),
                _e(r["global_error_1e4"]) if "global_error_1e4" in r else "—",
            ]
        )
    t = d["meta"]["targets"]
    decade = f"{_power(d['meta']['periods'] / 10)}–{_power(d['meta']['periods'])}"

    def mark(ok):
        return "met" if ok else "**not met**"

    return (
        _table(
            [
                "method",
                "steps per period",
                "µs per period",
                f"× {t['baseline']}",
                "largest energy error",
                "periods 10–10²",
                f"periods {decade}",
                "largest \\|L\\| error",
                "\\|q\\| − 1",
                "global error at 10⁴ periods",
            ],
            rows,
        )
        + f"\n\nTargets, on {t['method']}: |L| error ≤ 1e-12 — {mark(t['L_le_1e-12'])}; "
        f"energy error ≤ 1e-8 — {mark(t['energy_le_1e-8'])}, without trend (the largest "
        f"over the last decade within 2× of that over periods 10–10²) — "
        f"{mark(t['energy_bounded'])}; cost per period ≤ 3× {t['baseline']}'s — "
        f"{t['cost_ratio']:.2f}×, {mark(t['cost_le_3x'])}; global error at 10⁴ periods "
        f"below {t['baseline']}'s — {mark(t['global_below_baseline'])}. On "
        f"{t['fine_method']}: energy error ≤ 1e-13 — {mark(t['fine_energy_le_1e-13'])}, "
        f"at {t['fine_cost_ratio']:.2f}× the cost per period of {t['baseline']}."
    )


def _long_horizon_potentials() -> str:
    """One row per body under a potential torque and method: steps and cost per period,
    the energy error over the horizon, early and over its last decade, and the
    quaternion's norm."""
    d = _load("long_horizon")
    periods = d["meta"]["potential_periods"]
    decade = f"{_power(periods / 10)}–{_power(periods)}"
    rows = [
        [
            r["body"],
            r["method"],
            f"{r['steps_per_period']:.0f}",
            f"{r['us_per_period']:.0f}",
            _e(r["energy_max"]),
            _e(r["energy_10_100"]),
            _e(r["energy_last_decade"]),
            _e(r["quat_norm_drift"]),
        ]
        for r in d["rows"]
        if r["body"] != "torque-free"
    ]
    bounded = d["meta"]["targets"]["potentials_bounded"]
    return (
        _table(
            [
                "body",
                "method",
                "steps per period",
                "µs per period",
                "largest energy error",
                "periods 10–10²",
                f"periods {decade}",
                "\\|q\\| − 1",
            ],
            rows,
        )
        + "\n\nTarget, the splitting on every body: energy error without trend (the "
        f"largest over the last decade within 2× of that over periods 10–10²) — "
        f"{'met' if bounded else '**not met**'}."
    )


TABLES = {
    "environment": _environment,
    "gpu_environment": _gpu_environment,
    "kernel_build": _kernel_build,
    "gpu": _gpu,
    "gpu_accuracy": _gpu_accuracy,
    "throughput": _throughput,
    "work_precision": _work_precision,
    "gradients": _gradients,
    "gradient_steps": _gradient_steps,
    "compile": _compile,
    "sweep_scale": _sweep_scale,
    "store_write": _store_write,
    "identify": _identify,
    "long_horizon": _long_horizon,
    "long_horizon_potentials": _long_horizon_potentials,
}


def _check_versions() -> None:
    """Every CPU result measured with the versions `environment.json` lists (the GPU run's
    file carries its own, `_gpu_environment`)."""
    versions = _load("environment")["versions"]
    for path in sorted(RESULTS.glob("*.json")):
        if path.stem in ("environment", "gpu"):
            continue
        meta = json.loads(path.read_text()).get("meta", {})
        for pkg in ("jax", "diffrax", "equinox"):
            if pkg in meta and meta[pkg] != versions.get(pkg):
                raise PluginError(
                    f"performance: {path.name} was measured with {pkg} "
                    f"{meta[pkg]}, environment.json says {versions.get(pkg)}."
                )


def on_page_markdown(markdown: str, page, config, files) -> str:
    if not _MARKER.search(markdown):
        return markdown
    _check_versions()

    def table(match):
        name = match.group(1)
        if name not in TABLES:
            raise PluginError(f"{page.file.src_uri}: no performance table named {name!r}.")
        return TABLES[name]()

    return _MARKER.sub(table, markdown)
