"""What every JAX benchmark writes: its rows and the run's metadata as JSON."""

import json
import os
import pathlib
import platform
from importlib.metadata import version


def write_json(out: str, name: str, meta: dict, rows: list) -> pathlib.Path:
    """Write `{"meta": …, "rows": rows}` to `out/name.json` and return the path. `meta` is
    the script's own settings; the machine, its cores, JAX's devices, `XLA_FLAGS` and the
    versions of jax, diffrax and equinox are added here."""
    import jax

    path = pathlib.Path(out)
    path.mkdir(parents=True, exist_ok=True)
    meta = {
        "machine": platform.platform(),
        "cores": os.cpu_count(),
        "devices": jax.device_count(),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        **{pkg: version(pkg) for pkg in ("jax", "diffrax", "equinox")},
        **meta,
    }
    file = path / f"{name}.json"
    file.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    return file
