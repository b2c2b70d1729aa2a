"""The CUDA yardstick (`benchmarks/_cuda.py`) against the numba CPU solver
(`benchmarks/_baselines.py`), without a GPU: numba-cuda's simulator runs the kernel as Python,
one thread at a time, in a subprocess (``NUMBA_ENABLE_CUDASIM`` is read when numba is
imported, and this process may have imported it already).

Both run the same solver functions (`_baselines.solver_functions`), whose accuracy the
throughput benchmark's test checks against the elliptic solution and against scipy. Proven
here, for the three models: the kernel's launch, indexing and per-dtype build give, in
float64, the same steps with the same status and the same bits as `numba_solve` (the
simulator's Python floats are IEEE doubles without FMA contraction); in float32 the result
agrees with float64's to what the tolerance allows, with similar step counts; that every
operation is float32 is proven by typing the same functions with numba's CPU compiler (no
variable is float64), since the simulator cannot see it: under NumPy's promotion rules a
float64 literal does not promote a float32 scalar there, while numba would promote it.

`test_gpu_matches_numba` runs the compiled kernel on a real GPU (skipped without one).
"""

import ctypes.util
import json
import os
import pathlib
import shutil
import subprocess
import sys

import numpy as np
import pytest

BENCH = pathlib.Path(__file__).resolve().parents[1] / "benchmarks"
MODELS = ("torque_free", "heavy_top", "gravity_gradient")

pytestmark = pytest.mark.xdist_group("benchmark_cuda")  # one simulator run for the module

# argv: benchmarks folder, "sim" or "gpu", N per model, t_end, number of outputs. Prints JSON.
SCRIPT = r"""
import json, sys
sys.path.insert(0, sys.argv[1])
import numpy as np
import _cuda
from _baselines import MODELS, _prepare, _split, numba_solve, solver_functions

mode, N, t_end, n_out = sys.argv[2], int(sys.argv[3]), float(sys.argv[4]), int(sys.argv[5])
cuda = _cuda._import_cuda()
if not cuda.is_available():
    print(json.dumps({"available": False}))
    sys.exit()
params = {"inertia": np.array([[2.0, 0.05, 0.0], [0.05, 3.0, 0.02], [0.0, 0.02, 4.0]]),
          "weight": 1.0, "com": np.array([0.0, 0.0, 0.5]), "eps": 3.0}
rng = np.random.default_rng(7)
w0 = rng.normal(size=(N, 3))
q0 = rng.normal(size=(N, 4))
q0 /= np.linalg.norm(q0, axis=1, keepdims=True)
ts = np.linspace(0.0, t_end, n_out)


def dmax(a, b):
    return max(float(np.abs(a["omega"] - b["omega"]).max()),
               float(np.abs(a["quat"] - b["quat"]).max()))


res = {"available": True, "models": {}}
if mode == "sim":  # the device functions in float32, compiled for the CPU by numba
    import numba
    fns = solver_functions(np.float32, numba.njit)
for model in MODELS:
    cpu, gpu = (f(model, params, w0, q0, ts, 1e-8, 1e-8) for f in (numba_solve, _cuda.cuda_solve))
    cpu6 = numba_solve(model, params, w0, q0, ts, 1e-6, 1e-6)
    g32 = _cuda.cuda_solve(model, params, w0, q0, ts, 1e-6, 1e-6, dtype=np.float32)
    row = {"diff64": dmax(cpu, gpu), "finite": bool(np.isfinite(gpu["omega"]).all()),
           "steps_cpu": cpu["steps"].tolist(), "steps_cuda": gpu["steps"].tolist(),
           "status_cpu": cpu["status"].tolist(), "status_cuda": gpu["status"].tolist(),
           "dtype32": str(g32["omega"].dtype), "scale": float(np.abs(cpu6["omega"]).max()),
           "diff32_omega": float(np.abs(g32["omega"] - cpu6["omega"]).max()),
           "diff32_quat": float(np.abs(g32["quat"] - cpu6["quat"]).max()),
           "steps32": g32["steps"].tolist(), "steps64_tol6": cpu6["steps"].tolist(),
           "status32": g32["status"].tolist()}
    if mode == "sim":
        code, J, weight, com, eps, y0, ts64 = _prepare(model, params, w0, q0, ts)
        f32 = np.float32
        prm = tuple(f32(v) for v in (*J.ravel(), *np.linalg.inv(J).ravel(), *com, weight, eps))
        out = np.full((N, ts.size, 7), np.nan, dtype=f32)
        steps, status = np.zeros(N, dtype=np.int64), np.zeros(N, dtype=np.int64)
        for n in range(N):
            steps[n], status[n] = fns["solve_one"](code, prm, y0[n].astype(f32), ts64.astype(f32),
                                                   f32(1e-6), f32(1e-6), 100_000, out[n])
        row["diff32_njit"] = dmax(g32, _split(out, steps, status))
        row["steps32_njit"] = steps.tolist()
    res["models"][model] = row

if mode == "sim":
    # every variable of every device function, as numba typed them (all branches: the
    # functions were compiled, and typed, once above, with a runtime model code)
    def typed(fns):
        return [f"{name}.{var}: {ty}" for name, f in fns.items() for ov in f.overloads.values()
                for var, ty in ov.type_annotation.typemap.items()]

    res["typed_float32"] = [s for s in typed(fns) if "float32" in s]
    res["float64_vars"] = [s for s in typed(fns) if "float64" in s]
    # the canary: a bare literal times a float32 is typed float64, and seen so
    canary = numba.njit(lambda x: 0.5 * x)
    canary(np.float32(1))
    res["canary_float64_vars"] = [s for s in typed({"canary": canary}) if "float64" in s]
else:
    # the float32 kernel's PTX: no double-precision instruction
    ptx = "".join(_cuda._kernel(np.float32).inspect_asm().values())
    res["ptx32_f64"] = [ln.strip() for ln in ptx.splitlines() if ".f64" in ln][:10]
    res["ptx32_f32"] = sum(".f32" in ln for ln in ptx.splitlines())
print(json.dumps(res))
"""


def run(mode, n, t_end, n_out, timeout):
    env = dict(os.environ)
    env.pop("NUMBA_ENABLE_CUDASIM", None)
    if mode == "sim":
        env["NUMBA_ENABLE_CUDASIM"] = "1"
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(BENCH), mode, str(n), str(t_end), str(n_out)],
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    assert proc.returncode == 0, proc.stderr[-4000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def sim():
    """The simulator's run: 3 trajectories per model over t ∈ [0, 2], 5 outputs."""
    return run("sim", 3, 2.0, 5, timeout=600)


def check_float32(row, bound):
    """float32 at rtol = atol = 1e-6 against float64 at the same tolerances: they differ by
    the global errors of the two step sequences (each ~1e-6 per unit time at first, growing
    with t for these sensitive motions) and float32's round-off (~1e-7 per operation,
    growing with the steps); `bound` is relative to the largest |ω| (and absolute for the
    unit quaternion). The step counts differ a little, from round-off in the error
    estimate near the tolerance (by 0 or 1 in the runs seen)."""
    assert row["dtype32"] == "float32" and row["status32"] == [0] * len(row["status32"])
    assert row["diff32_omega"] <= bound * row["scale"], (row["diff32_omega"], row["scale"])
    assert row["diff32_quat"] <= bound, row["diff32_quat"]
    s32, s64 = np.array(row["steps32"]), np.array(row["steps64_tol6"])
    assert np.all(np.abs(s32 - s64) <= 0.25 * s64 + 2), (s32, s64)


@pytest.mark.parametrize("model", MODELS)
def test_float64_is_numba_bitwise(sim, model):
    """Same algorithm and operation order, and IEEE doubles on both sides: the same bits
    (max |Δ| over ω and q exactly 0), the same step counts and status."""
    row = sim["models"][model]
    assert row["finite"] and row["diff64"] == 0.0
    assert row["steps_cuda"] == row["steps_cpu"] and min(row["steps_cpu"]) > 3
    assert row["status_cuda"] == row["status_cpu"] == [0, 0, 0]


@pytest.mark.parametrize("model", MODELS)
def test_float32_agrees_with_float64(sim, model):
    """Over t ≤ 2 (seen: 3.5e-6 of |ω| ≤ 1.34, 1.1e-6 in q), bound 1e-4: a wrong float32 path
    (a constant, a cast) would exceed it; and the simulator's float32 run is the CPU-compiled
    float32 functions' run, bit for bit (NumPy float32 scalars there, numba float32 here;
    sqrt and nextafter cast back to float32)."""
    row = sim["models"][model]
    check_float32(row, 1e-4)
    assert row["diff32_njit"] == 0.0 and row["steps32_njit"] == row["steps32"]


def test_float32_build_has_no_float64(sim):
    """numba types every variable of the float32 build float32 (or int, bool, tuples of
    them): a bare float literal or a float64 constant would show as a float64 variable, as
    the canary's shows: numba types ``0.5 * x`` float64 for a float32 x."""
    assert sim["float64_vars"] == [] and len(sim["typed_float32"]) > 1000
    assert any(s.startswith("canary.$binop_mul") for s in sim["canary_float64_vars"])


def has_cuda_gpu() -> bool:
    """Cheap guess: a CUDA driver library, device node or nvidia-smi."""
    return bool(
        ctypes.util.find_library("cuda")
        or os.path.exists("/dev/nvidiactl")
        or shutil.which("nvidia-smi")
    )


@pytest.mark.gpu
def test_gpu_matches_numba():
    """The compiled kernel on a GPU, 1000 trajectories per model over t ∈ [0, 10]. float64:
    numba's results up to round-off, which is not bitwise here, as NVVM fuses multiply–adds
    into FMAs (its default; numba-cuda's fastmath is off), so a step's accept/reject
    decision may flip in rare cases (seen on an H100: all 3000 step counts equal, max |Δ|
    1.8e-12; 1e-6 leaves room for a flipped step, whose difference is of the tolerance's
    order). float32: as in the simulator's test, over a 5 times longer horizon, where the two
    solutions' global errors have grown (seen 4.5e-4 in ω, 2.3e-4 in q, for the gravity
    gradient), bound 2e-3; and the float32 kernel's PTX holds no double-precision
    instruction."""
    if not has_cuda_gpu():
        pytest.skip("no CUDA GPU")
    res = run("gpu", 1000, 10.0, 11, timeout=900)
    if not res["available"]:
        pytest.skip("numba.cuda sees no GPU")
    for model, row in res["models"].items():
        assert row["finite"], model
        assert row["status_cuda"] == row["status_cpu"] == [0] * 1000, model
        steps_cpu, steps_cuda = np.array(row["steps_cpu"]), np.array(row["steps_cuda"])
        assert np.mean(steps_cpu != steps_cuda) <= 0.01, model
        assert np.abs(steps_cpu - steps_cuda).max() <= 2, model
        assert row["diff64"] <= 1e-6, (model, row["diff64"])
        check_float32(row, 2e-3)
    assert res["ptx32_f64"] == [] and res["ptx32_f32"] > 100, res["ptx32_f64"]
