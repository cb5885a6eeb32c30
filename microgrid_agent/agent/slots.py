"""How many agents forked from one host (``dmosim run --hosting fork``) handle a message at once: as many as the
machine has cores, the others waiting their turn.

Their work is CPU-bound (building and solving models), so a machine gains nothing from more at once; what it loses
is the DMO's and the routers' share of the cores. With 200 agents all solving on 2 cores, the DMO answered so late
that the agents sent again and again, and Zenoh sessions whose keep-alives waited behind them lapsed
(docs/benchmarks.md, "fleet"). A slot is a lock on a file, ``flock``: the kernel gives it back when its holder dies,
so an agent killed mid-solve (a fault) takes no slot with it.
"""

from __future__ import annotations

import atexit
import contextlib
import fcntl
import os
import shutil
import tempfile
import zlib
from collections.abc import Iterator

_paths: list[str] = []  # one file per slot, made by the host before it forks; none: no limit


def before_forks() -> None:
    """In the agents' host, once its imports are done (dmosim.launch.host): the agents forked from it take turns in
    as many slots as the machine has cores. The files go when the host exits."""
    directory = tempfile.mkdtemp(prefix="dmosim-slots-")
    _paths[:] = [os.path.join(directory, str(i)) for i in range(os.cpu_count() or 1)]
    for path in _paths:
        open(path, "w").close()
    host = os.getpid()  # a forked child inherits the registration, and must not remove the files
    atexit.register(lambda: os.getpid() == host and shutil.rmtree(directory, ignore_errors=True))


@contextlib.contextmanager
def computing(agent: str) -> Iterator[None]:
    """Hold a slot while handling a message: a free one if there is, else wait for the agent's own (by the hash of
    its id). Without a host's slots, nothing is waited for."""
    if not _paths:
        yield
        return
    fds = [os.open(path, os.O_RDWR) for path in _paths]
    held = None
    try:
        for fd in fds:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                continue
            held = fd
            break
        if held is None:
            held = fds[zlib.crc32(agent.encode()) % len(fds)]
            fcntl.flock(held, fcntl.LOCK_EX)  # waits without the GIL
        yield
    finally:
        for fd in fds:
            os.close(fd)  # which releases the slot held
