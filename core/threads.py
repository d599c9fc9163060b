"""Explicit per-process thread counts for the native libraries.

OMP_NUM_THREADS does not limit OpenEXR, OpenImageIO or OpenCV, so each is set here, once per process
(the CLI and every dask worker call this at start-up). The per-frame stages scale with processes.
"""

from __future__ import annotations

import os
import sys


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
