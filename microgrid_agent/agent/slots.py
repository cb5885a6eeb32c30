"""How many agents forked from one host (``dmosim run --hosting fork``) handle a message at once: as many as the
machine has cores, the others waiting their turn.

Their work is CPU-bound (building and solving models), so a machine gains nothing from more at once; what it loses
is the DMO's and the routers' share of the cores. With 200 agents all solving on 2 cores, the DMO answered so late
that the agents sent again and again, and Zenoh sessions whose keep-alives waited behind them lapsed
(docs/benchmarks.md, "fleet").

The turns are the units of a System V semaphore the host makes before it forks. An agent takes one with
``SEM_UNDO``, so the kernel gives it back when the agent's process dies (an agent killed mid-solve by a fault takes
no turn with it), and a turn given back goes to an agent waiting for any turn: with a lock per turn, each agent
waiting on the lock its name hashed to, a turn stood free while agents waited on the other in 5% of a 40-agent day.
The semaphore goes when the host exits (a host killed with SIGKILL leaves it behind: ``ipcs -s`` lists it,
``ipcrm`` removes it). Without a host (agents as processes), nothing is waited for.

A process holds one turn at a time: the agents sharing it (``--per-process``) run their Python one at a time under
its interpreter lock, so two of them holding both turns would leave a core idle. Agents of a process arrive together
(a grid state reaches them all at once), and a semaphore hands turns out in the order they were asked for: without
this, 50 agents ten to a process kept 1.5 of the 2 cores busy.
"""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import errno
import os
import threading
from collections.abc import Iterator

_LIBC = ctypes.CDLL(None, use_errno=True)  # a call through it releases the GIL: a waiting agent holds no other back
_IPC_PRIVATE, _IPC_CREAT, _IPC_RMID, _GETVAL, _SETVAL, _SEM_UNDO = 0, 0o1000, 0, 12, 16, 0x1000  # <sys/sem.h>
_semaphore: list[int] = []  # the host's semaphore id, inherited by the agents it forks; none: no limit
_in_this_process = [threading.Lock()]  # held by the agent of this process that holds or waits for a turn


def _forked() -> None:
    _in_this_process[0] = threading.Lock()  # a new process: none of its agents computes yet


os.register_at_fork(after_in_child=_forked)


class _SemBuf(ctypes.Structure):
    _fields_ = [("sem_num", ctypes.c_ushort), ("sem_op", ctypes.c_short), ("sem_flg", ctypes.c_short)]


def before_forks() -> None:
    """In the agents' host, once its imports are done (dmosim.launch.host): the agents forked from it take turns,
    as many at once as the machine has cores. The semaphore goes when the host exits."""
    semaphore = _checked(_LIBC.semget(_IPC_PRIVATE, 1, _IPC_CREAT | 0o600))
    _checked(_LIBC.semctl(semaphore, 0, _SETVAL, ctypes.c_int(os.cpu_count() or 1)))
    host = os.getpid()  # a forked child inherits the registration, and must not remove the semaphore
    atexit.register(lambda: os.getpid() == host and _LIBC.semctl(semaphore, 0, _IPC_RMID))
    _semaphore[:] = [semaphore]


def free_turns() -> int | None:
    """How many turns no agent holds now; None without a host."""
    return _checked(_LIBC.semctl(_semaphore[0], 0, _GETVAL)) if _semaphore else None


@contextlib.contextmanager
def computing() -> Iterator[None]:
    """Hold a turn while handling a message: the first one free, waiting if none is or if another agent of this
    process holds one."""
    if not _semaphore:
        yield
        return
    with _in_this_process[0]:
        _change(-1)
        try:
            yield
        finally:
            _change(+1)


def _change(by: int) -> None:
    op = _SemBuf(0, by, _SEM_UNDO)
    while _LIBC.semop(_semaphore[0], ctypes.byref(op), 1) != 0:
        if ctypes.get_errno() != errno.EINTR:  # EINTR: a signal was handled while it waited, and it waits on
            raise _error()


def _checked(result: int) -> int:
    if result < 0:
        raise _error()
    return result


def _error() -> OSError:
    code = ctypes.get_errno()
    return OSError(code, f"the agents' turns (System V semaphore): {os.strerror(code)}")
