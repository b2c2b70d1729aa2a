"""What every JAX benchmark writes: its rows and the run's metadata as JSON."""

import json
import os
import pathlib
import platform
import subprocess
from importlib.metadata import version


def write_json(out: str, name: str, meta: dict, rows: list) -> pathlib.Path:
    """Write `{"meta": …, "rows": rows}` to `out/name.json` and return the path. `meta` is
    the script's own settings; the machine, its cores, JAX's devices, `XLA_FLAGS`, the
    versions of jax, diffrax and equinox, and the git revision of the code measured (where it
    runs from a git checkout) are added here."""
    import jax

    path = pathlib.Path(out)
    path.mkdir(parents=True, exist_ok=True)
    meta = {
        "machine": platform.platform(),
        "cores": os.cpu_count(),
        "devices": jax.device_count(),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        **{pkg: version(pkg) for pkg in ("jax", "diffrax", "equinox")},
        **({"revision": rev} if (rev := _revision()) else {}),
        **meta,
    }
    file = path / f"{name}.json"
    file.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    return file


def _revision() -> str | None:
    """`git describe --always --dirty` of this checkout, or `None` outside one."""
    try:
        out = subprocess.run(
            ["git", "describe", "--always", "--dirty"],
            cwd=pathlib.Path(__file__).parent,
            capture_output=True,
            text=True,
            timeout=10,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None if out.returncode == 0 else None
