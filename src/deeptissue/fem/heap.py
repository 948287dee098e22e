"""Keep the memory a solve frees for its next allocation, instead of handing it back to the kernel.

glibc's malloc serves a large request by mmap and gives it back to the kernel with munmap when it is freed. A
Newton iteration on a limb allocates its temporaries afresh (the element blocks of the tangent alone are 66 MB
at 45 k dofs), so every iteration has the kernel find and zero hundreds of MB of pages again: on a virtual
machine whose host reclaims freed memory that is slow (docs/performance.md, "Where a solve's time goes").
:func:`keep_freed_memory` makes this process serve every request from its heap and keep what it frees.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging

__all__ = ["keep_freed_memory"]

_log = logging.getLogger(__name__)

# mallopt parameters (glibc malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
_KEPT = False


def keep_freed_memory() -> bool:
    """Make glibc's malloc serve every request from the heap (no mmap) and never give freed memory back to the
    kernel, for the rest of this process. Returns whether that is in effect (False where the C library has no
    ``mallopt``, e.g. not glibc: the solve is then only slower). Idempotent."""
    global _KEPT
    if _KEPT:
        return True
    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").mallopt
    except (OSError, AttributeError):
        _log.debug("no mallopt in the C library: freed memory goes back to the kernel")
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    _KEPT = mallopt(_M_MMAP_MAX, 0) == 1 and mallopt(_M_TRIM_THRESHOLD, 2**31 - 1) == 1
    return _KEPT
