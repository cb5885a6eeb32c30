"""What a process has freed goes back to the operating system when it asks, and its threads share few arenas
(messages/transport/heap.py), measured on real processes: the C heap keeps freed blocks that live ones pin in place,
resident, until then, and gives each new thread an arena of its own up to eight per core."""

from __future__ import annotations

import json
import platform
import subprocess
import sys

import pytest

from dmosim.launch.processes import role_env
from messages.transport.heap import ARENAS

pytestmark = pytest.mark.slow  # each measure is of a fresh process: its arenas and its heap from the start

HOLES = r'''
import json
from messages.transport.heap import return_free_memory

def resident_mib():
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith("RssAnon:")) / 1024

size = 2048  # a variable: a constant's product would be folded into one object
blocks = [b"x" * size for _ in range(32_768)]  # 64 MiB of the C heap, in blocks too big for Python's own allocator
pinned = blocks[::64]  # one block in 64 stays: what is freed around it cannot go back by itself
del blocks
freed = resident_mib()
print(json.dumps({"trimmed": return_free_memory(), "freed": freed, "after": resident_mib()}))
'''


THREADS = r'''
import ctypes, sys, threading
from messages.transport.heap import limit_arenas

if sys.argv[1] == "limit":
    limit_arenas()
start, hold = threading.Barrier(9), []

def allocate():
    start.wait()  # all at once, each from its own thread
    hold.append([b"x" * 4096 for _ in range(64)])

threads = [threading.Thread(target=allocate) for _ in range(8)]
for t in threads:
    t.start()
start.wait()
for t in threads:
    t.join()
ctypes.CDLL(None).malloc_stats()  # one "Arena N:" paragraph per arena, on stderr
'''

GLIBC = pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc",
                           reason="glibc's malloc_trim and mallopt")


def arenas(how: str, **env) -> int:
    out = subprocess.run([sys.executable, "-c", THREADS, how], capture_output=True, text=True, timeout=120,
                         env={**role_env(), **env}, check=True)
    return sum(line.startswith("Arena ") for line in out.stderr.splitlines())


@GLIBC
def test_threads_of_a_process_share_at_most_its_arenas_unless_the_environment_says_otherwise():
    assert arenas("default") > ARENAS  # glibc's own rule: a new arena for each new thread, up to 8 per core
    assert arenas("limit") == ARENAS
    assert arenas("limit", MALLOC_ARENA_MAX="3") == 3  # the user's setting stands


@GLIBC
def test_memory_freed_among_live_blocks_goes_back_to_the_os_when_asked():
    out = subprocess.run([sys.executable, "-c", HOLES], capture_output=True, text=True, timeout=120, env=role_env(),
                         check=True)
    measured = json.loads(out.stdout)
    assert measured["trimmed"]
    assert measured["freed"] - measured["after"] > 40, measured  # of the 63 MiB freed
