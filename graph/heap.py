"""Handing freed heap memory back to the operating system (glibc's malloc_trim).

A landmark removal or a keyframe thinning builds dense blocks of a few MiB (the Schur
complement's QR, iSAM2's re-eliminated root clique) and frees them within the frame.
glibc keeps freed memory resident: it returns to the OS only what lies at the top of
its heap, so a free region between live allocations stays in the RSS until a later
allocation happens to reuse it. Over a lifelong run such regions accumulate as the
heap's layout shifts (a ~10 MiB step of the steady RSS at frame ~15 500 of the
20 000-frame simulation, README "Lifelong"). ``malloc_trim(0)`` walks the free lists
and releases every whole free page (``MADV_DONTNEED``) wherever it lies; the memory
stays mapped and is faulted back in, zeroed, when reused. It changes no allocation,
so the computation is the same, bit for bit.

Where the C library has no ``malloc_trim`` (musl, macOS), `release_free_heap` does
nothing and says so.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
from collections.abc import Callable
from functools import cache

log = logging.getLogger(__name__)


@cache
def _malloc_trim() -> Callable[[int], int] | None:
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        trim = libc.malloc_trim
    except (OSError, AttributeError, TypeError):
        log.info("no malloc_trim in the C library (%s): freed heap stays resident", name)
        return None
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    return trim


def heap_release_available() -> bool:
    """Whether `release_free_heap` can do anything here (glibc)."""
    return _malloc_trim() is not None


def release_free_heap() -> bool:
    """Return the heap's free pages to the OS (glibc ``malloc_trim(0)``; ~0.2-0.3 ms on
    the lifelong map's ~150 MiB heap). True if some memory was released; False if none
    was or the C library cannot."""
    trim = _malloc_trim()
    return bool(trim(0)) if trim is not None else False
