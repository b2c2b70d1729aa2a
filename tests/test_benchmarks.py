"""Smoke test: the benchmark scripts run at tiny sizes and write their JSON."""

import importlib.util
import json
import pathlib

import numpy as np

BENCH = pathlib.Path(__file__).resolve().parents[1] / "benchmarks"


def test_throughput_runs_and_is_accurate(tmp_path):
    spec = importlib.util.spec_from_file_location("throughput", BENCH / "throughput.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    rows = mod.main(sizes=(3,), scipy_max=2, repeats=1, out=str(tmp_path))
    saved = json.loads((tmp_path / "throughput.json").read_text())
    assert saved["rows"] == rows and rows[0]["batch"] == 3
    # both solvers at rtol 1e-8 agree with the elliptic solution to ~1e-7 over t ≤ 20
    assert rows[0]["rbdyn_max_error"] < 1e-6 and rows[0]["scipy_max_error"] < 1e-6
    assert np.isfinite(rows[0]["speedup_vs_scipy"])
