"""Smoke test: the benchmark scripts run at tiny sizes and write their JSON."""

import importlib.util
import json
import pathlib
import re

import numpy as np
import pytest

BENCH = pathlib.Path(__file__).resolve().parents[1] / "benchmarks"


def test_throughput_runs_and_is_accurate(tmp_path):
    spec = importlib.util.spec_from_file_location("throughput", BENCH / "throughput.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    # the plain path is left out (plain_max=0): the lane solver's equality with it is
    # tested in tests/test_lanes.py, and each plain solve is one more compilation here
    rows = mod.main(
        sizes=(3,),
        models=("torque_free", "heavy_top"),
        lanes=2,
        scipy_max=2,
        plain_max=0,
        ref_max=3,
        out=str(tmp_path),
    )
    saved = json.loads((tmp_path / "throughput.json").read_text())
    assert saved["rows"] == rows and [r["batch"] for r in rows] == [3, 3]
    for r in rows:
        # every method at rtol 1e-8 stays close to the reference over t ≤ 100 (the elliptic
        # solution; numba at 1e-12 for the asymmetric heavy top, whose errors grow fastest:
        # measured 4e-5). For the heavy top this compares rbdyn_jax with numba's independent
        # equations (benchmarks/_baselines.py).
        assert "plain" not in r
        for method in ("default", "lanes", "numba", "scipy"):
            assert r[method]["max_error"] < 1e-3, (r["model"], method)
            assert np.isfinite(r[method]["traj_per_s"])
        # the equal-accuracy yardstick is at least as accurate as the lane solver, at the
        # loosest tolerance of its grid that gets there
        eq = r["numba_equal"]
        assert eq["median_error"] <= r["lanes"]["median_error"] or eq["tol"] == mod.TOL / 32
        assert eq["tol"] <= mod.TOL and np.isfinite(eq["traj_per_s"])
    assert rows[0]["lanes"]["max_error"] < 1e-6  # torque-free vs the elliptic solution


def test_compile_latency_runs_in_fresh_processes(tmp_path):
    """`benchmarks/compile.py` for `simulate` and the bare-diffrax yardstick: three fresh
    processes each (no cache, cold, warm). The solve's program holds no host callback, so
    the cold run writes cache entries; the only program refused is the eager `throw=True`
    check outside the solve. The yardstick's first call is the unit of the `vs_bare`
    column, and its vmapped solve is the same solve as `simulate` of its first trajectory:
    the same equations, solver, controller and tolerances take the same steps, so they
    agree to round-off (J⁻¹ is applied differently: an inverse there, a Cholesky solve in
    rbdyn_jax; seen 4e-16, bound 1e-12 for the growth of that round-off over 20 s)."""
    spec = importlib.util.spec_from_file_location("compile_bench", BENCH / "compile.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    rows = mod.main(cases=("simulate", mod.YARDSTICK), out=str(tmp_path))
    saved = json.loads((tmp_path / "compile.json").read_text())
    assert len(saved["rows"]) == len(rows) == 2
    row, bare = rows
    assert row["entries"] > 0
    assert all(
        np.isfinite(r[k]) and r[k] > 0 for k in ("no_cache_s", "cold_s", "warm_s") for r in rows
    )
    assert set(row["callback_programs"]) <= {"jit_branched_error_if_impl"}
    assert row["trace_hits"] == 1 and bare["trace_hits"] == 0  # rbdyn_jax's trace cache
    assert bare["vs_bare"] == 1.0 and row["vs_bare"] == row["no_cache_s"] / bare["no_cache_s"]
    assert all(r["runs"]["no_cache"]["finite"] for r in rows)

    ys = np.asarray(mod.build_call(mod.YARDSTICK)())
    traj = mod.build_call("simulate")()
    np.testing.assert_allclose(ys[0, :, :3], np.asarray(traj.ys.omega), rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        ys[0, :, 3:] / np.linalg.norm(ys[0, :, 3:], axis=-1, keepdims=True),
        np.asarray(traj.ys.quat),
        rtol=0,
        atol=1e-12,
    )


def load(name):
    spec = importlib.util.spec_from_file_location(name, BENCH / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_work_precision_runs(tmp_path):
    # three of the six methods: the plain path, the lane solver and numba (each diffrax
    # solver is one more compilation; Dopri5 through the lanes is in tests/test_lanes.py)
    rows = load("work_precision").main(
        n=4,
        tols=(1e-7,),
        out=str(tmp_path),
        repeats=1,
        methods=("Tsit5", "Tsit5 lanes", "numba DP5"),
    )
    assert (tmp_path / "work_precision.json").exists()
    by = {r["method"]: r for r in rows}
    # the lane solver takes diffrax's steps: same count and same error as the plain path
    assert by["Tsit5 lanes"]["mean_steps"] == by["Tsit5"]["mean_steps"]
    assert abs(by["Tsit5 lanes"]["max_error"] - by["Tsit5"]["max_error"]) < 1e-12
    assert all(r["max_error"] < 1e-3 for r in rows)  # rtol 1e-7 over t ≤ 100: measured ~2e-5
    assert {r["method"] for r in rows} == {"Tsit5", "Tsit5 lanes", "numba DP5"}


def test_gradients_runs_and_agrees(tmp_path):
    # jacfwd through the lanes only (its equality with reverse mode is in tests/test_lanes.py)
    rows = load("gradients").main(n=4, out=str(tmp_path), repeats=1, only=("jacfwd, lanes",))
    by = {
        r["method"].split(",")[0] + ("" if "lanes" not in r["method"] else " lanes"): r
        for r in rows
    }
    assert set(by) == {"forward loss", "forward loss lanes", "jacfwd lanes"}
    # the losses and the gradient within the rtol-1e-8 solve's error of the 1e-12 reference
    # (reverse mode at rtol 1e-12; measured 2.8e-9 at N = 64)
    assert all(r["rel_error"] < 1e-6 for r in rows)
    assert np.max(np.abs(by["jacfwd lanes"]["value"])) > 1.0  # a real gradient


def test_gradient_steps_runs_and_agrees(tmp_path):
    rows, error = load("gradient_steps").main(
        lanes=2, steps=3, rounds=1, kinds=("checkpointed",), out=str(tmp_path)
    )
    saved = json.loads((tmp_path / "gradient_steps.json").read_text())
    assert saved["rows"] == rows and saved["meta"]["reverse_vs_sensitivities"] == error
    assert [r["method"] for r in rows][:2] == ["forward", "sensitivities"] and len(rows) == 5
    assert all(np.isfinite(r["us_per_step"]) and r["us_per_step"] > 0 for r in rows)
    # The reverse step is the adjoint of the steps the sensitivities differentiate: equal
    # in exact arithmetic, to round-off over three steps (measured 2.6e-14 over 300).
    assert error < 1e-10


def test_gpu_report_runs_on_a_cpu(tmp_path):
    """`benchmarks/gpu.py`'s rows on this CPU at 3 trajectories over t ≤ 3: the kernel (in
    interpret mode, at its default block and at `--blocks 2`), the lane solver, the default
    call, the heavy top's rows, and the summaries-only sweep (4 trajectories, its store
    written and removed). The CUDA rows are recorded as failed (no driver here) and the run
    goes on. The gradient rows are left out
    (`grad_max=0`): the kernel's sensitivities take two minutes to compile in interpret
    mode, and its gradients are tested in tests/test_kernel.py."""
    mod = load("gpu")
    mod.T_END, mod.N_OUT = 3.0, 4
    rows = mod.main(
        sizes=[3],
        grad_max=0,
        vmap_max=0,
        cpu_layout_max=0,
        whole_min=10,
        lanes=[],
        ref_max=3,
        budget=600.0,
        out=str(tmp_path),
        sweep_n=4,
        models=["heavy_top"],
        model_min=0,
        blocks=[2],
    )
    saved = json.loads((tmp_path / "gpu.json").read_text())
    assert saved["rows"] == rows
    by = {r["method"]: r for r in rows}
    assert set(by) == {
        "cuda f64",
        "cuda f32",
        "kernel",
        "kernel f32",
        "Kernel(2)",
        "Kernel(2) f32",
        "default",
        "default f32",
        "lanes",
        "lanes f32",
        "sweep",
        "cuda f64 heavy_top",
        "kernel heavy_top",
        "lanes heavy_top",
    }
    assert "failed" in by["cuda f64"]
    assert by["default"]["batching"] == "Lanes"  # a CPU backend
    for m in ("kernel", "default", "lanes"):
        assert by[m]["all_successful"] and by[m]["max_error"] < 1e-6, m
    for m in ("kernel", "Kernel(2)"):  # blocks of 4 and of 2: the same steps in float64
        assert by[m]["mean_steps"] == by["lanes"]["mean_steps"], m
        assert by[f"{m} f32"]["all_successful"], m
    for m in ("", " heavy_top"):
        assert by[f"kernel{m}"]["mean_steps"] == by[f"lanes{m}"]["mean_steps"]
        assert by[f"kernel{m}"]["all_successful"]
    assert by["sweep"]["all_successful"] and by["sweep"]["store_bytes"] > 0
    # the kernel's first call compiles (its phases as JAX reports them, within the call)
    phases = by["kernel"]["first_call_phases"]
    assert 0 < phases["compile_s"] < by["kernel"]["first_call_s"] and phases["trace_s"] > 0
    # each repeat returns before it finishes, so the medians keep the order
    assert 0 < by["kernel"]["dispatch_s"] <= by["kernel"]["seconds"]
    # one chunk of 4: its seconds (within the whole run's), no sustained rate after it
    assert by["sweep"]["chunks"] == 1 and by["sweep"]["steady_traj_per_s"] is None
    assert 0 < by["sweep"]["first_chunk_s"] <= by["sweep"]["seconds"]
    assert not (tmp_path / "gpu_sweep.zarr").exists()


def test_long_horizon_runs_and_the_splitting_keeps_its_invariants(tmp_path):
    """`benchmarks/long_horizon.py` over 30 periods, Tsit5 at 1e-10 against the order-6
    splitting at T/50, and the splitting on the heavy top and the gravity-gradient body:
    its JSON and PNG, the energy error bounded by the splitting's 1.7e-9 (measured), |L| to
    rounding (1e-15 measured; 1e-13 allowed), the curves binned; under the potential
    torques the energy error at T/200 (3e-10 and 5e-8 measured; 1e-7 allowed) and the
    quaternion's norm to rounding."""
    spec = importlib.util.spec_from_file_location("long_horizon", BENCH / "long_horizon.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    rows = mod.main(
        periods=30.0,
        per_decade=20,
        out=str(tmp_path),
        repeats=1,
        methods=("Tsit5 1e-10", "Splitting 6, T/50"),
        potential_periods=30.0,
        potential_methods=("Splitting 6, T/200",),
    )
    saved = json.loads((tmp_path / "long_horizon.json").read_text())
    assert saved["rows"] == rows and (tmp_path / "long_horizon.png").stat().st_size > 1000
    tsit, split, top, gg = rows
    assert split["steps"] == 1500 and split["energy_max"] < 5e-9 and split["L_max"] < 1e-13
    assert tsit["L_max"] > 100 * split["L_max"]
    assert all(np.isfinite(r["us_per_period"]) and len(r["curve"]["energy"][0]) > 10 for r in rows)
    assert (top["body"], gg["body"]) == ("heavy top", "gravity gradient")
    assert all(
        r["steps"] == 6000
        and r["energy_max"] < 1e-7
        and r["quat_norm_drift"] < 1e-13
        and "L_max" not in r
        for r in (top, gg)
    )
    assert saved["meta"]["targets"]["energy_le_1e-8"]


def test_kernel_build_reads_the_kernel_lowered_for_an_h100():
    """`benchmarks/kernel_build.py` reads the Triton module of the kernel lowered for an H100
    from this CPU. JAX has no public API for it: this fails when Pallas's Triton lowering
    moves. The module is the kernel as built: one step loop holding the loop that saves
    output times; the values every lane shares (the inertia's 9 elements, the controller's
    rtol and atol, the time scale's start and span) read as 13 scalars; and as many memory
    operations on rows of lanes for the torque-free body's 7 states as for the gradient's
    25 states and sensitivities (each costs Triton's coalescing pass a pass over the kernel):
    a load per dtype of rows, the output times' reads, a store of saved rows and one of the
    counts; so too for a sweep's kernel, whose every trajectory has its own inertia."""
    mod = load("kernel_build")
    for case in ("torque_free-float32", "gradient", "sweep"):
        text = mod.case_module(case, n=16)
        assert text.count("tt.func public @rbdyn_kernel") == 1, case
        assert text.count("scf.while") == 2, case
        assert len(re.findall(r"tt\.(?:load|store) [^\n]*tensor<", text)) == 8, case
    scalar_loads = re.findall(
        r"tt\.load %\w+ : !tt\.ptr<f32>", mod.case_module("torque_free-float32")
    )
    assert len(scalar_loads) == 13


def test_kernel_build_compiles_for_sm_90(tmp_path):
    """Where the `triton` package is installed (the `kernel-build` extra), the benchmark
    compiles the module for sm_90 and reads ptxas's report of the kernel."""
    pytest.importorskip("triton")
    rows = load("kernel_build").main(cases=["torque_free-float32"], out=str(tmp_path))
    saved = json.loads((tmp_path / "kernel_build.json").read_text())
    assert saved["rows"] == rows and rows[0]["case"] == "torque_free-float32"
    assert 0 < rows[0]["registers"] <= 255 and rows[0]["blocks_per_sm"] >= 1
    assert rows[0]["compile_s"] > rows[0]["coalesce_s"] > 0
    # the machine code: float32 arithmetic (FFMA, FMUL, FADD) a part of it, and the
    # controller's power and the error norm's divisions on the special-function unit
    assert rows[0]["sass_instructions"] > rows[0]["sass_float"] > 0 and rows[0]["sass_mufu"] > 0


def test_store_write_runs_and_its_stores_read_back(tmp_path):
    """`benchmarks/store_write.py` writes solved trajectories into a store per compressor;
    each store reads back the values written, bit for bit (it raises otherwise), and a
    store keeping the states takes their bytes: 81 × 7 float64 a trajectory (4,536 B),
    which Blosc barely compresses (their low bits are noise: measured 4,235 B with LZ4)."""
    mod = load("store_write")
    rows = mod.main(n=256, states_n=64, repeats=1, out=str(tmp_path))
    saved = json.loads((tmp_path / "store_write.json").read_text())
    assert saved["rows"] == rows and saved["meta"]["compression"]["cname"] == "lz4"
    assert [(r["trajectories"], r["compressor"]) for r in rows] == [
        (t, c) for t in ("none", "all") for c in mod.COMPRESSORS
    ]
    for r in rows:
        assert r["traj_per_s"] > 0
        base = next(b for b in rows if b["trajectories"] == r["trajectories"])
        assert r["size_ratio"] == pytest.approx(r["bytes_per_traj"] / base["bytes_per_traj"])
    none, states = rows[0]["bytes_per_traj"], rows[3]["bytes_per_traj"]
    assert 0.85 * 4536 < states - none < 4536 + 200  # 200 B: a small store's metadata
