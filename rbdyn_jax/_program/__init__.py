"""The compile layer: how rbdyn_jax's functions become compiled programs, beside the physics.

- `program`: `Program`, the one way in: a function compiled once per input structure,
  traced with its checks as NaN where its inputs were validated before tracing, and then
  stored by the cache of traced programs.
- `checks`: runtime checks as NaN while a program is traced, under one lock.
- `traces`: the on-disk cache of traced programs, beside JAX's persistent compilation cache.
- `devices`: the one mesh of local devices, and the one way a batch is split over it;
- `xla`: the jit policy: XLA's compiler options, passed by the outermost `jit` only;
  `nested_filter_jit` for the functions a program traces once and calls several times.
- `flags`: XLA's process-wide flags (devices, loops), set by `import rbdyn_jax` before JAX
  starts: the only settings the package changes, and only on import.

This `__init__` imports nothing, so that `import rbdyn_jax` (which reads `flags`) imports no
JAX; import from the modules.
"""
