"""Explicit per-process thread counts for the native libraries.

OMP_NUM_THREADS does not limit OpenEXR, OpenImageIO or OpenCV, so each is set here, once per process
(the CLI and every dask worker call this at start-up). The per-frame stages scale with processes.
"""

from __future__ import annotations


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
    try:
        import torch

        torch.set_num_threads(n)
    except ImportError:  # torch is a dependency, but thread control must not require it
        pass
