"""The test command itself: `pytest -n 2 --dist loadgroup` keeps each `xdist_group` on
one worker (the dask tests' one cluster, the CUDA simulator's one run, each computed once
per session and not once per worker)."""

import re
import subprocess
import sys
import textwrap

GROUPED = textwrap.dedent("""
    import pytest

    @pytest.mark.xdist_group("together")
    @pytest.mark.parametrize("i", range(4))
    def test_grouped(i):
        pass

    @pytest.mark.parametrize("i", range(4))
    def test_free(i):
        pass
""")


def test_an_xdist_group_runs_on_one_worker(tmp_path):
    (tmp_path / "test_grouped.py").write_text(GROUPED)
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "-v",
            "-n",
            "2",
            "--dist",
            "loadgroup",
            "-p",
            "no:cacheprovider",
            "test_grouped.py",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    workers = re.findall(r"\[(gw\d)\].*PASSED test_grouped\.py::test_grouped\[\d\]", run.stdout)
    assert len(workers) == 4, run.stdout[-3000:]
    assert len(set(workers)) == 1, (
        "pytest-xdist's loadgroup spread a group over the workers (with pytest 9.2 it can no "
        "longer mark the group in the test ids, pytest-dev/pytest-xdist#1386): "
        f"{workers}"
    )
