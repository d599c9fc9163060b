"""Explicit per-process thread counts for the native libraries.

OMP_NUM_THREADS does not limit OpenEXR, OpenImageIO or OpenCV, so each is set here, once per process
(the CLI and every dask worker call this at start-up). The per-frame stages scale with processes.
"""

from __future__ import annotations

import os
import sys

# GNU OpenMP (PyTorch's intra-op pool) spins 300,000 rounds, several ms, after every parallel region before
# its threads sleep. On a machine with as many cores as threads those spinning threads take the cores from
# whatever runs next outside OpenMP: the hash grid's numba kernels (`training/hashgrid_cpu.py`) ran 1.5x
# slower after a PyTorch op than alone (forward 20 vs 13 ms, backward 22 vs 15 ms a `fast` step, AMD EPYC VM,
# docs/benchmarks.md). 10,000 rounds still bridges the gaps between back-to-back PyTorch ops.
OPENMP_SPIN_ENV = {"GOMP_SPINCOUNT": "10000"}


def bound_openmp_spin() -> None:
    """Shorten GNU OpenMP's spin-wait unless the user set it (libgomp reads it once, when torch loads it,
    so this must run before `import torch`: the package root calls it)."""
    for key, value in OPENMP_SPIN_ENV.items():
        os.environ.setdefault(key, value)


def set_library_threads(n: int) -> None:
    """Give OpenEXR, OpenImageIO, OpenCV and PyTorch `n` threads each in this process."""
    import cv2
    import OpenEXR
    import OpenImageIO as oiio

    n = max(1, int(n))
    OpenEXR.set_global_thread_count(n)
    oiio.attribute("threads", n)
    oiio.attribute("exr_threads", n)
    cv2.setNumThreads(n)
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(n)
    else:
        # Importing torch only to set its threads cost 1.7-2.4 CPU-s in every pool worker (the simulator and
        # most preprocess tasks never use it); torch reads these at import, should a task import it later.
        os.environ["OMP_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = str(n)
