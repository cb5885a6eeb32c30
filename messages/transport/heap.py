"""How a long-lived process of a run keeps its C heap from growing with the days: few allocation arenas, and what a
piece of work freed (an agent's schedule, a day of the DMO's or of the recording) given back to the operating system
at its end.

glibc's allocator gives each thread that allocates while another holds an arena an arena of its own, up to eight per
core, and keeps freed memory in each for reuse, returning only what lies at the top. A process with many threads
(an agent's Zenoh session has about nine; ten agents sharing a process, ninety) then spreads each day's solves
(cvxpy, HiGHS) over a dozen arenas, and the free holes they leave below live data made its resident memory grow day
after day though what it used did not (docs/benchmarks.md, "week"). ``limit_arenas`` caps the arenas at
``ARENAS`` before the process's threads start; ``return_free_memory`` (``malloc_trim(0)``) hands every free page
back. Elsewhere (musl, macOS) there are no such calls and both do nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

ARENAS = 2  # glibc arenas per process: 40 agents ten to a process grew 2.8-5% in 5 days with 2, 5-11% with the default
_M_ARENA_MAX = -8  # mallopt's parameter number, glibc's malloc.h

try:
    _LIBC = ctypes.CDLL(ctypes.util.find_library("c"))
    _MALLOC_TRIM, _MALLOPT = _LIBC.malloc_trim, _LIBC.mallopt
except (OSError, AttributeError):  # not glibc
    _MALLOC_TRIM = _MALLOPT = None


def limit_arenas() -> bool:
    """Allocate from at most ``ARENAS`` arenas from now on (call before the process starts its threads), unless the
    environment's ``MALLOC_ARENA_MAX`` already says how many; whether this platform can (glibc)."""
    if _MALLOPT is None:
        return False
    if "MALLOC_ARENA_MAX" not in os.environ:
        _MALLOPT(_M_ARENA_MAX, ARENAS)
    return True


def return_free_memory() -> bool:
    """Give the OS back the pages the C heap holds free; whether this platform can (glibc)."""
    if _MALLOC_TRIM is None:
        return False
    _MALLOC_TRIM(0)
    return True
