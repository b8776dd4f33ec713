"""
Imported by ``simulate``'s forkserver: load every simulator kernel before any worker starts.

The workers are forked from the forkserver, so they start with the kernels in memory
instead of each loading them from numba's cache (~0.5 s of CPU a worker) or, on a cold
cache, each compiling them (~45 s a worker, all at once). A failure here is left to the
workers to meet and report: the forkserver must keep serving.
"""

from softshape_ros.sim.warmup import compile_kernels

try:
    compile_kernels()
except Exception:      # noqa: BLE001 (the workers repeat the call and raise it properly)
    pass
