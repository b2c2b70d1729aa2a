"""First-call latency (trace + compile + run) of rbdyn_jax's solves, with and without JAX's
persistent compilation cache.

Setting: torque-free body, J = [[2, 0.05, 0], [0.05, 3, 0.02], [0, 0.02, 4]], ω0 ~ N(0, 1)
per component (seed 0), identity attitude, t ∈ [0, 20], 21 output times, rtol = atol = 1e-8,
float64, default solver (Tsit5). Cases:

- `simulate`: `rb.simulate`, one trajectory;
- `default`: `rb.simulate_batch(model, y0s, ts)`, the default batching, N = 256;
- `batch`: `rb.simulate_batch(..., batching=rb.Vmap())` (vmapped `diffeqsolve`), N = 256;
- `lanes`: `rb.simulate_batch(..., batching=rb.Lanes(64))`, N = 256;
- `grad`: `jax.jit(jax.grad(loss))`, loss = Σ|ω − data|² over `simulate_batch` (`Vmap`,
  `RecursiveCheckpointAdjoint`), N = 16, w.r.t. the 6 log-Cholesky parameters θ of J
  (evaluated at the true parameters + 0.05), the model built as `identify.fit` builds it,
  `rb.with_log_cholesky(model, θ)` (physical by construction, unchecked);
- `jacfwd_lanes`, `grad_lanes`: `jax.jit(jax.jacfwd(loss))` and `jax.jit(jax.grad(loss))`,
  the same loss through `rb.Lanes(16)` (its forward sensitivities);
  all jitted with `compiler_options=rb.COMPILER_OPTIONS`, as rbdyn_jax advises for a
  caller's own jit (its solves are compiled with them);
- `grad_lanes_ctor`: `grad_lanes` with the model built by the constructor,
  `rb.RigidBody(rb.inertia.from_log_cholesky(θ))`, whose inertia checks of a traced θ are
  run-time checks (`eqx.error_if`): host callbacks in the caller's program, and JAX never
  caches a program with callbacks;
- `grad_lanes_ctor_nan`: the same in a process started with `EQX_ON_ERROR=nan` (equinox's
  switch: its checks give NaN instead of a host callback);
- `bare_diffrax`: the machine's yardstick, no rbdyn_jax: `jax.jit(jax.vmap(solve))` of
  `diffrax.diffeqsolve` (Tsit5, `PIDController`, `SaveAt(ts=…)`) on the scipy baseline's
  right-hand side (`_baselines._numpy_rhs`) in `jax.numpy`, N = 256, compiled with JAX's
  defaults. First calls vary with the machine and from one run to the next, so the table
  gives each case's first call also as a multiple of this one, measured in the same run.

The data are ω(t) of the true body from scipy's `solve_ivp` (so that no JAX program is
compiled before the timed call). Every measurement runs in a fresh process (this script
re-invoked with `--child CASE --cache DIR|none`), which times `import jax` + `import
rbdyn_jax.integrate` (the package and its solver layer, imported by the first name used
otherwise; diffrax for the yardstick), then the building of the inputs and the model
("build", e.g. `RigidBody(J)` and its inertia checks; before the timed call), the first call
(`block_until_ready`) and a second call with the same inputs (steady state). Three processes
per case: (1) no persistent cache; (2) cache cold: a fresh empty cache directory
(`jax_compilation_cache_dir`, min compile time 0 s, min entry size 0 bytes); (3) cache warm:
a new process on the same directory.
"entries" counts the cache files (`*-cache`) that the first call of (2) wrote (0: nothing of
it was cacheable); "cb skip" counts the programs JAX compiled during that call but refused
to store because they hold host callbacks (taken from JAX's log; their names are in the
JSON). "traces" counts the solves that (3) loaded from rbdyn_jax's cache of traced programs
(`rbdyn_jax/_program/traces.py`, in the same directory) instead of tracing them; a gradient is
the caller's own `jit`, which rbdyn_jax cannot store, but inside it the lane solver's
loops (the forward solve, and the sensitivities' solves of ω's group and of the whole state)
are loaded from there. The speed-up is first call
without cache / first call warm.

rbdyn_jax's cases run with XLA's flags as `import rbdyn_jax` sets them (one XLA CPU device
per core, every while loop compiled whole), as a user's program gets them;
`--xla-defaults` runs them with XLA's own defaults instead (`RBDYN_JAX_CONFIGURE_XLA=0`: one
device, loops dispatched kernel by kernel). The yardstick always runs with XLA's defaults.
The children start without the parent's `XLA_FLAGS`.

Run: `python benchmarks/compile.py [--cases simulate batch lanes grad jacfwd_lanes …]
[--xla-defaults]` — prints
a table and writes results/benchmarks/compile.json (`--out DIR`). Sequential, ≈ 5 min at
the defaults on a 2-core CPU; `--cases simulate` is a quick smoke test.
"""

import argparse
import json
import logging
import os
import pathlib
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from importlib.metadata import version

J_TRUE = [[2.0, 0.05, 0.0], [0.05, 3.0, 0.02], [0.0, 0.02, 4.0]]
T_END, N_OUT, TOL, SEED = 20.0, 21, 1e-8, 0
CASES = {  # name: (batch size, lanes per device: None the vmapped path, "default" the default)
    "simulate": (1, None),
    "default": (256, "default"),
    "batch": (256, None),
    "lanes": (256, 64),
    "grad": (16, None),
    "jacfwd_lanes": (16, 16),
    "grad_lanes": (16, 16),
    "grad_lanes_ctor": (16, 16),
    "grad_lanes_ctor_nan": (16, 16),
    "bare_diffrax": (256, None),
}
YARDSTICK = "bare_diffrax"
# Gradient cases whose loss builds the model with its constructor (run-time inertia checks),
# and those of them run with equinox's checks as NaN (`EQX_ON_ERROR=nan` in the child's
# environment): the caller's switch that makes such a program cacheable.
CTOR_CASES = ("grad_lanes_ctor", "grad_lanes_ctor_nan")
NAN_CASES = ("grad_lanes_ctor_nan",)
CACHE_ENV = (
    "JAX_COMPILATION_CACHE_DIR",
    "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS",
    "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES",
    "JAX_ENABLE_COMPILATION_CACHE",
)


# ----------------------------------------------------------------------------------------
# Child: one case, one cache condition, in a fresh process.
# ----------------------------------------------------------------------------------------


def _cache_entries(cache):
    return 0 if cache is None else len(list(pathlib.Path(cache).glob("*-cache")))


class _Recorder(logging.Handler):
    """JAX's compile statistics while `on`: the programs compiled (or loaded from the cache)
    and the time it took, persistent cache hits, and the programs not stored because they
    hold host callbacks."""

    def __init__(self):
        super().__init__(logging.DEBUG)
        self.on = False
        self.stats = {
            "compiles": 0,
            "compile_or_load_s": 0.0,
            "cache_hits": 0,
            "callback_programs": [],
        }

    def emit(self, record):
        if self.on and "because it uses host callbacks" in str(record.msg):
            self.stats["callback_programs"].append(str(record.args[0]))

    def duration(self, event, secs, **_):
        if self.on and event == "/jax/core/compile/backend_compile_duration":
            self.stats["compiles"] += 1
            self.stats["compile_or_load_s"] += secs

    def event(self, event, **_):
        if self.on and event == "/jax/compilation_cache/cache_hits":
            self.stats["cache_hits"] += 1


def _start_jax(cache, case):
    """Import jax (float64, the cache configured) and, but for the yardstick, rbdyn_jax with
    its solver layer `rbdyn_jax.integrate` (which `import rbdyn_jax` leaves to the first
    name used; it imports diffrax), or diffrax for the yardstick; their import times."""
    t0 = time.perf_counter()
    import jax

    jax.config.update("jax_enable_x64", True)
    if cache is not None:
        jax.config.update("jax_compilation_cache_dir", cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    t1 = time.perf_counter()
    if case == YARDSTICK:
        import diffrax  # noqa: F401
    else:
        import rbdyn_jax.integrate  # noqa: F401

    return t1 - t0, time.perf_counter() - t1


def _reference_omega(w0, ts):
    """ω(t) of the true body for each row of `w0` (scipy, tight tolerances), (N, n, 3)."""
    import numpy as np
    from scipy.integrate import solve_ivp

    J = np.array(J_TRUE)

    def rhs(t, w):
        return np.linalg.solve(J, np.cross(J @ w, w))

    return np.stack(
        [
            solve_ivp(
                rhs, (ts[0], ts[-1]), w, t_eval=ts, rtol=1e-11, atol=1e-11, method="DOP853"
            ).y.T
            for w in w0
        ]
    )


def _batching(lanes) -> dict:
    """`simulate_batch`'s batching arguments for a case's `lanes`."""
    import diffrax

    import rbdyn_jax as rb

    if lanes == "default":
        return {}
    if lanes is None:
        return {"batching": rb.Vmap(), "adjoint": diffrax.RecursiveCheckpointAdjoint()}
    return {"batching": rb.Lanes(lanes)}


def _loss_fn(y0s, ts, data, lanes, ctor):
    import jax.numpy as jnp

    import rbdyn_jax as rb

    base = rb.RigidBody(jnp.array(J_TRUE))

    def loss(theta):
        if ctor:  # run-time checks of the traced inertia: host callbacks
            model = rb.RigidBody(rb.inertia.from_log_cholesky(theta))
        else:  # physical by construction, unchecked (as `identify.fit` builds its models)
            model = rb.with_log_cholesky(base, theta)
        traj = rb.simulate_batch(model, y0s, ts, rtol=TOL, atol=TOL, **_batching(lanes))
        return jnp.sum((traj.ys.omega - data) ** 2)

    return loss


def _bare_call(w0, ts_np):
    """The yardstick: a vmapped `diffeqsolve` of the torque-free body, without rbdyn_jax:
    the right-hand side is the scipy baseline's (`_baselines._numpy_rhs`) in `jax.numpy`
    (the problem of the `batch` case)."""
    import diffrax
    import jax
    import jax.numpy as jnp

    here = str(pathlib.Path(__file__).parent)
    if here not in sys.path:
        sys.path.insert(0, here)
    import _baselines

    J = jnp.array(J_TRUE)
    f = _baselines._numpy_rhs(
        _baselines.MODELS["torque_free"], J, jnp.linalg.inv(J), None, None, None, xp=jnp
    )
    ts = jnp.asarray(ts_np)

    def solve(y0):
        return diffrax.diffeqsolve(
            diffrax.ODETerm(lambda t, y, args: f(t, y)),
            diffrax.Tsit5(),
            ts[0],
            ts[-1],
            None,
            y0,
            saveat=diffrax.SaveAt(ts=ts),
            max_steps=16_384,
            stepsize_controller=diffrax.PIDController(rtol=TOL, atol=TOL),
        ).ys

    y0s = jnp.concatenate(
        [jnp.asarray(w0), jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (w0.shape[0], 1))], axis=1
    )
    fn = jax.jit(jax.vmap(solve))
    return lambda: fn(y0s)


def build_call(case):
    """A zero-argument function making the case's call; every input is built here."""
    import numpy as np

    n, lanes = CASES[case]
    ts_np = np.linspace(0.0, T_END, N_OUT)
    w0 = np.random.default_rng(SEED).normal(size=(n, 3))
    if case == YARDSTICK:
        return _bare_call(w0, ts_np)

    import jax
    import jax.numpy as jnp

    import rbdyn_jax as rb

    ts = jnp.asarray(ts_np)
    y0s = rb.State(jnp.asarray(w0), jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (n, 1)))
    if case == "simulate":
        model, y0 = rb.RigidBody(jnp.array(J_TRUE)), jax.tree_util.tree_map(lambda x: x[0], y0s)
        return lambda: rb.simulate(model, y0, ts, rtol=TOL, atol=TOL)
    if case in ("default", "batch", "lanes"):
        model = rb.RigidBody(jnp.array(J_TRUE))
        return lambda: rb.simulate_batch(model, y0s, ts, rtol=TOL, atol=TOL, **_batching(lanes))
    loss = _loss_fn(y0s, ts, jnp.asarray(_reference_omega(w0, ts_np)), lanes, case in CTOR_CASES)
    theta = rb.inertia.to_log_cholesky(jnp.array(J_TRUE)) + 0.05
    mode = jax.jacfwd if case == "jacfwd_lanes" else jax.grad
    fn = jax.jit(mode(loss), compiler_options=rb.COMPILER_OPTIONS)
    return lambda: fn(theta)


def _all_finite(out):
    import jax
    import numpy as np

    leaves = jax.tree_util.tree_leaves(out)
    return bool(
        all(
            np.all(np.isfinite(np.asarray(x)))
            for x in leaves
            if np.issubdtype(np.asarray(x).dtype, np.floating)
        )
    )


def child(case, cache):
    """Measure one case in this (fresh) process; print the result as one JSON line."""
    import_jax_s, import_rb_s = _start_jax(cache, case)
    import jax
    from jax import monitoring

    rec = _Recorder()
    logger = logging.getLogger("jax._src.compiler")
    logger.setLevel(logging.DEBUG)
    logger.addHandler(rec)
    monitoring.register_event_duration_secs_listener(rec.duration)
    monitoring.register_event_listener(rec.event)

    t0 = time.perf_counter()
    call = build_call(case)  # the inputs and the model (its inertia checks), untimed by
    build = time.perf_counter() - t0  # `first_s`: reported beside it as `build_s`
    before = _cache_entries(cache)
    rec.on = True
    t0 = time.perf_counter()
    out = jax.block_until_ready(call())
    first = time.perf_counter() - t0
    rec.on = False
    entries = _cache_entries(cache) - before
    t0 = time.perf_counter()
    jax.block_until_ready(call())
    steady = time.perf_counter() - t0
    traces = sys.modules.get("rbdyn_jax._program.traces")  # rbdyn_jax's cache of traced solves
    print(
        json.dumps(
            {
                "import_jax_s": import_jax_s,
                "import_rbdyn_jax_s": import_rb_s,
                "build_s": build,
                "first_s": first,
                "steady_s": steady,
                "entries_written": entries,
                "traces": dict(traces.stats) if traces else None,
                "entries_total": _cache_entries(cache),
                "finite": _all_finite(out),
                "backend": jax.default_backend(),
                **rec.stats,
            }
        )
    )


# ----------------------------------------------------------------------------------------
# Driver
# ----------------------------------------------------------------------------------------


def run_child(case, cache, xla_defaults=False):
    env = {
        k: v for k, v in os.environ.items() if k not in CACHE_ENV + ("EQX_ON_ERROR", "XLA_FLAGS")
    }
    env["RBDYN_JAX_CONFIGURE_XLA"] = "0" if xla_defaults or case == YARDSTICK else "1"
    if case in NAN_CASES:
        env["EQX_ON_ERROR"] = "nan"
    proc = subprocess.run(
        [sys.executable, os.path.abspath(__file__), "--child", case, "--cache", cache or "none"],
        env=env,
        capture_output=True,
        text=True,
    )
    if proc.returncode != 0:
        raise RuntimeError(
            f"child {case} (cache {cache}) failed ({proc.returncode}):\n{proc.stderr[-4000:]}"
        )
    return json.loads(proc.stdout.strip().splitlines()[-1])


def measure(case, xla_defaults=False):
    """The three conditions of one case: no cache, cold cache, warm cache."""
    tmp = tempfile.mkdtemp(prefix=f"rbdyn_compile_{case}_")
    try:
        runs = {}
        for cond, cache in (("no_cache", None), ("cold", tmp), ("warm", tmp)):
            print(f"  {case}: {cond} …", flush=True)
            runs[cond] = run_child(case, cache, xla_defaults)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    imports = sorted(r["import_jax_s"] + r["import_rbdyn_jax_s"] for r in runs.values())
    return {
        "case": case,
        "batch": CASES[case][0],
        "lanes": CASES[case][1],
        "import_s": imports[1],
        "build_s": runs["no_cache"]["build_s"],
        **{f"{c}_s": r["first_s"] for c, r in runs.items()},
        "steady_s": runs["warm"]["steady_s"],
        "speedup_warm": runs["no_cache"]["first_s"] / runs["warm"]["first_s"],
        "entries": runs["cold"]["entries_written"],
        "trace_hits": (runs["warm"]["traces"] or {}).get("hits", 0),
        "callback_programs": runs["cold"]["callback_programs"],
        "runs": runs,
    }


def print_table(rows):
    head = (
        f"{'case':<20} {'import s':>8} {'build s':>7} | {'first call: no cache':>20} "
        f"{'/ bare':>6} "
        f"{'cold':>7} {'warm':>7} | {'speed-up':>8} | {'steady':>7} | {'entries':>7} "
        f"{'cb skip':>7} {'traces':>6}"
    )
    print(head)
    print("-" * len(head))
    for r in rows:
        rel = f"{r['vs_bare']:>5.2f}x" if r.get("vs_bare") else f"{'—':>6}"
        print(
            f"{r['case']:<20} {r['import_s']:>8.2f} {r['build_s']:>7.2f} | "
            f"{r['no_cache_s']:>20.2f} {rel} "
            f"{r['cold_s']:>7.2f} {r['warm_s']:>7.2f} | {r['speedup_warm']:>7.1f}x | "
            f"{r['steady_s']:>7.3f} | {r['entries']:>7} {len(r['callback_programs']):>7} "
            f"{r['trace_hits']:>6}"
        )
    for r in rows:
        if r["callback_programs"]:
            print(
                f"{r['case']}: not cached (host callbacks): "
                f"{', '.join(sorted(set(r['callback_programs'])))}"
            )


def main(cases=tuple(CASES), out="results/benchmarks", xla_defaults=False):
    t0 = time.perf_counter()
    rows = [measure(c, xla_defaults) for c in cases]
    bare = next((r["no_cache_s"] for r in rows if r["case"] == YARDSTICK), None)
    for r in rows:  # first call without cache as a multiple of the yardstick's, same run
        r["vs_bare"] = r["no_cache_s"] / bare if bare else None
    print_table(rows)
    path = pathlib.Path(out)
    path.mkdir(parents=True, exist_ok=True)
    meta = {
        "machine": platform.platform(),
        "cpus": os.cpu_count(),
        "jax": version("jax"),
        "equinox": version("equinox"),
        "diffrax": version("diffrax"),
        "backend": rows[0]["runs"]["no_cache"]["backend"] if rows else None,
        "inertia": J_TRUE,
        "t_end": T_END,
        "n_out": N_OUT,
        "rtol": TOL,
        "atol": TOL,
        "seed": SEED,
        "xla_defaults": xla_defaults,
        "total_s": time.perf_counter() - t0,
    }
    (path / "compile.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    print(f"wrote {path / 'compile.json'} ({meta['total_s']:.0f} s)")
    return rows


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", nargs="+", choices=list(CASES), default=list(CASES))
    p.add_argument("--out", default="results/benchmarks")
    p.add_argument(
        "--xla-defaults",
        action="store_true",
        help="rbdyn_jax's cases with XLA's defaults (RBDYN_JAX_CONFIGURE_XLA=0)",
    )
    p.add_argument("--child", choices=list(CASES), help=argparse.SUPPRESS)
    p.add_argument("--cache", default="none", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        child(args.child, None if args.cache == "none" else args.cache)
    else:
        main(tuple(args.cases), args.out, args.xla_defaults)
