"""Batched solves on a GPU, side by side in one run: rbdyn_jax's strategies (`Kernel`,
`Lanes`, `Vmap` and the default call) against a hand-written CUDA kernel (the yardstick:
one thread per trajectory, Dormand–Prince 5(4), `_cuda.py`) and against the plain vmapped
`diffrax.diffeqsolve`, at 10³–10⁶ trajectories; forward solves, gradients and float32; and
a summaries-only sweep of 10⁷ trajectories end to end. Every rate is also given as a ratio
to the CUDA kernel's float64 rate measured in the same run at the same batch size (a
float32 row also to its float32 rate).

Setting (the throughput benchmark's): torque-free J = [[2, 0.05, 0], [0.05, 3, 0.02],
[0, 0.02, 4]], ω0 ~ N(0, 1) per axis (seed 0), identity attitude, t ∈ [0, 100], 101 outputs,
rtol = atol = 1e-8 in float64 and 1e-6 in float32. Rows:

- `default`: `rb.simulate_batch(model, y0s, ts)`, which on a GPU takes the Pallas kernel
  (`rb.Kernel`; the row names the strategy the default took, and for `Lanes` its lanes);
- `default f32`: the same call on float32 inputs (the solve runs in float32);
- `kernel`, `kernel f32`: `batching=rb.Kernel()` (a block of 128 trajectories a program),
  float64 and float32; `Kernel(B)`, `Kernel(B) f32` for each block B of `--blocks` (a
  trajectory a GPU thread at any block);
- `lanes`, `lanes f32`: `batching=rb.Lanes()`, the lane solver in its array layout with the
  lanes it takes for the batch;
- `kernel gradient`, `lanes gradient`: `jax.jit(jax.grad(loss))` of a batch loss (Σ ω² over
  the outputs) w.r.t. the inertia's six log-Cholesky parameters (`rb.with_log_cholesky`),
  through `Kernel` and through `Lanes` (forward sensitivities, integrated in the kernel or
  in the lane loop); the time is also given as a multiple of the same strategy's forward
  call (`kernel`, `lanes`);
- `lane per trajectory`: `rb.Lanes(N)`: every trajectory in a lane of its own, no refill
  (the default refills a third as many lanes on batches over 16,384, at most 131,072; the
  rows give the lanes it took), and `Lanes(L)` for each count of `--lanes`;
- `vmap`: `batching=rb.Vmap()` (rbdyn_jax's vmapped `diffeqsolve`);
- `plain vmap`: `jax.jit(jax.vmap(diffrax.diffeqsolve))` on `_baselines`' right-hand side in
  `jax.numpy`, no rbdyn_jax (Tsit5, the same controller);
- `lanes cpu layout` (only with `--cpu-layout-max`): `rb.Lanes(256, layout="cpu")`, the
  CPU's layout of the lane loop on the GPU;
- `cuda f64`, `cuda f32`: the kernel alone (device arrays allocated once, launch and
  synchronise timed);
- for the throughput benchmark's other models (`--models`: `heavy_top`, uniform gravity of
  weight 1 at r_c = (0, 0, 0.5); `gravity_gradient`, ε = 3), at the sizes ≥ `--model-min`,
  float64: `cuda f64 <model>`, `kernel <model>`, `lanes <model>`; their errors are against the
  CUDA kernel's solution (Dormand–Prince 5(4) at the same tolerance: both solvers' errors);
- `sweep` (`--sweep-n`, default 10⁷; 0 leaves it out): `sweep.run("torque_free_flip", n,
  store, trajectories="none")`, the shipped scenario (t ∈ [0, 40], 81 outputs, Tsit5 at
  1e-8) with its summaries only, timed once from the call to the store written and
  closed (compilation included), and from its `progress` reports the first chunk's seconds
  (compilation included) and the trajectories a second of the chunks after it (each solved
  while the one before is written); the store, under `--out`, is removed afterwards.

Each rate is the median of repeated calls after a first call, which is reported apart (it
includes compilation; `first_call_phases` splits its compilation into JAX's tracing,
lowering and the backend's compilation, which on a GPU includes Triton's, as
`jax.monitoring` reports them, summed over the programs compiled), and `dispatch_s` the
median time a repeated call takes to return before the device has finished (the host's
share of a call: its Python, its checks, its launches). Errors: the largest and
the median over trajectories of max_t |ω − ω_ref| on the first `--ref-max` trajectories,
ω_ref the Jacobi elliptic solution (`rb.analytic.torque_free_elliptic`). The card is named
from JAX's and numba's device queries.
Results are written after every row (`gpu.json` under `--out`), so a run stopped by
`--budget` (seconds; later rows are skipped) or killed keeps what it measured.

Run: `python benchmarks/gpu.py [--sizes 1000 10000 100000 1000000] [--grad-max 100000]
[--vmap-max 100000] [--whole-min 100000] [--lanes L …] [--blocks B …] [--cpu-layout-max 0]
[--models heavy_top gravity_gradient] [--model-min 100000] [--sweep-n 10000000]
[--budget 600] [--out results/benchmarks]`. The whole report in one
command within a 10-minute device call: `python benchmarks/gpu.py --sizes 100000 1000000
--vmap-max 100000 --whole-min 2000000 --budget 480`.
Without a GPU it runs on the CPU (the kernel then needs numba-cuda's simulator,
`NUMBA_ENABLE_CUDASIM=1`, and only tiny sizes are sensible).
"""

import argparse
import pathlib
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import rbdyn_jax as rb  # noqa: E402
from rbdyn_jax.integrate import default_batching, default_lanes, device_memory  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).parent))
import _baselines  # noqa: E402
import _cuda  # noqa: E402
import _report  # noqa: E402

J = np.array([[2.0, 0.05, 0.0], [0.05, 3.0, 0.02], [0.0, 0.02, 4.0]])
T_END, N_OUT = 100.0, 101
WEIGHT, COM, EPS = 1.0, np.array([0.0, 0.0, 0.5]), 3.0  # the throughput benchmark's
MODELS = ("heavy_top", "gravity_gradient")
TOL = {"float64": 1e-8, "float32": 1e-6}


def initial_rates(n, seed=0):
    return np.random.default_rng(seed).normal(size=(n, 3))


def states(w0, dtype):
    q = np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (len(w0), 1))
    return rb.State(jnp.asarray(w0, dtype), jnp.asarray(q, dtype))


def elliptic(w0, ts):
    """ω(t) of the torque-free body in closed form (body axes), float64."""
    moments, axes = rb.inertia.principal_axes(jnp.asarray(J))
    sol = jax.jit(jax.vmap(lambda w: rb.analytic.torque_free_elliptic(moments, w, ts)))
    return np.asarray(sol(jnp.asarray(w0) @ axes) @ axes.T)


def errors(omega, ref):
    m = min(len(omega), len(ref))
    e = np.max(np.abs(np.asarray(omega[:m], np.float64) - ref[:m]), axis=(1, 2))
    return {"max_error": float(np.max(e)), "median_error": float(np.median(e))}


# What the latest `timed` saw beyond its seconds: its first call's compilation phases
# (`first_call_phases`: seconds by `jax.monitoring` event, tracing to a jaxpr, lowering to
# MLIR, the backend's compilation, each summed over the programs the call compiles) and the
# median seconds its repeated calls took to return before the device finished
# (`dispatch_s`: the host's share of a call).
LAST_TIMING: dict = {}
PHASES = {
    "/jax/core/compile/jaxpr_trace_duration": "trace_s",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower_s",
    "/jax/core/compile/backend_compile_duration": "compile_s",
}
_timing = {"on": False, "phases": {}}  # the listener: registered, and what it collects


def _phase(event: str, duration: float, **_) -> None:
    phases = _timing["phases"]
    if event in PHASES:
        phases[PHASES[event]] = phases.get(PHASES[event], 0.0) + duration


def timed(fn, repeats):
    """(last output, first call's seconds, median of `repeats` further calls); the rest in
    `LAST_TIMING`."""
    if not _timing["on"]:
        jax.monitoring.register_event_duration_secs_listener(_phase)
        _timing["on"] = True
    _timing["phases"] = {}
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    LAST_TIMING.clear()
    LAST_TIMING["first_call_phases"] = _timing["phases"]
    _timing["phases"] = {}  # a repeat's compilations (none expected) are not the first call's
    times, dispatch = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        dispatch.append(time.perf_counter() - t0)
        out = jax.block_until_ready(out)
        times.append(time.perf_counter() - t0)
    if dispatch:
        LAST_TIMING["dispatch_s"] = float(np.median(dispatch))
    return out, first, float(np.median(times))


def rbdyn_model(name, dtype=np.float64):
    torque = {
        "torque_free": None,
        "heavy_top": rb.UniformGravity(jnp.asarray(WEIGHT, dtype), jnp.asarray(COM, dtype)),
        "gravity_gradient": rb.GravityGradient(jnp.asarray(EPS, dtype)),
    }[name]
    return rb.RigidBody(jnp.asarray(J, dtype), torque)


def rbdyn_forward(w0, ts, dtype, batching, model_name="torque_free"):
    model = rbdyn_model(model_name, dtype)
    y0s, ts = states(w0, dtype), jnp.asarray(ts, dtype)
    tol = TOL[np.dtype(dtype).name]
    return lambda: rb.simulate_batch(model, y0s, ts, rtol=tol, atol=tol, batching=batching)


def rbdyn_gradient(w0, ts, batching=None):
    body = rb.RigidBody(jnp.asarray(J))
    y0s, ts = states(w0, np.float64), jnp.asarray(ts)
    theta = rb.inertia.to_log_cholesky(jnp.asarray(J))

    def loss(th):
        tr = rb.simulate_batch(
            rb.with_log_cholesky(body, th),
            y0s,
            ts,
            rtol=TOL["float64"],
            atol=TOL["float64"],
            batching=batching,
        )
        return jnp.sum(tr.ys.omega**2)

    grad = jax.jit(jax.grad(loss), compiler_options=rb.COMPILER_OPTIONS)
    return lambda: grad(theta)


def plain_vmap(w0, ts):
    """`jax.jit(jax.vmap(diffeqsolve))` without rbdyn_jax: `_baselines`' right-hand side in
    `jax.numpy`, Tsit5, the same controller."""
    Jj = jnp.asarray(J)
    f = _baselines._numpy_rhs(
        _baselines.MODELS["torque_free"], Jj, jnp.linalg.inv(Jj), None, None, None, xp=jnp
    )
    ts = jnp.asarray(ts)

    def solve(y0):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(lambda t, y, args: f(t, y)),
            diffrax.Tsit5(),
            ts[0],
            ts[-1],
            None,
            y0,
            saveat=diffrax.SaveAt(ts=ts),
            max_steps=16_384,
            stepsize_controller=diffrax.PIDController(rtol=TOL["float64"], atol=TOL["float64"]),
        )
        return sol.ys, sol.stats["num_steps"]

    y0s = jnp.concatenate(
        [jnp.asarray(w0), jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (len(w0), 1))], axis=1
    )
    fn = jax.jit(jax.vmap(solve))
    return lambda: fn(y0s)


def sweep_run(n, out):
    """A summaries-only sweep of `n` trajectories of `torque_free_flip` into a store under
    `out`, timed end to end; the store is removed afterwards."""
    import shutil

    import zarr

    from rbdyn_jax import sweep

    store = pathlib.Path(out) / "gpu_sweep.zarr"
    chunks = []  # (seconds since the run began, trajectories solved) after each chunk
    t0 = time.perf_counter()
    sweep.run(
        "torque_free_flip",
        n,
        store,
        trajectories="none",
        overwrite=True,
        progress=lambda p: chunks.append((p.elapsed, p.solved_now)),
    )
    seconds = time.perf_counter() - t0
    status = zarr.open_group(str(store), mode="r")["status"][:]
    size = sum(f.stat().st_size for f in store.rglob("*") if f.is_file())
    shutil.rmtree(store)
    return {
        "method": "sweep",
        "batch": n,
        "dtype": "float64",
        "traj_per_s": n / seconds,
        "seconds": seconds,
        "first_call_s": seconds,
        "all_successful": bool(np.all(status == 0)),
        "successful": int(np.sum(status == 0)),
        "store_bytes": size,
        "backend": jax.default_backend(),
        # The first chunk includes the compilation; the chunks after it, solved while the
        # one before is written, give the sustained rate.
        "chunks": len(chunks),
        "first_chunk_s": chunks[0][0] if chunks else None,
        "steady_traj_per_s": (
            sum(k for _, k in chunks[1:]) / (chunks[-1][0] - chunks[0][0])
            if len(chunks) > 1
            else None
        ),
    }


def cuda_kernel(w0, ts, dtype, model_name="torque_free"):
    """The yardstick: the kernel alone on device arrays, and a reader of its outputs."""
    cuda = _cuda._import_cuda()
    tol = TOL[np.dtype(dtype).name]
    params = {"inertia": J, "weight": WEIGHT, "com": COM, "eps": EPS}
    solver = _cuda.CudaSolver(model_name, params, ts, tol, tol, dtype=dtype)
    y0 = np.concatenate([w0, np.tile([1.0, 0.0, 0.0, 0.0], (len(w0), 1))], axis=1)
    y0 = cuda.to_device(y0.astype(dtype))
    out, steps, status = solver.outputs(len(w0))

    def run():
        solver(y0, out, steps, status)
        cuda.synchronize()

    def read():
        return out.copy_to_host()[..., :3], steps.copy_to_host(), status.copy_to_host()

    return run, read


def rate_row(method, n, dtype, first, t, omega, steps, ok, ref):
    return {
        "method": method,
        "batch": n,
        "dtype": np.dtype(dtype).name,
        "traj_per_s": n / t,
        "seconds": t,
        "first_call_s": first,
        "mean_steps": float(np.mean(steps)),
        "max_steps": int(np.max(steps)),
        "all_successful": bool(ok),
        **({} if ref is None else errors(omega, ref)),
    }


def model_row(method, n, w0, ts, repeats, ref_max, refs):
    """`cuda f64 <model>`, `kernel <model>` or `lanes <model>` (float64); errors against the
    CUDA kernel's ω on the first `ref_max` trajectories (`refs`, filled by its row)."""
    kind, model_name = method.rsplit(" ", 1)
    if kind == "cuda f64":
        run, read = cuda_kernel(w0, ts, np.float64, model_name)
        _, first, t = timed(run, repeats)
        omega, steps, status = read()
        refs[(model_name, n)] = np.asarray(omega[:ref_max], np.float64)
        return rate_row(method, n, np.float64, first, t, omega, steps, np.all(status == 0), None)
    batching = rb.Kernel() if kind == "kernel" else rb.Lanes()
    tr, first, t = timed(rbdyn_forward(w0, ts, np.float64, batching, model_name), repeats)
    return rate_row(
        method,
        n,
        np.float64,
        first,
        t,
        tr.ys.omega,
        tr.stats["num_steps"],
        np.all(np.asarray(tr.result._value) == 0),
        refs.get((model_name, n)),
    )


def measure(method, n, w0, ts, ref, repeats):
    """One row: the method's rate, first call, steps and errors at batch size `n`."""
    if method in (
        "default",
        "default f32",
        "kernel",
        "kernel f32",
        "lanes",
        "lanes f32",
        "vmap",
        "lanes cpu layout",
        "lane per trajectory",
    ) or method.startswith(("Lanes(", "Kernel(")):
        dtype = np.float32 if method.endswith("f32") else np.float64
        batching = {
            "vmap": rb.Vmap(),
            "lanes cpu layout": rb.Lanes(256, layout="cpu"),
            "lane per trajectory": rb.Lanes(n),
            "kernel": rb.Kernel(),
            "kernel f32": rb.Kernel(),
            "lanes": rb.Lanes(),
            "lanes f32": rb.Lanes(),
        }.get(method)
        if method.startswith("Lanes("):
            batching = rb.Lanes(int(method[6:-1]))
        if method.startswith("Kernel("):
            batching = rb.Kernel(int(method[7:].split(")")[0]))
        tr, first, t = timed(rbdyn_forward(w0, ts, dtype, batching), repeats)
        row = rate_row(
            method,
            n,
            dtype,
            first,
            t,
            tr.ys.omega,
            tr.stats["num_steps"],
            np.all(np.asarray(tr.result._value) == 0),
            ref,
        )
        if method.startswith("default"):  # the strategy the default took (and its lanes)
            tol = TOL[np.dtype(dtype).name]
            chosen = default_batching(
                diffrax.Tsit5(),
                diffrax.PIDController(rtol=tol, atol=tol),
                None,
                rb.RigidBody(jnp.asarray(J, dtype)),
                states(w0[:1], dtype),
            )
            row["batching"] = type(chosen).__name__
            if isinstance(chosen, rb.Lanes):
                per_lane = 7 * np.dtype(dtype).itemsize  # the state (ω, q) of a trajectory
                row["lanes"] = default_lanes(
                    n,
                    len(jax.devices()),
                    jax.devices()[0].platform,
                    per_lane,
                    device_memory(jax.devices()[0]),
                )
        return row
    if method == "plain vmap":
        (ys, steps), first, t = timed(plain_vmap(w0, ts), repeats)
        return rate_row(
            method,
            n,
            np.float64,
            first,
            t,
            ys[..., :3],
            steps,
            np.all(np.isfinite(np.asarray(ys))),
            ref,
        )
    if method in ("kernel gradient", "lanes gradient"):
        batching = rb.Kernel() if method == "kernel gradient" else rb.Lanes()
        g, first, t = timed(rbdyn_gradient(w0, ts, batching), repeats)
        return {
            "method": method,
            "batch": n,
            "dtype": "float64",
            "traj_per_s": n / t,
            "seconds": t,
            "first_call_s": first,
            "all_successful": bool(np.all(np.isfinite(np.asarray(g)))),
        }
    if method in ("cuda f64", "cuda f32"):
        dtype = np.float32 if method == "cuda f32" else np.float64
        run, read = cuda_kernel(w0, ts, dtype)
        _, first, t = timed(run, repeats)
        omega, steps, status = read()
        return rate_row(method, n, dtype, first, t, omega, steps, np.all(status == 0), ref)
    raise ValueError(method)


def plan(
    sizes,
    grad_max,
    vmap_max,
    cpu_layout_max,
    whole_min,
    lanes=(),
    sweep_n=0,
    models=(),
    model_min=0,
    blocks=(),
):
    """(method, n) in the order measured: the yardstick first at each size, then the rest;
    the sweep after the largest size's kernel rows (before its slower reference rows)."""
    rows = []
    for n in sizes:
        rows += [
            ("cuda f64", n),
            ("kernel", n),
            ("default", n),
            ("cuda f32", n),
            ("kernel f32", n),
            ("default f32", n),
        ]
        rows += [(f"Kernel({b}){s}", n) for b in blocks for s in ("", " f32")]
        if n <= grad_max:
            rows.append(("kernel gradient", n))
        if sweep_n and n == max(sizes):
            rows.append(("sweep", sweep_n))
        rows += [("lanes", n), ("lanes f32", n)]
        if n <= grad_max:
            rows.append(("lanes gradient", n))
        if n >= whole_min:
            rows.append(("lane per trajectory", n))
            rows += [(f"Lanes({L})", n) for L in lanes if L < n]
        if n <= vmap_max:
            rows += [("vmap", n), ("plain vmap", n)]
        if n <= cpu_layout_max:
            rows.append(("lanes cpu layout", n))
        if n >= model_min:
            rows += [(f"{kind} {m}", n) for m in models for kind in ("cuda f64", "kernel", "lanes")]
    return rows


def device_names():
    d = jax.devices()[0]
    names = {"jax_device": f"{d.device_kind} ({d.platform})"}
    try:
        name = _cuda._import_cuda().get_current_device().name
        names["cuda_device"] = name.decode() if isinstance(name, bytes) else str(name)
    except Exception as e:  # no CUDA driver (and no simulator): the kernel rows will fail
        names["cuda_device"] = f"unavailable: {type(e).__name__}"
    return names


def main(
    sizes,
    grad_max,
    vmap_max,
    cpu_layout_max,
    whole_min,
    lanes,
    ref_max,
    budget,
    out,
    sweep_n=0,
    models=(),
    model_min=0,
    blocks=(),
):
    t_start = time.perf_counter()
    ts = np.linspace(0.0, T_END, N_OUT)
    meta = {
        "t_end": T_END,
        "n_out": N_OUT,
        "tol": TOL,
        "sizes": sizes,
        "sweep_n": sweep_n,
        "models": list(models),
        "model_min": model_min,
        "blocks": list(blocks),
        # first calls compile cold unless JAX's persistent cache is configured
        "compilation_cache": jax.config.jax_compilation_cache_dir or None,
        **device_names(),
    }
    print(f"device: {meta['jax_device']}; CUDA yardstick on: {meta['cuda_device']}")
    rows, refs, model_refs = [], {}, {}
    for method, n in plan(
        sizes,
        grad_max,
        vmap_max,
        cpu_layout_max,
        whole_min,
        lanes,
        sweep_n,
        models,
        model_min,
        blocks,
    ):
        if time.perf_counter() - t_start > budget:
            rows.append({"method": method, "batch": n, "skipped": "budget"})
            print(f"{method:>19} {n:>8}  skipped (over --budget {budget:.0f} s)")
            continue
        try:
            if method == "sweep":
                row = sweep_run(n, out)
            elif method.rsplit(" ", 1)[-1] in MODELS:
                row = model_row(
                    method, n, initial_rates(n), ts, 3 if n <= 100_000 else 1, ref_max, model_refs
                )
            else:
                w0 = initial_rates(n)
                if n not in refs:
                    refs[n] = elliptic(w0[:ref_max], jnp.asarray(ts))
                row = measure(method, n, w0, ts, refs[n], 3 if n <= 100_000 else 1)
        except Exception as e:  # recorded, and the run goes on (out of memory, say)
            row = {"method": method, "batch": n, "failed": f"{type(e).__name__}: {e}"[:500]}
        if "first_call_s" in row and method != "sweep":
            row.update(LAST_TIMING)
        model = method.rsplit(" ", 1)[-1]
        suffix = f" {model}" if model in MODELS else ""
        for yard_method, key in (
            (f"cuda f64{suffix}", "ratio_to_cuda_f64"),
            ("cuda f32", "ratio_to_cuda_f32"),
        ):
            if key == "ratio_to_cuda_f32" and row.get("dtype") != "float32":
                continue
            yard = next(
                (
                    r
                    for r in rows
                    if r["method"] == yard_method and r["batch"] == n and "traj_per_s" in r
                ),
                None,
            )
            if yard is not None and "traj_per_s" in row:
                row[key] = row["traj_per_s"] / yard["traj_per_s"]
        forward = {"kernel gradient": "kernel", "lanes gradient": "lanes"}.get(method)
        fwd = next(
            (r for r in rows if r["method"] == forward and r["batch"] == n and "seconds" in r), None
        )
        if fwd is not None and "seconds" in row:
            row["times_forward"] = row["seconds"] / fwd["seconds"]
        rows.append(row)
        print_row(row)
        _report.write_json(out, "gpu", meta, rows)
    print(f"wrote {pathlib.Path(out) / 'gpu.json'} ({time.perf_counter() - t_start:.0f} s)")
    return rows


HEAD = (
    f"{'method':>19} {'batch':>8} {'dtype':>7} | {'traj/s':>10} {'/cuda f64':>9} | "
    f"{'first s':>7} {'call s':>8} | {'steps':>6} {'max':>6} | {'max err':>8} "
    f"{'med err':>8} | note"
)


def print_row(r, _printed=[]):  # noqa: B006 (print the header once)
    if not _printed:
        print(HEAD)
        print("-" * len(HEAD))
        _printed.append(True)
    if "traj_per_s" not in r:
        print(f"{r['method']:>19} {r['batch']:>8}  {r.get('failed', r.get('skipped'))}")
        return
    ratio = f"{r['ratio_to_cuda_f64']:>9.2e}" if "ratio_to_cuda_f64" in r else f"{'':>9}"
    steps = (
        f"{r['mean_steps']:>6.0f} {r['max_steps']:>6}" if "mean_steps" in r else f"{'':>6} {'':>6}"
    )
    err = (
        f"{r['max_error']:>8.1e} {r['median_error']:>8.1e}"
        if "max_error" in r
        else f"{'':>8} {'':>8}"
    )
    note = f"{r['times_forward']:.2f}× forward" if "times_forward" in r else ""
    if "ratio_to_cuda_f32" in r:
        note += f"{r['ratio_to_cuda_f32']:.2f}× cuda f32"
    if "batching" in r:
        note += f"took {r['batching']}" + (f"({r['lanes']})" if "lanes" in r else "")
    if "store_bytes" in r:
        note += f"store {r['store_bytes'] / 1e6:.0f} MB written, end to end"
    if not r.get("all_successful", True):
        note += " (not all successful)"
    print(
        f"{r['method']:>19} {r['batch']:>8} {r['dtype']:>7} | {r['traj_per_s']:>10.4g} "
        f"{ratio} | {r['first_call_s']:>7.2f} {r['seconds']:>8.4f} | {steps} | {err} | "
        f"{note}",
        flush=True,
    )


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[1000, 10_000, 100_000, 1_000_000])
    p.add_argument("--grad-max", type=int, default=100_000)
    p.add_argument("--vmap-max", type=int, default=100_000)
    p.add_argument("--cpu-layout-max", type=int, default=0)
    p.add_argument("--whole-min", type=int, default=100_000)
    p.add_argument("--lanes", type=int, nargs="*", default=[])
    p.add_argument("--ref-max", type=int, default=1000)
    p.add_argument("--models", nargs="*", default=list(MODELS), choices=MODELS)
    p.add_argument("--model-min", type=int, default=100_000)
    p.add_argument("--sweep-n", type=int, default=10_000_000)
    p.add_argument("--blocks", type=int, nargs="*", default=[])
    p.add_argument("--budget", type=float, default=600.0)
    p.add_argument("--out", default="results/benchmarks")
    a = p.parse_args()
    main(
        a.sizes,
        a.grad_max,
        a.vmap_max,
        a.cpu_layout_max,
        a.whole_min,
        a.lanes,
        a.ref_max,
        a.budget,
        a.out,
        a.sweep_n,
        a.models,
        a.model_min,
        a.blocks,
    )
