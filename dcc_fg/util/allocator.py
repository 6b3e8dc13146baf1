"""The C allocator's settings for per-frame image work: large buffers reused from the heap.

OpenCV allocates the scratch images of a call (Shi-Tomasi's eigenvalue image, Sobel derivatives, KLT
pyramids) with ``malloc`` and frees them on return. glibc serves a block above its mmap threshold
(128 KiB at start, raised only when such a block is freed) with fresh pages from the kernel and
unmaps it on ``free``, so each call faults its buffers in again, page by page; once scipy is
imported (it is, everywhere in dcc-fg) the threshold stays low. On this project's 2-core VM a
640x480 ``cv2.cornerMinEigenVal`` took 5.2 ms that way and 1.2 ms with the settings below,
``cv2.goodFeaturesToTrack`` 7.7 ms and 3.5 ms (ad-hoc timing loop, scipy imported first), and the
VIO front end's corner detection on the 60 s rendered flight 2.2-2.6 s and 1.3 s of CPU time.

:func:`reuse_large_buffers` raises the mmap threshold to 32 MiB (glibc's largest) and the trim
threshold to 64 MiB, so buffers of that size are carved from the heap and freed memory stays there
for the next frame. The price is memory the process keeps after a peak (at most the trim threshold
above what it uses; the inline VIO of the 60 s flight peaked at 256 MiB with the settings and 257 MiB
without). Process-wide; a no-op where the C library is not glibc.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

#: glibc's ``mallopt`` parameters (malloc.h)
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 32 << 20
TRIM_THRESHOLD_BYTES = 64 << 20

_done: bool | None = None


def reuse_large_buffers() -> bool:
    """Serve blocks up to 32 MiB from the heap and keep up to 64 MiB of freed heap (module docstring).

    Returns True when the settings are in effect (glibc), False elsewhere. Idempotent."""
    global _done
    if _done is not None:
        return _done
    _done = False
    if not sys.platform.startswith("linux"):
        return False
    name = ctypes.util.find_library("c") or "libc.so.6"
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl and other C libraries have no mallopt
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    _done = bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(
        mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)
    )
    return _done
