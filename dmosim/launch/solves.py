"""The schedules' solves that the agents of a market in one process wait for (inprocess.py), run side by side: each in
a worker process of a pool (twice as many as the machine has cores: inprocess.py), so that they use the cores as
agents' processes do (the interpreter's lock lets threads gain little: three solves in threads ran 1.23 times as
fast as in turn).

The pool is forked once, when the first solves come that can run side by side, and kept for the run; its workers die
with this process, however it ends, and start HiGHS's threads anew (this process has solved the bids with its own).
One solve, or one core, is run in this process: forking gains nothing then, and a test of the fast tier starts no
process.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor

from microgrid_agent.agent.machine import ScheduleJob
from microgrid_agent.schedule import StochasticSchedule
from microgrid_agent.solvers.benders import dies_with
from microgrid_agent.solvers.highs import forked

Solution = tuple[StochasticSchedule, float]  # the schedule, and the CPU seconds its solve took


class Solves:
    """Runs solves, at most ``workers`` at once. A context manager: leaving it stops the pool, if one was started,
    whatever ended the run."""

    def __init__(self, workers: int):
        self.workers = workers
        self._pool: ProcessPoolExecutor | None = None

    def run(self, jobs: list[ScheduleJob]) -> Iterator[Solution]:
        """The solution of each job, in order, each as soon as it is there; the jobs run side by side in the pool
        (the CPU of its worker process) or, one alone or with one worker, one after the other here (the CPU of this
        thread). A job's error is raised where its solution would come."""
        if len(jobs) == 1 or self.workers == 1:
            return (timed(job, time.thread_time) for job in jobs)
        if self._pool is None:
            self._pool = ProcessPoolExecutor(self.workers, mp_context=mp.get_context("fork"), initializer=started,
                                             initargs=(os.getpid(),))
        futures = [self._pool.submit(timed, job, time.process_time) for job in jobs]
        return (future.result() for future in futures)

    def __enter__(self) -> Solves:
        return self

    def __exit__(self, *exc) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None


def started(market: int) -> None:
    """A worker of the pool as it starts: it dies with the market's process (``market``), and solves with HiGHS's
    threads of its own."""
    dies_with(market)
    forked()


def timed(job: ScheduleJob, cpu: Callable[[], float]) -> Solution:
    """``job``'s schedule and the CPU seconds its solve took by the clock ``cpu``."""
    before = cpu()
    schedule = job.run()
    return schedule, cpu() - before
