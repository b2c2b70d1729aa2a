"""GPU yardstick for the performance benchmarks: a hand-written CUDA kernel (numba-cuda) that
solves a batch of rigid-body trajectories, one GPU thread per trajectory, in float64 or float32.

The kernel's thread runs the numba solver of `_baselines.py` (its docstring states the
algorithm: Dormand–Prince 5(4) with FSAL, Hairer's error estimate and initial step, Shampine's
dense output at ``ts``), the same functions (`_baselines.solver_functions`) compiled for the
device, built per dtype: in float64 it takes the same steps as `_baselines.numba_solve` and
agrees with it to round-off (exactly, under numba-cuda's simulator; on a GPU, NVVM contracts
multiply–adds into FMAs, which changes the last bits); in float32 every operation is float32.
numba.cuda is imported on first use only.

State (ω, q) of 7 scalars, stages and parameters live in registers as tuples; each thread
writes y(ts[j]) of its trajectory to ``out[i, j, :7]`` and its step count and status.
"""

from __future__ import annotations

import numpy as np
from _baselines import _prepare, _split, solver_functions

__all__ = ["CudaSolver", "cuda_solve"]

cuda = None  # numba.cuda once `_import_cuda` ran: a module global, which the simulator swaps
_KERNELS: dict = {}


def _import_cuda():
    """Import numba.cuda (once). numba-cuda 0.30 references ``np.row_stack``, which NumPy 2.5
    removed: alias it to ``np.vstack`` first, where it is missing."""
    global cuda
    if cuda is None:
        if not hasattr(np, "row_stack"):
            np.row_stack = np.vstack
        from numba import cuda
    return cuda


def _kernel(dtype):
    """The CUDA batch kernel for `dtype` (built and cached on first use; compiled by numba at
    its first launch): thread i solves trajectory i of ``y0`` (N, 7) into ``out[i]`` (n, 7),
    ``steps[i]``, ``status[i]``."""
    key = np.dtype(dtype)
    if key not in _KERNELS:
        _import_cuda()
        solve_one = solver_functions(key.type, cuda.jit(device=True))["solve_one"]

        @cuda.jit
        def kernel(code, prm, y0, ts, rtol, atol, max_steps, out, steps, status):
            i = cuda.grid(1)
            if i >= y0.shape[0]:
                return
            steps[i], status[i] = solve_one(code, prm, y0[i], ts, rtol, atol, max_steps, out[i])

        _KERNELS[key] = kernel
    return _KERNELS[key]


class CudaSolver:
    """One problem (model, parameters, output times, tolerances, dtype) set up on the GPU, to
    launch over device arrays: the kernel alone can be timed, without host transfers.

        solver = CudaSolver("heavy_top", params, ts, 1e-8, 1e-8)
        y0 = cuda.to_device(np.concatenate([omega0, quat0], axis=1))  # (N, 7), solver.dtype
        out, steps, status = solver.outputs(N)
        solver(y0, out, steps, status); cuda.synchronize()

    The launch is asynchronous. `model` and `params` as for `_baselines.numba_solve`; `dtype`
    np.float64 or np.float32 (then ts, tolerances and parameters are rounded to float32);
    `threads` per block, the grid being ceil(N / threads) blocks.
    """

    def __init__(
        self,
        model: str,
        params: dict,
        ts,
        rtol: float,
        atol: float,
        dtype=np.float64,
        max_steps: int = 100_000,
        threads: int = 64,
    ):
        if np.dtype(dtype) not in (np.float64, np.float32):
            raise ValueError(f"dtype must be float64 or float32, not {np.dtype(dtype)}")
        # _prepare for its validation and casts (no initial states here)
        code, J, weight, com, eps, _, ts = _prepare(
            model, params, np.zeros((0, 3)), np.zeros((0, 4)), ts
        )
        F = np.dtype(dtype).type
        self.dtype, self.n_out, self.threads = np.dtype(dtype), ts.size, int(threads)
        self.kernel = _kernel(F)
        # numba_solve's parameter tuple: J, J⁻¹ (row-major), com, weight, eps
        self.args = (
            code,
            tuple(F(v) for v in (*J.ravel(), *np.linalg.inv(J).ravel(), *com, weight, eps)),
            cuda.to_device(ts.astype(F)),
            F(rtol),
            F(atol),
            int(max_steps),
        )

    def outputs(self, n: int):
        """Device buffers for `n` trajectories: out (n, len(ts), 7) NaN (outputs not reached
        stay NaN), steps (n,) and status (n,) int64."""
        return (
            cuda.to_device(np.full((n, self.n_out, 7), np.nan, dtype=self.dtype)),
            cuda.to_device(np.zeros(n, dtype=np.int64)),
            cuda.to_device(np.zeros(n, dtype=np.int64)),
        )

    def __call__(self, y0, out, steps, status) -> None:
        """Launch the kernel on device arrays y0 (N, 7) of `dtype` and `outputs(N)`."""
        code, prm, ts, rtol, atol, max_steps = self.args
        n = y0.shape[0]
        if n:
            blocks = (n + self.threads - 1) // self.threads
            self.kernel[blocks, self.threads](
                code, prm, y0, ts, rtol, atol, max_steps, out, steps, status
            )


def cuda_solve(
    model: str,
    params: dict,
    omega0: np.ndarray,
    quat0: np.ndarray,
    ts: np.ndarray,
    rtol: float,
    atol: float,
    max_steps: int = 100_000,
    dtype=np.float64,
    threads: int = 64,
) -> dict:
    """Solve N trajectories with the CUDA kernel, one GPU thread each (host arrays in and
    out, transfers included).

    Arguments and return layout as `_baselines.numba_solve` ({"omega": (N, n, 3), "quat":
    (N, n, 4) unit, "steps": (N,), "status": (N,) 0 ok, 1 max_steps reached, 2 step too
    small}; outputs not reached are NaN), the arrays in `dtype`. Compiles on first call.
    """
    solver = CudaSolver(model, params, ts, rtol, atol, dtype, max_steps, threads)
    y0 = _prepare(model, params, omega0, quat0, ts)[5]
    out, steps, status = solver.outputs(y0.shape[0])
    solver(cuda.to_device(y0.astype(solver.dtype)), out, steps, status)
    cuda.synchronize()
    return _split(out.copy_to_host(), steps.copy_to_host(), status.copy_to_host())
