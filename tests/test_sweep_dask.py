"""Sweeps on a Dask cluster (`sweep.run(..., client=...)`, `rbdyn sweep --scheduler/--workers`)
against the in-process run: the same bits, a worker killed mid-chunk losing nothing,
resume, summaries.

The cluster is a real `distributed.LocalCluster` of 2 worker processes (one thread each),
each a JAX process of its own: the tasks solve and write the store in those processes.
"""

import os
import signal
import threading
import time

import numpy as np
import pytest
import zarr
from helpers import assert_same_arrays as assert_same, load_store as load, small_scenario as small

from rbdyn_jax import cli, sweep
from rbdyn_jax.scenario import Scenario

distributed = pytest.importorskip("distributed")

pytestmark = pytest.mark.xdist_group("dask")  # one cluster for the module (--dist loadgroup)


@pytest.fixture(autouse=True)
def no_cache(monkeypatch):
    """`rbdyn sweep` run in this process turns on JAX's persistent compilation cache for
    the process, unless `$RBDYN_JAX_CACHE_DIR` is empty: keep it off for the other tests."""
    monkeypatch.setenv("RBDYN_JAX_CACHE_DIR", "")


@pytest.fixture(scope="module")
def client():
    with distributed.LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        dashboard_address=":0",
        env={"JAX_ENABLE_X64": "1"},
    ) as cluster:
        with distributed.Client(cluster) as c:
            yield c


N = 100


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    out = tmp_path_factory.mktemp("dask") / "ref.zarr"
    return sweep.run(Scenario.from_dict(small()), N, out, chunk=N, seed=3, lanes=16)


@pytest.mark.parametrize("chunk", [16, 40])
def test_workers_give_the_in_process_bits(client, reference, tmp_path, chunk):
    seen = []
    out = sweep.run(
        Scenario.from_dict(small()),
        N,
        tmp_path / "d.zarr",
        chunk=chunk,
        seed=3,
        lanes=16,
        client=client,
        progress=seen.append,
    )
    assert_same(load(reference), load(out))
    assert sum(p.solved_now for p in seen) == N and max(p.done for p in seen) == N
    assert len(seen) == -(-N // chunk)  # one report per task
    assert zarr.open_group(str(out), mode="r").attrs["complete"] == 1
    assert sweep.summarize(out) == sweep.summarize(reference)  # on the cluster's scheduler


def test_resume_on_the_cluster_after_an_interrupted_run(client, reference, tmp_path):
    """An in-process run stops after two chunks (as if killed); the cluster finishes it
    with another `chunk` given."""
    out = tmp_path / "r.zarr"

    def stop(p):
        if p.done >= 32:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        sweep.run(Scenario.from_dict(small()), N, out, chunk=16, seed=3, lanes=16, progress=stop)
    assert np.sum(zarr.open_group(str(out), mode="r")["status"][:] >= 0) == 32
    seen = []
    # another --chunk: the tasks keep the store's chunks (no two write one zarr chunk)
    sweep.run(
        Scenario.from_dict(small()),
        N,
        out,
        chunk=40,
        seed=3,
        lanes=16,
        resume=True,
        client=client,
        progress=seen.append,
    )
    assert sorted(p.solved_now for p in seen) == [4, 16, 16, 16, 16]  # any order
    assert_same(load(reference), load(out))


def test_cli_on_a_running_scheduler(client, reference, tmp_path, capsys):
    toml = tmp_path / "small.toml"
    toml.write_text(_toml(small()))
    out = tmp_path / "cli.zarr"
    code = cli.main(
        [
            "sweep",
            str(toml),
            "--n",
            str(N),
            "--out",
            str(out),
            "--chunk",
            "32",
            "--seed",
            "3",
            "--lanes",
            "16",
            "--scheduler",
            client.scheduler.address,
        ]
    )
    assert code == 0
    assert "as Dask tasks on 2 worker(s)" in capsys.readouterr().out
    assert_same(load(reference), load(out))


def test_cli_names_a_scheduler_it_cannot_use(tmp_path, capsys):
    """An address Dask cannot parse: one line naming it, status 2, no store."""
    out = tmp_path / "x.zarr"
    argv = ["sweep", "torque_free_flip", "--n", "4", "--out", str(out), "--scheduler", "nonsense"]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("rbdyn sweep: no Dask scheduler at nonsense:") and "Traceback" not in err
    assert not out.exists()


@pytest.mark.parametrize("keep", ["none", 8])
def test_workers_keep_the_states_asked_for(client, reference, tmp_path, keep):
    """Tasks writing a store of no states (the chunk chosen for a worker's devices: 1024 on
    its CPU), or of every 8th trajectory's (two rows of states a task, in zarr chunks of
    their own): the in-process full store's bits."""
    chunk = None if keep == "none" else 16
    out = sweep.run(
        Scenario.from_dict(small()),
        N,
        tmp_path / "k.zarr",
        chunk=chunk,
        seed=3,
        lanes=16,
        trajectories=keep,
        client=client,
    )
    assert zarr.open_group(str(out), mode="r").attrs["chunk"] == (chunk or 1024)
    ref, got = load(reference), load(out)
    names = [k for k in ref if k not in ("omega", "quat")]
    assert_same({k: ref[k] for k in names}, {k: got[k] for k in names})
    if keep == "none":
        assert "omega" not in got and "quat" not in got
    else:
        for k in ("omega", "quat"):
            assert np.array_equal(ref[k][::8], got[k], equal_nan=True), k


def test_workers_solve_a_float32_sweep_in_float32(client, tmp_path):
    """On workers with 64-bit types a float32 scenario still computes in float32, and gives
    the bits of the in-process run with 64-bit types off."""
    import jax

    sc = Scenario.from_dict(small(solver={"rtol": 1e-6, "atol": 1e-6, "dtype": "float32"}))
    with jax.enable_x64(False):
        ref = sweep.run(sc, N, tmp_path / "ref.zarr", chunk=N, seed=3, lanes=16)
    out = sweep.run(sc, N, tmp_path / "d.zarr", chunk=50, seed=3, lanes=16, client=client)
    assert_same(load(ref), load(out))
    assert zarr.open_group(str(out), mode="r")["omega"].dtype == np.float32


def test_cli_local_cluster(tmp_path, reference, capsys):
    """`--workers 2` starts its own LocalCluster of two processes; one task of `N` (one
    worker compiles): the same bits as the in-process run."""
    toml = tmp_path / "small.toml"
    toml.write_text(_toml(small()))
    out = tmp_path / "w.zarr"
    code = cli.main(
        [
            "sweep",
            str(toml),
            "--n",
            str(N),
            "--out",
            str(out),
            "--chunk",
            str(N),
            "--seed",
            "3",
            "--lanes",
            "16",
            "--workers",
            "2",
        ]
    )
    assert code == 0
    assert "as Dask tasks on 2 worker(s)" in capsys.readouterr().out
    assert_same(load(reference), load(out))


def _toml(d: dict) -> str:
    """The small scenario as TOML (its values are numbers, strings and lists)."""

    def value(v):
        if isinstance(v, str):
            return f'"{v}"'
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return repr(v)

    lines = []

    def table(prefix, t):
        scalars = {k: v for k, v in t.items() if not isinstance(v, dict)}
        if prefix:
            lines.append(f"[{prefix}]")
        lines.extend(f"{k} = {value(v)}" for k, v in scalars.items())
        for k, v in t.items():
            if isinstance(v, dict):
                table(f"{prefix}.{k}" if prefix else k, v)

    table("", d)
    return "\n".join(lines) + "\n"


def test_store_by_url_through_fsspec(client, reference, tmp_path):
    """A store given as a URL is written through fsspec (here its `file://` filesystem, the
    code path of `s3://` or `gs://`), by the workers too: the same bits, the same refusal
    of an existing store, and every reader takes the URL."""
    url = (tmp_path / "u.zarr").as_uri()
    out = sweep.run(Scenario.from_dict(small()), N, url, chunk=32, seed=3, lanes=16, client=client)
    assert out == url
    assert_same(load(reference), load(tmp_path / "u.zarr"))
    with pytest.raises(FileExistsError, match="--overwrite"):
        sweep.run(Scenario.from_dict(small()), N, url, chunk=32, seed=3, lanes=16)
    assert sweep.summarize(url) == sweep.summarize(reference)
    assert sweep.open_dataset(url).sizes["trajectory"] == N
    sweep.to_netcdf(url, tmp_path / "u.nc")
    sweep.run(Scenario.from_dict(small()), N, url, chunk=32, seed=3, lanes=16, overwrite=True)
    assert_same(load(reference), load(tmp_path / "u.zarr"))


def _executing(dask_worker) -> int:
    return len(dask_worker.state.executing)


# Last of the tests on the shared cluster (pytest runs a file in order): the worker its
# nanny starts in place of the killed one compiles every program anew.
def test_worker_killed_mid_chunk_loses_nothing(client, tmp_path):
    """A worker process is killed (SIGKILL) while it solves a chunk, after other chunks
    are written: Dask reruns its chunk, and the store equals the in-process run with every
    trajectory counted once."""
    d = small(time={"t1": 150.0, "n": 5}, outputs={"summaries": ["energy_drift"]})
    sc = Scenario.from_dict(d)
    n, chunk = 384, 32
    out = tmp_path / "killed.zarr"
    seen, result = [], {}
    run = threading.Thread(
        target=lambda: result.update(
            path=sweep.run(
                sc, n, out, chunk=chunk, seed=5, lanes=16, client=client, progress=seen.append
            )
        )
    )
    pids = client.run(os.getpid)
    run.start()
    killed = None
    deadline = time.time() + 240
    while run.is_alive() and time.time() < deadline and killed is None:
        time.sleep(0.01)
        try:
            done = int(np.sum(zarr.open_group(str(out), mode="r")["status"][:] >= 0))
        except Exception:  # the store is not created yet
            continue
        if done < chunk:
            continue
        for address, busy in client.run(_executing).items():
            if busy and address in pids:
                os.kill(pids[address], signal.SIGKILL)
                killed = (address, done)
                break
    run.join(timeout=300)
    assert killed is not None and killed[1] < n, "no worker was killed mid-run"
    assert not run.is_alive() and result["path"] == out.absolute()
    assert sum(p.solved_now for p in seen) == n and seen[-1].done == n
    ref = sweep.run(sc, n, tmp_path / "ref.zarr", chunk=n, seed=5, lanes=16)
    names = ("omega", "quat", "inertia", "status", "num_steps", "energy_drift")
    assert_same(load(ref, names), load(out, names))
    assert killed[0] not in client.run(os.getpid)  # that worker is gone (its nanny restarts one)


def test_workers_without_64_bit_types_are_refused_before_any_task(tmp_path):
    """rbdyn_jax never switches `jax_enable_x64` on: a float64 sweep on workers started
    without it is refused before a task is sent (nothing solved, no store written), naming
    the setting and the workers; the task itself refuses too, and changes no setting."""
    import jax

    with distributed.LocalCluster(
        n_workers=1,
        threads_per_worker=1,
        processes=True,
        dashboard_address=":0",
        env={"JAX_ENABLE_X64": "0"},
    ) as cluster:
        with distributed.Client(cluster) as c:
            assert list(c.run(lambda: jax.config.jax_enable_x64).values()) == [False]
            with pytest.raises(ValueError, match=r"1 of 1 lack them.*JAX_ENABLE_X64=1"):
                sweep.run(Scenario.from_dict(small()), N, tmp_path / "d.zarr", client=c)
            assert not (tmp_path / "d.zarr").exists()
            with pytest.raises(ValueError, match="float64 sweep needs 64-bit types"):
                c.submit(
                    sweep.solve_chunk,
                    str(tmp_path / "d.zarr"),
                    small(),
                    "small",
                    0,
                    N,
                    seed=3,
                    lanes=16,
                    chunk=N,
                ).result()
            assert list(c.run(lambda: jax.config.jax_enable_x64).values()) == [False]
