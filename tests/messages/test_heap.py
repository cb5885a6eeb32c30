"""What a process has freed goes back to the operating system when it asks (messages/transport/heap.py), measured
on a real process: the C heap keeps freed blocks that live ones pin in place, resident, until then."""

from __future__ import annotations

import json
import platform
import subprocess
import sys

import pytest

from dmosim.launch.processes import role_env

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


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc's malloc_trim")
def test_memory_freed_among_live_blocks_goes_back_to_the_os_when_asked():
    out = subprocess.run([sys.executable, "-c", HOLES], capture_output=True, text=True, timeout=120, env=role_env(),
                         check=True)
    measured = json.loads(out.stdout)
    assert measured["trimmed"]
    assert measured["freed"] - measured["after"] > 40, measured  # of the 63 MiB freed
