"""Process-level memory settings (called once, at the start of a command or a worker)."""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

#: glibc's ``mallopt`` parameter for the number of malloc arenas (``M_ARENA_MAX``, malloc.h)
M_ARENA_MAX = -8


def one_malloc_arena() -> bool:
    """Make glibc serve every thread from one malloc arena (what ``MALLOC_ARENA_MAX=1``
    does), before any worker thread starts.  With an arena per thread, memory a decode or
    alignment thread frees stays in its arena and adds to the peak; one arena costs no
    speed, since the frames are large arrays and the threads allocate little else.  Returns
    whether it was set (False off glibc, or when the user set ``MALLOC_ARENA_MAX`` already)."""
    if not sys.platform.startswith("linux") or "MALLOC_ARENA_MAX" in os.environ:
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return bool(libc.mallopt(M_ARENA_MAX, 1))
    except (OSError, AttributeError):
        return False


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation without swapping (Linux's
    ``MemAvailable``; else the physical memory), or None when unknown."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return None
