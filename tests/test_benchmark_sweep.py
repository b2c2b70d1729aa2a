"""Smoke test: benchmarks/sweep_scale.py runs its four parts at tiny sizes and writes JSON.

Four subprocesses, the fewest that cover the parts: (N=64, D=1) and (N=64, D=2) for the
device comparison, the latter also the chunk-size row, the first size of the memory check
and the in-process row of part 4, (N=128, D=2), and a Dask LocalCluster of 2 workers × 1
device at N=64. Two chunks each (lanes 8, chunk 32), so the steady rate is defined. Two
run at a time (`--jobs 2`, one a core of a 2-core machine: four at once only contend for
the cores, and the LocalCluster compiles once per worker).
"""

import json
import pathlib
import subprocess
import sys

SCRIPT = pathlib.Path(__file__).resolve().parents[1] / "benchmarks" / "sweep_scale.py"


def test_sweep_scale_runs_all_parts(tmp_path):
    out = tmp_path / "sweep_scale.json"
    args = [
        "--n",
        "64",
        "--chunks",
        "32",
        "--compare-chunk",
        "32",
        "--rss-chunk",
        "32",
        "--sizes",
        "64",
        "128",
        "--devices",
        "2",
        "--workers",
        "2",
        "--lanes",
        "8",
        "--jobs",
        "2",
        "--out",
        str(out),
    ]
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), *args],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.count("identical: True") == 2  # parts 2 and 4
    res = json.loads(out.read_text())
    assert {"meta", "chunks", "devices", "memory", "dask"} <= set(res)
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
    assert set(res["devices"]["compared"]) >= {
        "omega",
        "quat",
        "status",
        "summarize",
        "first_flip_time",
    }
    assert [r["n"] for r in res["memory"]["rows"]] == [64, 128]
    assert res["memory"]["peak_rss_ratio"] > 0 and res["memory"]["n_ratio"] == 2

    dask = res["dask"]
    assert dask["workers"] == 2 and dask["identical"] is True and dask["ratio"] > 0
    assert set(dask["compared"]) == set(res["devices"]["compared"])
    local, cluster = dask["rows"]
    assert local["engine"] == "in-process" and local["devices"] == 2
    assert {k: v for k, v in local.items() if k in res["devices"]["rows"][1]} == res["devices"][
        "rows"
    ][1]  # part 2's run, not run again
    assert cluster["engine"] == "dask" and cluster["workers"] == 2
    assert cluster["devices"] == cluster["jax_devices"] == 1
    assert cluster["n_chunks"] == 2 and cluster["status"] == {"successful": 64}
    for r in dask["rows"]:
        assert r["first_chunk_s"] > 0 and r["rest_s"] > 0 and r["steady_traj_per_s"] > 0
    assert cluster["cluster_start_s"] > 0 and len(cluster["worker_compile_s"]) == 2
    assert cluster["peak_rss_mib"] >= cluster["base_rss_mib"] > 0
    assert len(cluster["worker_rss_mib"]) == 2 and cluster["worker_peak_rss_mib"] > 0
