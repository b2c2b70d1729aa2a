"""Scaling of Monte Carlo sweeps (`rbdyn_jax.sweep.run`): chunk size, device count, memory,
and in-process against a Dask LocalCluster.

Setting: the shipped scenario `torque_free_flip` (or `--scenario NAME`), seed 0, float64,
CPU only (`JAX_PLATFORMS=cpu`), each configuration in a fresh subprocess whose XLA host
device count is set with `XLA_FLAGS=--xla_force_host_platform_device_count=D` (default
D = os.cpu_count(), all cores as host devices) and whose XLA otherwise starts as docs/performance.md
advises (`rb.configure_xla()`, while loops compiled whole). Per run, from the `progress`
callback of `sweep.run`: the wall time of the first chunk (it includes the compilation) and of the
rest, trajectories/s over the chunks after the first (steady state; a padded last chunk
costs a full one), and the peak RSS of the process (`ru_maxrss`; "base" = the peak right
after importing rbdyn_jax and starting JAX, before the sweep).

1. chunk sizes at fixed N (default N = 8192, chunks 256 1024 4096), D devices;
2. 1 vs D devices at chunk 1024 (D ≥ 2), and whether the two stores hold bitwise-identical
   `omega`, `quat`, `inertia`, `status`, `num_steps`, every summary variable and
   `sweep.summarize` output ("identical: True/False");
3. peak RSS at N and 4N (default 8192, 32768) at chunk 1024: memory must not grow with N;
4. in-process against a Dask LocalCluster at N and chunk 1024: the in-process run of part 2
   on D devices beside `sweep.run(..., client=Client(LocalCluster(n_workers=K,
   threads_per_worker=1, processes=True)))` (K = `--workers`, default os.cpu_count()),
   each worker with max(1, D // K) XLA host devices (the cluster starts in the
   configuration's subprocess, whose environment its workers inherit). Measured: the
   cluster's start-up (until K workers are up); "first chunk" = the warm-up, in which every
   worker compiles the solver and solves one chunk of a scratch sweep (all at once, so that
   the sweep's chunks never wait on a compilation, whichever worker takes them); "rest" =
   the sweep of all N on the compiled workers, and steady trajectories/s = N / rest; the
   driver's peak RSS (it holds the scheduler) and the largest worker's (`client.run`).
   Reported: whether the two stores are bitwise identical (as in part 2) and the ratio of
   the steady rates, LocalCluster ÷ in-process. A chunk is padded to a multiple of
   8 × lanes × its devices (D in-process, D // K on a worker), and with N / chunk < K some
   workers stay idle: the rates are those of this N and chunk, not each engine's best.

A configuration shared by two parts runs once (at defaults 6 subprocesses, one after the
other; `--jobs J` runs J at once, for smoke tests only). `--parts` picks parts. The zarr
stores go to a temporary directory, each deleted once it is no longer needed.

Run: `python benchmarks/sweep_scale.py [--n 8192] [--chunks 256 1024 4096]
[--sizes 8192 32768] [--workers K] [--parts 1 2 3 4] [--scenario torque_free_flip]` —
prints a table per part and writes results/benchmarks/sweep_scale.json.
"""

import argparse
import json
import os
import pathlib
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from importlib.metadata import version

COMPARED = ("omega", "quat", "inertia", "status", "num_steps")


# ----------------------------------------------------------------------------------------
# Worker: one configuration, in a fresh process (the device count is fixed at JAX start).
# ----------------------------------------------------------------------------------------


def _rss_mib():
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux


def worker(cfg):
    t_proc = time.perf_counter()
    import rbdyn_jax

    rbdyn_jax.configure_xla()  # as docs/performance.md advises (the device count is the parent's)
    import jax

    jax.config.update("jax_enable_x64", True)
    from rbdyn_jax import sweep

    n_dev = len(jax.devices())
    base_rss = _rss_mib()
    ticks = []
    t0 = time.perf_counter()
    sweep.run(
        cfg["scenario"],
        cfg["n"],
        cfg["store"],
        chunk=cfg["chunk"],
        seed=cfg["seed"],
        devices=cfg["devices"],
        lanes=cfg["lanes"],
        progress=lambda p: ticks.append((p.elapsed, p.solved_now, p.failed)),
    )
    total = time.perf_counter() - t0
    peak_rss = _rss_mib()
    first = ticks[0][0]
    rest = ticks[-1][0] - first
    rest_n = sum(t[1] for t in ticks[1:])
    summary = sweep.summarize(cfg["store"])
    return {
        "n": cfg["n"],
        "chunk": cfg["chunk"],
        "devices": cfg["devices"],
        "jax_devices": n_dev,
        "lanes": cfg["lanes"],
        "n_chunks": len(ticks),
        "first_chunk_s": first,
        "rest_s": rest,
        "steady_traj_per_s": rest_n / rest if len(ticks) > 1 and rest > 0 else None,
        "overall_traj_per_s": cfg["n"] / total,
        "run_s": total,
        "process_s": time.perf_counter() - t_proc,
        "base_rss_mib": base_rss,
        "peak_rss_mib": peak_rss,
        "failed": ticks[-1][2],
        "status": summary["status"],
        "concurrent_jobs": cfg["jobs"],
    }


def _warm_up(source, name, store, chunk, seed, lanes, devices):
    """In a Dask worker: compile the chunk solver `solve_chunk` will use (the same scenario
    source, lanes, devices and padded chunk: `sweep` keeps it for the process) by solving
    one chunk of a scratch sweep in this process; (seconds, jax devices)."""
    t0 = time.perf_counter()
    import jax

    jax.config.update("jax_enable_x64", True)
    from rbdyn_jax import sweep
    from rbdyn_jax.scenario import Scenario

    sc = Scenario.from_dict(source, default_name=name)
    sweep.run(sc, chunk, store, chunk=chunk, seed=seed, devices=devices, lanes=lanes)
    shutil.rmtree(store, ignore_errors=True)
    return time.perf_counter() - t0, len(jax.devices())


def cluster_worker(cfg):
    """Part 4's LocalCluster run: the cluster starts here, so its worker processes inherit
    this process's environment (the XLA flags of `configure_xla`, the device count)."""
    t_proc = time.perf_counter()
    import rbdyn_jax

    rbdyn_jax.configure_xla()  # into os.environ, before the workers start
    import jax

    jax.config.update("jax_enable_x64", True)
    from distributed import Client, LocalCluster

    from rbdyn_jax import sweep
    from rbdyn_jax.scenario import Scenario

    sc = Scenario.load(cfg["scenario"])
    k = cfg["workers"]
    base_rss = _rss_mib()
    ticks = []
    t0 = time.perf_counter()
    with (
        LocalCluster(
            n_workers=k,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            env={"JAX_ENABLE_X64": "1"},
        ) as cluster,
        Client(cluster) as client,
    ):
        client.wait_for_workers(k)
        start = time.perf_counter() - t0
        t1 = time.perf_counter()
        warm = client.gather(
            [
                client.submit(
                    _warm_up,
                    sc.source,
                    sc.name,
                    f"{cfg['store']}.warm{i}",
                    cfg["chunk"],
                    cfg["seed"],
                    cfg["lanes"],
                    cfg["devices"],
                    workers=[addr],
                    allow_other_workers=False,
                    pure=False,
                )
                for i, addr in enumerate(client.scheduler_info(n_workers=-1)["workers"])
            ]
        )
        first = time.perf_counter() - t1
        if len(warm) != k:
            raise RuntimeError(f"{len(warm)} of {k} workers warmed up")
        t2 = time.perf_counter()
        sweep.run(
            sc,
            cfg["n"],
            cfg["store"],
            chunk=cfg["chunk"],
            seed=cfg["seed"],
            devices=cfg["devices"],
            lanes=cfg["lanes"],
            client=client,
            progress=lambda p: ticks.append((p.elapsed, p.solved_now, p.failed)),
        )
        total = time.perf_counter() - t2
        worker_rss = list(client.run(_rss_mib).values())
    peak_rss = _rss_mib()
    rest = ticks[-1][0]
    summary = sweep.summarize(cfg["store"])
    return {
        "engine": "dask",
        "n": cfg["n"],
        "chunk": cfg["chunk"],
        "workers": k,
        "devices": cfg["devices"],
        "jax_devices": min(d for _, d in warm),
        "lanes": cfg["lanes"],
        "n_chunks": len(ticks),
        "cluster_start_s": start,
        "first_chunk_s": first,
        "worker_compile_s": [s for s, _ in warm],
        "rest_s": rest,
        "steady_traj_per_s": cfg["n"] / rest if rest > 0 else None,
        "run_s": total,
        "process_s": time.perf_counter() - t_proc,
        "base_rss_mib": base_rss,
        "peak_rss_mib": peak_rss,
        "worker_peak_rss_mib": max(worker_rss),
        "worker_rss_mib": worker_rss,
        "failed": ticks[-1][2],
        "status": summary["status"],
        "concurrent_jobs": cfg["jobs"],
    }


# ----------------------------------------------------------------------------------------
# Driver
# ----------------------------------------------------------------------------------------


def _spawn(cfg, host_devices, label):
    """`cfg` in a fresh subprocess with `host_devices` XLA host devices; its result row."""
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    flags = [
        f
        for f in env.get("XLA_FLAGS", "").split()
        if not f.startswith("--xla_force_host_platform_device_count")
    ]
    env["XLA_FLAGS"] = " ".join([*flags, f"--xla_force_host_platform_device_count={host_devices}"])
    print(f"  run {label} …", flush=True)
    proc = subprocess.run(
        [sys.executable, os.path.abspath(__file__), "--worker", json.dumps(cfg)],
        env=env,
        capture_output=True,
        text=True,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"worker {cfg} failed ({proc.returncode}):\n{proc.stderr}")
    return json.loads(pathlib.Path(cfg["result"]).read_text())


def _cfg(args, tmp, name, **kw):
    return {
        "scenario": args.scenario,
        "lanes": args.lanes,
        "seed": args.seed,
        "store": str(tmp / f"{name}.zarr"),
        "result": str(tmp / f"{name}.json"),
        "jobs": args.jobs,
        **kw,
    }


def run_worker(args, tmp, n, chunk, devices):
    """One in-process configuration in a fresh subprocess; its store is left in `tmp`."""
    cfg = _cfg(args, tmp, f"n{n}_c{chunk}_d{devices}", n=n, chunk=chunk, devices=devices)
    row = _spawn(cfg, devices, f"n={n} chunk={chunk} devices={devices}")
    return row, cfg["store"]


def run_cluster(args, tmp, n, chunk, workers, devices):
    """Part 4's LocalCluster of `workers` × `devices` in a fresh subprocess; its store is
    left in `tmp`."""
    cfg = _cfg(
        args,
        tmp,
        f"n{n}_c{chunk}_dask{workers}x{devices}",
        n=n,
        chunk=chunk,
        devices=devices,
        workers=workers,
    )
    row = _spawn(
        cfg, devices, f"n={n} chunk={chunk} LocalCluster {workers} workers × {devices} devices"
    )
    return row, cfg["store"]


def compare_stores(a, b):
    """{variable: bitwise equal} over the compared arrays and every summary variable, plus
    `summarize` (the counts and statistics) as a whole."""
    import numpy as np
    import zarr

    from rbdyn_jax import sweep

    ga, gb = zarr.open_group(a, mode="r"), zarr.open_group(b, mode="r")
    names = [*COMPARED, *ga.attrs["summaries"].split()]
    same = {k: bool(np.array_equal(ga[k][:], gb[k][:], equal_nan=True)) for k in names}
    same["summarize"] = sweep.summarize(a) == sweep.summarize(b)
    return same


def _f(x, spec):
    return "—" if x is None else format(x, spec)


def _table(title, rows, cols):
    """cols: (header, key, format)."""
    print(f"\n{title}")
    head = " ".join(f"{h:>{w}}" for h, _, w, _ in cols)
    print(head)
    print("-" * len(head))
    for r in rows:
        print(" ".join(f"{_f(r[k], f):>{w}}" if f else f"{r[k]!s:>{w}}" for _, k, w, f in cols))


TIMES = [
    ("first chunk s", "first_chunk_s", 13, ".2f"),
    ("rest s", "rest_s", 8, ".2f"),
    ("steady traj/s", "steady_traj_per_s", 13, ".0f"),
    ("peak RSS MiB", "peak_rss_mib", 12, ".0f"),
]


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    cpus = os.cpu_count() or 1
    p.add_argument("--scenario", default="torque_free_flip")
    p.add_argument("--n", type=int, default=8192, help="N for parts 1 and 2")
    p.add_argument("--chunks", type=int, nargs="+", default=[256, 1024, 4096])
    p.add_argument(
        "--sizes",
        type=int,
        nargs=2,
        default=[8192, 32768],
        help="the two N of the memory check (part 3)",
    )
    p.add_argument(
        "--devices",
        type=int,
        default=cpus,
        help="host devices for parts 1 and 3 and the many-device run of part 2",
    )
    p.add_argument("--compare-chunk", type=int, default=1024, help="chunk of part 2")
    p.add_argument("--rss-chunk", type=int, default=1024, help="chunk of part 3")
    p.add_argument("--lanes", type=int, default=64)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--workers",
        type=int,
        default=cpus,
        help="Dask LocalCluster workers of part 4 (each max(1, devices // workers) host devices)",
    )
    p.add_argument("--parts", type=int, nargs="+", choices=[1, 2, 3, 4], default=[1, 2, 3, 4])
    p.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="subprocesses at a time (> 1 only for smoke tests: timings contend)",
    )
    p.add_argument("--out", default="results/benchmarks/sweep_scale.json")
    p.add_argument("--worker", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        cfg = json.loads(args.worker)
        row = cluster_worker(cfg) if "workers" in cfg else worker(cfg)
        pathlib.Path(cfg["result"]).write_text(json.dumps(row))
        return row

    many = max(args.devices, 2)  # part 2 compares 1 with ≥ 2 devices
    result = {
        "meta": {
            "machine": platform.platform(),
            "python": platform.python_version(),
            "cpu_count": cpus,
            "jax": version("jax"),
            "jaxlib": version("jaxlib"),
            "platform": "cpu",
            "dtype": "float64",
            "scenario": args.scenario,
            "lanes": args.lanes,
            "seed": args.seed,
            "devices": args.devices,
            "date": time.strftime("%Y-%m-%d"),
        }
    }
    # Every distinct (n, chunk, devices) runs once; only part 2's two stores are kept.
    plan = {}
    if 1 in args.parts:
        plan.update({(args.n, c, args.devices): False for c in args.chunks})
    if 3 in args.parts:
        plan.update({(n, args.rss_chunk, args.devices): False for n in args.sizes})
    pair = [(args.n, args.compare_chunk, d) for d in (1, many)]
    if 2 in args.parts:
        plan.update(dict.fromkeys(pair, True))
    # Part 4: the in-process run of part 2 on D devices beside the LocalCluster (last).
    per_worker = max(1, args.devices // args.workers)
    local = (args.n, args.compare_chunk, args.devices)
    cluster = ("dask", args.n, args.compare_chunk, args.workers, per_worker)
    if 4 in args.parts:
        plan[local] = True
        plan[cluster] = True
    runs = {}
    with tempfile.TemporaryDirectory(prefix="sweep_scale_") as tmp:

        def one(key):
            if key[0] == "dask":
                row, store = run_cluster(args, pathlib.Path(tmp), *key[1:])
            else:
                row, store = run_worker(args, pathlib.Path(tmp), *key)
            if not plan[key]:
                shutil.rmtree(store, ignore_errors=True)
            return key, row, store

        with ThreadPoolExecutor(max_workers=args.jobs) as pool:
            for key, row, store in pool.map(one, plan):
                runs[key] = (row, store)
        if 2 in args.parts:
            same = compare_stores(runs[pair[0]][1], runs[pair[1]][1])
            result["devices"] = {
                "n": args.n,
                "chunk": args.compare_chunk,
                "rows": [runs[k][0] for k in pair],
                "compared": same,
                "identical": all(same.values()),
            }
        if 4 in args.parts:
            same = compare_stores(runs[local][1], runs[cluster][1])
            a, b = runs[local][0], runs[cluster][0]
            rate_a, rate_b = a["steady_traj_per_s"], b["steady_traj_per_s"]
            empty = dict.fromkeys(("workers", "cluster_start_s", "worker_peak_rss_mib"))
            result["dask"] = {
                "n": args.n,
                "chunk": args.compare_chunk,
                "workers": args.workers,
                "devices_per_worker": per_worker,
                "rows": [{"engine": "in-process", **empty, **a}, b],
                "compared": same,
                "identical": all(same.values()),
                "ratio": rate_b / rate_a if rate_a and rate_b else None,
            }
    if 1 in args.parts:
        result["chunks"] = {
            "n": args.n,
            "devices": args.devices,
            "rows": [runs[(args.n, c, args.devices)][0] for c in args.chunks],
        }
    if 3 in args.parts:
        rows = [runs[(n, args.rss_chunk, args.devices)][0] for n in args.sizes]
        result["memory"] = {
            "chunk": args.rss_chunk,
            "devices": args.devices,
            "rows": rows,
            "peak_rss_ratio": rows[1]["peak_rss_mib"] / rows[0]["peak_rss_mib"],
            "n_ratio": rows[1]["n"] / rows[0]["n"],
        }

    if "chunks" in result:
        c = result["chunks"]
        _table(
            f"1. chunk size — {args.scenario}, N = {c['n']}, {c['devices']} devices",
            c["rows"],
            [("chunk", "chunk", 6, "d"), ("chunks", "n_chunks", 6, "d"), *TIMES],
        )
    if "devices" in result:
        d = result["devices"]
        _table(
            f"2. devices — N = {d['n']}, chunk {d['chunk']}",
            d["rows"],
            [("devices", "devices", 7, "d"), *TIMES],
        )
        r1, rd = d["rows"]
        if r1["steady_traj_per_s"] and rd["steady_traj_per_s"]:
            d["speedup"] = rd["steady_traj_per_s"] / r1["steady_traj_per_s"]
            print(f"steady speedup {rd['devices']} vs 1 device: {d['speedup']:.2f}x")
        diff = [k for k, v in d["compared"].items() if not v]
        print(
            f"identical: {d['identical']}"
            + (f" (differ: {', '.join(diff)})" if diff else f" ({', '.join(d['compared'])})")
        )
    if "memory" in result:
        m = result["memory"]
        _table(
            f"3. memory vs N — chunk {m['chunk']}, {m['devices']} devices",
            m["rows"],
            [
                ("N", "n", 7, "d"),
                ("run s", "run_s", 7, ".1f"),
                ("steady traj/s", "steady_traj_per_s", 13, ".0f"),
                ("base RSS MiB", "base_rss_mib", 12, ".0f"),
                ("peak RSS MiB", "peak_rss_mib", 12, ".0f"),
            ],
        )
        print(
            f"peak RSS ratio N={m['rows'][1]['n']} / N={m['rows'][0]['n']}: "
            f"{m['peak_rss_ratio']:.3f} (N ratio {m['n_ratio']:g})"
        )

    if "dask" in result:
        d = result["dask"]
        _table(
            f"4. in-process vs Dask LocalCluster — N = {d['n']}, chunk {d['chunk']}, "
            f"{d['workers']} workers × {d['devices_per_worker']} devices",
            d["rows"],
            [
                ("engine", "engine", 10, ""),
                ("workers", "workers", 7, "d"),
                ("devices", "devices", 7, "d"),
                ("start s", "cluster_start_s", 7, ".2f"),
                *TIMES,
                ("worker RSS MiB", "worker_peak_rss_mib", 14, ".0f"),
            ],
        )
        print(
            "(LocalCluster: first chunk = the warm-up, every worker compiling and solving "
            "one chunk at once; rest = the whole sweep after it)"
        )
        if d["ratio"] is not None:
            print(f"steady traj/s LocalCluster ÷ in-process: {d['ratio']:.2f}")
        diff = [k for k, v in d["compared"].items() if not v]
        print(
            f"identical: {d['identical']}"
            + (f" (differ: {', '.join(diff)})" if diff else f" ({', '.join(d['compared'])})")
        )

    path = pathlib.Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2))
    print(f"wrote {path}")
    return result


if __name__ == "__main__":
    main()
