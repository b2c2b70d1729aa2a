"""The GPU kernel as a GPU would build it, measured on any machine: `rb.Kernel`'s Pallas
kernel lowered for an H100 (`jax.export` for CUDA, from this machine) and its Triton module
compiled for sm_90 by the `triton` package's compiler and `ptxas`, a stand-in for the
Triton compiler inside XLA (the GPU's first call compiles the same module there).

For each case it reports what sets a GPU thread's cost and the first call's Triton share:

- `registers` a thread, `spill_stores` / `spill_loads` (bytes a thread moves to local
  memory, per `ptxas -v`) and `stack` (its frame, bytes);
- `blocks_per_sm`: the programs (blocks of `block` lanes, a lane a thread) an H100
  streaming multiprocessor holds at once by its 65,536 registers, and `resident_warps`;
- `compile_s`: the Triton compilation's seconds on this machine (TTIR passes, TTGIR,
  LLVM IR, PTX, `ptxas`), `coalesce_s` the part in Triton's coalescing pass, and the sizes
  of the module (`ttir_ops`) and of its PTX (`ptx_lines`);
- the machine code (SASS, `cuobjdump -sass` of ptxas's cubin), nearly all of it the step
  loop's: `sass_instructions`, of which `sass_float` floating-point multiply-adds,
  multiplies and adds and `sass_mufu` operations of the special-function unit
  (reciprocals, square roots, logarithms and exponentials: an H100 multiprocessor issues
  16 of them a cycle, against 64 float64 multiply-adds).

Cases: the torque-free body, the heavy top and the gravity-gradient satellite of
`gpu.py` (Tsit5, rtol = atol = 1e-8 in float64 and 1e-6 in float32, 101 outputs), each in
float64 and float32; `gradient`: `jax.grad` of Σ ω² over the outputs through the
kernel w.r.t. the six log-Cholesky parameters of the inertia (the kernel of state and
sensitivities, float64); and `sweep`: the kernel of a chunk of `sweep.run`'s shipped
scenario `torque_free_flip` (Tsit5 at 1e-8, 81 outputs over 40 s, each trajectory its own
sampled inertia, float64).

Needs the `triton` package (`pip install -c requirements.lock -e ".[kernel-build]"`; Linux
x86-64), which brings its own `ptxas`; no GPU. Run: `python benchmarks/kernel_build.py [--cases …]
[--blocks 128 …] [--out results/benchmarks]`.
"""

import argparse
import os
import pathlib
import re
import subprocess
import sys
import tempfile
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import rbdyn_jax as rb  # noqa: E402
from rbdyn_jax._program import checks  # noqa: E402
from rbdyn_jax.integrate._kernel_layout import GPU_BLOCK, triton_warps  # noqa: E402
from rbdyn_jax.integrate._kernel_solve import kernel_solve  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).parent))
import _report  # noqa: E402
from gpu import N_OUT, T_END, TOL, J, rbdyn_model, states  # noqa: E402

CASES = tuple(f"{m}-{d}" for m in ("torque_free", "heavy_top", "gravity_gradient") for d in TOL) + (
    "gradient",
    "sweep",
)
H100_REGISTERS, SM_ARCH = 65536, 90


def h100_mesh():
    """An abstract mesh naming an H100: Pallas's Triton lowering asks for the GPU's compute
    capability, which a machine without one names by its mesh."""
    return jax.sharding.AbstractMesh(
        (1,),
        ("x",),
        (jax.sharding.AxisType.Explicit,),
        abstract_device=jax.sharding.AbstractDevice(
            device_kind="NVIDIA H100 80GB HBM3", num_cores=132, platform="gpu"
        ),
    )


def triton_module(fn, *args) -> str:
    """The Triton module (text) of the one Pallas call in `jax.jit(fn)(*args)` lowered for
    CUDA. JAX has no public API for it: this wraps Pallas's Triton lowering
    (`jax._src.pallas.triton`), and fails loudly where that has moved."""
    from jax._src.pallas.triton import pallas_call_registration as registration

    lowering = registration.lowering
    original = lowering.lower_jaxpr_to_triton_module
    modules = []

    def capture(*a, **k):
        result = original(*a, **k)
        modules.append(result.module.operation.get_asm())
        return result

    lowering.lower_jaxpr_to_triton_module = capture
    try:
        with checks.as_nan(), jax.sharding.use_abstract_mesh(h100_mesh()):
            jax.export.export(
                jax.jit(fn),
                platforms=["cuda"],
                disabled_checks=[
                    jax.export.DisabledSafetyCheck.custom_call("__gpu$xla.gpu.triton")
                ],
            )(*args)
    finally:
        lowering.lower_jaxpr_to_triton_module = original
    if len(modules) != 1:
        raise RuntimeError(f"expected one Triton module, lowered {len(modules)}.")
    return modules[0]


def case_module(case: str, block: int = GPU_BLOCK, n: int | None = None) -> str:
    """The Triton module of a case (`CASES`) at `block` lanes a program, for a batch of `n`
    trajectories (default two blocks)."""
    n = 2 * block if n is None else n
    w0 = np.random.default_rng(0).normal(size=(n, 3))
    ts = np.linspace(0.0, T_END, N_OUT)
    if case == "sweep":
        return triton_module(*_sweep_solve(n, block))
    if case == "gradient":
        body = rb.RigidBody(jnp.asarray(J))
        y0s = states(w0, np.float64)

        def loss(theta):
            tr = rb.simulate_batch(
                rb.with_log_cholesky(body, theta),
                y0s,
                jnp.asarray(ts),
                rtol=TOL["float64"],
                atol=TOL["float64"],
                batching=rb.Kernel(block=block, interpret=False, devices=1),
            )
            return jnp.sum(tr.ys.omega**2)

        return triton_module(jax.grad(loss), rb.inertia.to_log_cholesky(jnp.asarray(J)))
    model_name, dtype = case.split("-")
    model = rbdyn_model(model_name, dtype)
    pid = rb.integrate.make_controller(rtol=TOL[dtype], atol=TOL[dtype], dtype=dtype)

    def solve(y0s, ts):
        return kernel_solve(model, y0s, ts, diffrax.Tsit5(), pid, 10**6, None, None, block, False)

    return triton_module(solve, states(w0, dtype), jnp.asarray(ts, dtype))


def _sweep_solve(n: int, block: int):
    """The solve of a sweep's chunk of `n` trajectories of `torque_free_flip` as `sweep.run`
    runs it on a GPU (its scenario's solver, tolerances and times; a per-trajectory inertia;
    `block` lanes a program),
    and its arguments: the sampled values (drawn here: sampling reads no GPU) and the times."""
    from rbdyn_jax.scenario import Scenario

    sc = Scenario.load("torque_free_flip")
    values = jax.vmap(lambda i: sc.sample(sc.dists, jax.random.key(0), i))(jnp.arange(n))

    def solve(values, ts):
        models, y0s = jax.vmap(sc.build)(values)
        return rb.simulate_batch(
            models,
            y0s,
            ts,
            model_axes=0,
            solver=sc.diffrax_solver,
            stepsize_controller=sc.stepsize_controller,
            dt0=sc.dt,
            max_steps=sc.max_steps,
            batching=rb.Kernel(block=block, interpret=False, devices=1),
        )

    return solve, values, jnp.asarray(sc.ts)


def build(module: str, block: int = GPU_BLOCK) -> dict:
    """Compile a Triton module's text for sm_90 as XLA's pipeline does (its TTIR passes
    first, as the `triton` package's own front end runs them), timed, and read `ptxas -v`'s
    report of its kernel."""
    import triton
    from triton._C.libtriton import ir, passes
    from triton.backends.compiler import GPUTarget
    from triton.backends.nvidia.compiler import CUDABackend

    target = GPUTarget("cuda", SM_ARCH, 32)
    warps = triton_warps(block)
    with tempfile.TemporaryDirectory() as tmp:
        os.environ["TRITON_CACHE_DIR"] = tmp  # nothing reused between cases
        src = pathlib.Path(tmp, "kernel.ttir")
        src.write_text(module)
        t0 = time.perf_counter()
        ctx = ir.context()
        ir.load_dialects(ctx)
        CUDABackend(target).load_dialects(ctx)
        mod = ir.parse_mlir_module(str(src), ctx)
        pm = ir.pass_manager(ctx)
        for add in (
            passes.common.add_inliner,
            passes.ttir.add_rewrite_tensor_pointer,
            passes.common.add_canonicalizer,
            passes.ttir.add_combine,
            passes.ttir.add_reorder_broadcast,
            passes.common.add_cse,
            passes.common.add_symbol_dce,
        ):
            add(pm)
        pm.run(mod, "ttir")
        src.write_text(str(mod))
        ttir_ops = len(re.findall(r"^\s*(?:%\S+ = )?\"?[a-z_]+\.[a-z_.]+", str(mod), re.M))
        compiled, coalesce_s = _pass_seconds(
            lambda: triton.compile(
                str(src),
                target=target,
                options={"num_warps": warps, "num_stages": 1},
            )
        )
        compile_s = time.perf_counter() - t0
        ptx = pathlib.Path(tmp, "kernel.ptx")
        ptx.write_text(compiled.asm["ptx"])
        tools = pathlib.Path(triton.__file__).parent / "backends/nvidia/bin"
        cubin = pathlib.Path(tmp, "kernel.cubin")
        report = subprocess.run(
            [str(tools / "ptxas"), "-v", f"--gpu-name=sm_{SM_ARCH}a", str(ptx), "-o", str(cubin)],
            capture_output=True,
            text=True,
            check=True,
        ).stderr
        sass = subprocess.run(
            [str(tools / "cuobjdump"), "-sass", str(cubin)],
            capture_output=True,
            text=True,
            check=True,
        ).stdout
    usage = _ptxas_usage(report, compiled.name)
    ops = _sass_opcodes(sass)
    threads = 32 * warps
    blocks = H100_REGISTERS // (max(usage["registers"], 1) * threads)
    return {
        **usage,
        "blocks_per_sm": blocks,
        "resident_warps": blocks * warps,
        "compile_s": compile_s,
        "coalesce_s": coalesce_s,
        "ttir_ops": ttir_ops,
        "ptx_lines": compiled.asm["ptx"].count("\n"),
        "sass_instructions": len(ops),
        "sass_float": sum(op in ("DFMA", "DMUL", "DADD", "FFMA", "FMUL", "FADD") for op in ops),
        "sass_mufu": ops.count("MUFU"),
    }


def _sass_opcodes(sass: str) -> list[str]:
    """The opcode of every instruction in `cuobjdump -sass`'s listing (a predicate such as
    `@!P0` skipped, modifiers such as `.RCP64H` dropped)."""
    return re.findall(r"^\s+/\*[0-9a-f]{4,}\*/\s+(?:@!?U?P[T0-9]\s+)?([A-Z][A-Z0-9_]*)", sass, re.M)


def _pass_seconds(fn):
    """`fn()` and the seconds MLIR's pass timing gives Triton's coalescing pass in it."""
    os.environ["MLIR_ENABLE_TIMING"] = "1"
    fd = os.dup(2)  # MLIR writes its timing report to the process's stderr (fd 2)
    try:
        with tempfile.TemporaryFile("w+") as f:
            os.dup2(f.fileno(), 2)
            try:
                out = fn()
            finally:
                os.dup2(fd, 2)
            f.seek(0)
            text = f.read()
    finally:
        os.close(fd)
        os.environ.pop("MLIR_ENABLE_TIMING", None)
    found = re.findall(r"^\s*([\d.]+) \(\s*[\d.]+%\)\s+TritonGPUCoalesce$", text, re.M)
    return out, (float(found[0]) if found else None)


def _ptxas_usage(report: str, name: str) -> dict:
    """Registers, spills and stack of the kernel `name` in `ptxas -v`'s report."""
    block = report.split(f"Compiling entry function '{name}'", 1)[1]
    spill = re.search(
        r"(\d+) bytes stack frame, (\d+) bytes spill stores, (\d+) bytes spill loads", block
    )
    regs = re.search(r"Used (\d+) registers", block)
    if spill is None or regs is None:
        raise RuntimeError(f"no usage of {name!r} in ptxas's report:\n{report}")
    stack, stores, loads = (int(x) for x in spill.groups())
    return {
        "registers": int(regs.group(1)),
        "spill_stores": stores,
        "spill_loads": loads,
        "stack": stack,
    }


def main(cases=CASES, blocks=(GPU_BLOCK,), out="results/benchmarks"):
    import triton

    rows = []
    print(
        f"{'case':<26}{'block':>6}{'regs':>6}{'spill st/ld B':>16}{'blocks/SM':>11}"
        f"{'compile s':>11}{'coalesce s':>12}{'TTIR ops':>10}"
    )
    for case in cases:
        for block in blocks:
            row = {"case": case, "block": block, **build(case_module(case, block), block)}
            rows.append(row)
            print(
                f"{case:<26}{block:>6}{row['registers']:>6}"
                f"{row['spill_stores']:>8}/{row['spill_loads']:<7}{row['blocks_per_sm']:>11}"
                f"{row['compile_s']:>11.2f}{row['coalesce_s'] or float('nan'):>12.2f}"
                f"{row['ttir_ops']:>10}"
            )
    meta = {
        "triton": triton.__version__,
        "target": f"sm_{SM_ARCH}a (H100)",
        "blocks": list(blocks),
        "t_end": T_END,
        "n_out": N_OUT,
        "tol": TOL,
    }
    print("wrote", _report.write_json(out, "kernel_build", meta, rows))
    return rows


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", nargs="+", default=list(CASES), choices=CASES)
    p.add_argument("--blocks", type=int, nargs="+", default=[GPU_BLOCK])
    p.add_argument("--out", default="results/benchmarks")
    main(**vars(p.parse_args()))
