"""What the `rbdyn` commands share: their exit statuses, JAX's persistent compilation cache,
and the message of a user-caused error."""

import os

EXIT_USAGE = 2  # a usage error, an invalid scenario or data, a path that cannot be written
EXIT_SOME_FAILED = 3  # `rbdyn sweep`: some trajectories failed (the rest are written)
EXIT_ALL_FAILED = 4  # `rbdyn sweep`: every trajectory failed
EXIT_DAMAGED = 5  # a store with missing or damaged chunks (`rbdyn verify` lists them)
EXIT_NOT_CONVERGED = 6  # `rbdyn fit`: the fit did not converge (its files are written)
EXIT_INCOMPLETE = 7  # `rbdyn verify`: a whole store with trajectories not solved yet
EXIT_INTERRUPTED = 130  # Ctrl-C (128 + SIGINT)


def cache_dir() -> str:
    """`$RBDYN_JAX_CACHE_DIR`, default `~/.cache/rbdyn_jax/xla`; empty: no cache."""
    return os.environ.get(
        "RBDYN_JAX_CACHE_DIR", os.path.join(os.path.expanduser("~"), ".cache", "rbdyn_jax", "xla")
    )


def compilation_cache(jax) -> None:
    """JAX's persistent compilation cache in `cache_dir()`, so a repeated sweep or fit skips
    tracing and compiling its program (rbdyn_jax stores the traced program beside it)."""
    path = cache_dir()
    if path:
        jax.config.update("jax_compilation_cache_dir", path)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


def error_text(e: Exception, path: str) -> str:
    """The message of a user-caused error: an OS error on `path` as `cannot write PATH:
    reason`, any other as it is."""
    if isinstance(e, OSError) and e.errno is not None:
        import pathlib

        folder = pathlib.Path(path).parent
        if not folder.is_dir():  # some writers (netCDF's) report it as a permission
            return f"cannot write {path}: no folder {folder}"
        return f"cannot write {path}: {e.strerror}"
    return str(e)
