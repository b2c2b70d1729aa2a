"""Smoke test: benchmarks/sweep_scale.py runs its three parts at tiny sizes and writes JSON.

Three worker subprocesses, the fewest that cover the parts: (N=64, D=1) and (N=64, D=2)
for the device comparison, the latter also the chunk-size row and the first size of the
memory check, and (N=128, D=2). Two chunks each (lanes 8, chunk 32), so the steady rate is
defined. They run at once (`--jobs 3`): each compiles for ~20 s on a 2-core machine.
"""

import json
import pathlib
import subprocess
import sys

SCRIPT = pathlib.Path(__file__).resolve().parents[1] / "benchmarks" / "sweep_scale.py"


def test_sweep_scale_runs_all_parts(tmp_path):
    out = tmp_path / "sweep_scale.json"
    args = ["--n", "64", "--chunks", "32", "--compare-chunk", "32", "--rss-chunk", "32",
            "--sizes", "64", "128", "--devices", "2", "--lanes", "8", "--jobs", "3",
            "--out", str(out)]
    proc = subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True,
                          text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "identical: True" in proc.stdout
    res = json.loads(out.read_text())
    assert {"meta", "chunks", "devices", "memory"} <= set(res)
    assert res["meta"]["scenario"] == "torque_free_flip" and res["meta"]["jax"]

    rows = [*res["chunks"]["rows"], *res["devices"]["rows"], *res["memory"]["rows"]]
    for r in rows:
        assert r["n_chunks"] == r["n"] // 32 and r["status"] == {"successful": r["n"]}
        assert r["first_chunk_s"] > 0 and r["rest_s"] > 0
        assert r["steady_traj_per_s"] > 0 and r["overall_traj_per_s"] > 0
        assert r["peak_rss_mib"] >= r["base_rss_mib"] > 0
        assert r["jax_devices"] == r["devices"]
    assert [r["chunk"] for r in res["chunks"]["rows"]] == [32]
    assert [r["devices"] for r in res["devices"]["rows"]] == [1, 2]

    assert res["devices"]["identical"] is True
    assert set(res["devices"]["compared"]) >= {"omega", "quat", "status", "summarize",
                                               "first_flip_time"}
    assert [r["n"] for r in res["memory"]["rows"]] == [64, 128]
    assert res["memory"]["peak_rss_ratio"] > 0 and res["memory"]["n_ratio"] == 2
