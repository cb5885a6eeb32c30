"""What a long-lived process of a run has freed, given back to the operating system at the end of a piece of work
(an agent's schedule, a day of the DMO's or of the recording), so that its resident memory does not creep up with
the days.

glibc's allocator keeps freed memory in its arenas (one per thread that allocated, up to eight per core) for reuse,
and returns only what lies at the top of an arena. A day's solves (cvxpy, HiGHS) or a day's chunks of recording
leave free holes below live data, so a process's resident memory grew each day towards the largest day so far,
though what it used did not (docs/benchmarks.md, "week"). ``malloc_trim(0)`` hands every free page back. Elsewhere
(musl, macOS) there is no such call and this does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util

try:
    _MALLOC_TRIM = ctypes.CDLL(ctypes.util.find_library("c")).malloc_trim
except (OSError, AttributeError):  # not glibc
    _MALLOC_TRIM = None


def return_free_memory() -> bool:
    """Give the OS back the pages the C heap holds free; whether this platform can (glibc)."""
    if _MALLOC_TRIM is None:
        return False
    _MALLOC_TRIM(0)
    return True
