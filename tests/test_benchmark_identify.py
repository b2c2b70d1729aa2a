"""Smoke test: benchmarks/identify.py runs at tiny sizes (1 trajectory × 15 samples, one
compiled repeat) and writes its JSON; rbdyn's `fit` and the scipy baseline both recover the
inertia and reach the same optimum of the same objective; the fits in new processes with the
persistent cache (empty, then warm) give the first fit's result.

One subprocess, which starts two more; their imports and the fit's compilation dominate.
"""

import json
import math
import pathlib
import subprocess
import sys

import numpy as np

SCRIPT = pathlib.Path(__file__).resolve().parents[1] / "benchmarks" / "identify.py"


def test_identify_benchmark_runs_and_recovers_inertia(tmp_path):
    out = tmp_path / "identify.json"
    args = ["--trajectories", "1", "--samples", "15", "--repeats", "1", "--out", str(out)]
    proc = subprocess.run(
        [sys.executable, "-W", "error", str(SCRIPT), *args],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    assert "scipy least_squares trf" in proc.stdout
    res = json.loads(out.read_text())
    assert {"meta", "rows", "ratios", "checks"} <= set(res)
    meta = res["meta"]
    assert meta["trajectories"] == 1 and meta["samples"] == 15
    assert meta["n_params"] == 12 and meta["n_residuals"] == 90

    first, compiled, sp, empty, warm = res["rows"]
    assert first["method"].startswith("rbdyn") and "compiled" in compiled["method"]
    assert sp["method"].startswith("scipy")
    assert "empty cache" in empty["method"] and "warm cache" in warm["method"]
    # The warm process loads the program the empty one stored: the same fit, bitwise; and
    # the same program as this process's first call (same flags and options), to round-off.
    assert warm["J_fit"] == empty["J_fit"] and warm["cost"] == empty["cost"]
    np.testing.assert_allclose(empty["J_fit"], first["J_fit"], rtol=1e-12, atol=1e-12)
    keys = {
        "method",
        "wall_s",
        "residual_evals",
        "jacobian_evals",
        "cost",
        "max_abs_err_J",
        "max_err_in_stderr",
        "J_fit",
        "time_ratio_scipy_over_this",
    }
    j_true = np.array(meta["J_true"])
    guess_err = np.max(np.abs(np.array(meta["J_guess"]) - j_true))  # 0.35
    for row in res["rows"]:
        assert keys <= set(row)
        assert row["wall_s"] > 0 and row["residual_evals"] > 0 and row["cost"] > 0
        # recovered: σ = 1e-3 on 15 samples gives stderr ~0.01–0.04 on J
        assert row["max_abs_err_J"] < 0.25 * guess_err
        assert row["max_err_in_stderr"] < 5.0
        assert np.max(np.abs(np.array(row["J_fit"]) - j_true)) == row["max_abs_err_J"]
    assert first["wall_s"] > compiled["wall_s"]  # the first call compiles
    for r in res["ratios"].values():
        assert math.isfinite(r) and r > 0

    # The two methods minimise the same objective and meet at its minimum.
    checks = res["checks"]
    assert checks["log_cholesky_max_diff"] < 1e-12
    assert checks["cost_rel_diff_at_rbdyn_optimum"] < 1e-5
    assert abs(sp["cost"] - first["cost"]) < 1e-4 * first["cost"]
    assert checks["max_J_rbdyn_minus_scipy_in_stderr"] < 0.1
