"""Writing a sweep's results into its zarr store, compressor against compressor: how fast
`sweep.run` writes a chunk of solved trajectories (compression, CRC32C checksum, files) and
how many bytes a trajectory takes on disk, with the store's compressor
(`rbdyn_jax.sweep._store.COMPRESSION`) beside Blosc Zstandard at levels 5 and 1.

`sweep.run` writes a chunk while the devices solve the next one, so the slower of the two
sets a sweep's pace: on a CPU the solves, on a GPU (a chunk of 2²⁰ trajectories solved in
a fraction of a second) possibly the writes.

Data: a sweep of `--n` trajectories of `torque_free_flip` (seed 0, float64, every state
kept), solved on this machine's CPU by `sweep.run` and read back. For each compressor, a
new store of the same layout receives the same values as `sweep.run` writes a chunk
(`_store._write`), timed (median of `--repeats` writes of the same chunk, default 5):

- `none`: the `--n` trajectories without states (`trajectories="none"`: inertia, status,
  num_steps and the four summaries);
- `all`: the first `--states-n` of them with their states (omega, quat at 81 times) too.

Reported per layout and compressor: trajectories written a second, bytes a trajectory on
disk (the store's files, metadata included, over its trajectories), and both as ratios to
the store's own compressor. Every store is read back and compared with the values written,
bit for bit (the compressors are lossless).

Run: `python benchmarks/store_write.py [--n 131072] [--states-n 32768] [--repeats 5]
[--out results/benchmarks]` prints a table and writes OUT/store_write.json.
"""

import rbdyn_jax as rb  # JAX starts XLA at its first computation, after this

if __name__ == "__main__":  # a script: before JAX starts (imported by a test: as is)
    rb.configure_xla()

import argparse  # noqa: E402
import pathlib  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
import zarr  # noqa: E402

from rbdyn_jax import sweep  # noqa: E402
from rbdyn_jax.scenario import Scenario  # noqa: E402
from rbdyn_jax.sweep import _store  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import _report  # noqa: E402

SCENARIO = "torque_free_flip"
_STATES = ("omega", "quat")  # what `trajectories="none"` leaves out
COMPRESSORS = {
    "store's": dict(_store.COMPRESSION),
    "zstd 5": {"cname": "zstd", "clevel": 5},
    "zstd 1": {"cname": "zstd", "clevel": 1},
}


def solved(n: int, folder: pathlib.Path) -> dict[str, np.ndarray]:
    """Every variable `sweep.run` writes, for `n` trajectories of the scenario solved here."""
    path = sweep.run(SCENARIO, n, folder / "solved.zarr", chunk=n, trajectories="all")
    g = zarr.open_group(str(path), mode="r")
    names = ["omega", "quat", "inertia", "status", "num_steps", *Scenario.load(SCENARIO).summaries]
    return {k: g[k][:] for k in names}


def write_rate(values: dict, n: int, trajectories: str, compression: dict, folder, repeats):
    """(seconds of one write of `n` trajectories' `values` (median), bytes a trajectory on
    disk) in a new store with `compression`; the store read back equals `values`."""
    sc = Scenario.load(SCENARIO).with_settings(trajectories=trajectories)
    out = {k: v[:n] for k, v in values.items() if trajectories == "all" or k not in _STATES}
    saved = _store.COMPRESSION
    _store.COMPRESSION = compression
    try:
        loc = _store._Location.of(folder / f"{trajectories}-{compression['cname']}.zarr")
        g = _store._create_store(loc, sc, n, n, 0, 64)
    finally:
        _store.COMPRESSION = saved
    idx = np.arange(n)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        _store._write(g, idx, out, None)
        times.append(time.perf_counter() - t0)
    _store._consolidate(g)
    for k, v in out.items():
        if not np.array_equal(g[k][:], v, equal_nan=True):
            raise AssertionError(f"{k} read back differs ({compression})")
    size = sum(f.stat().st_size for f in pathlib.Path(loc.url).rglob("*") if f.is_file())
    loc.remove()
    return float(np.median(times)), size / n


def main(n=1 << 17, states_n=1 << 15, repeats=5, out="results/benchmarks"):
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = pathlib.Path(tmp)
        values = solved(max(n, states_n), folder)
        for trajectories, m in (("none", n), ("all", states_n)):
            base = None
            for label, compression in COMPRESSORS.items():
                seconds, size = write_rate(values, m, trajectories, compression, folder, repeats)
                row = {
                    "trajectories": trajectories,
                    "compressor": label,
                    "cname": compression["cname"],
                    "clevel": compression["clevel"],
                    "n": m,
                    "traj_per_s": m / seconds,
                    "bytes_per_traj": size,
                }
                base = base or row
                row["speed_ratio"] = row["traj_per_s"] / base["traj_per_s"]
                row["size_ratio"] = size / base["bytes_per_traj"]
                rows.append(row)
    print(
        f"{'states':<8}{'compressor':<22}{'n':>8}{'traj/s':>12}{'B/traj':>10}"
        f"{'speed ×':>9}{'size ×':>8}"
    )
    for r in rows:
        name = f"{r['compressor']} ({r['cname']} {r['clevel']})"
        print(
            f"{r['trajectories']:<8}{name:<22}{r['n']:>8}{r['traj_per_s']:>12.0f}"
            f"{r['bytes_per_traj']:>10.1f}{r['speed_ratio']:>9.2f}{r['size_ratio']:>8.3f}"
        )
    meta = {
        "scenario": SCENARIO,
        "n": n,
        "states_n": states_n,
        "repeats": repeats,
        "zarr": zarr.__version__,
        "compression": dict(_store.COMPRESSION),
    }
    print("wrote", _report.write_json(out, "store_write", meta, rows))
    return rows


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=1 << 17)
    p.add_argument("--states-n", type=int, default=1 << 15)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out", default="results/benchmarks")
    main(**vars(p.parse_args()))
