"""A market run in one Python process: the DMO's machine, every agent's machine and the recorder, with no network
and on the logical clock (docs/experiments.md, "In one process").

The driver is the network. What a role sends is stamped as a bus stamps it (messages/stamping.py), encoded, filed
in the recording, and handed to the roles that would receive it on its key, in the order it was sent: the DMO's
messages to the agents they are for, the agents' to the DMO. An agent whose machine asks for its schedule's solve
(``Solve``) waits for it while the others go on; when nothing more can happen without a solve's result, the solves
waited for run side by side, in worker processes (solves.py), and their results go in in the agents' name order.
Nothing is lost, so nothing is sent again; an agent whose machine is done leaves (the DMO sees its presence go), and
one that fails ends the run with its error. A phase ends when every agent has answered, so the run settles as a run
of processes on the logical clock does, only faster: no process but the solves' workers starts, imports or waits on
another.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import math
import os
import sys
import secrets
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from dmo.operator.actions import CheckPresence, Journaled, OpenWindow, Publish, Realised, Settled, Stop, Wait
from dmo.operator.config import DayConfig
from dmo.operator.events import Dropped, Left, Present, Received, TimedOut
from dmo.operator.finished import FinishedDays
from dmo.operator.machine import DmoMachine
from dmo.operator.report import DmoReport
from dmo.operator.results import RunResult
from messages import DMO, Clock, Keys, decode, sha256
from messages.recording import RecordingWriter, read_attachments
from messages.schemas import HandlingTime, MessageCounts, Receipt
from messages.stamping import Sender
from microgrid_agent.agent.delivery import RefusedPayload
from microgrid_agent.agent.machine import (AgentMachine, AskStatement, AwaitReceipts, Handled, NoStatement, Send, Solve,
                                           Solved)
from scenarios.fleet import FleetMember, member_case

from ..experiment.spec import Experiment
from .roles import agent_config, day_config, strategy_of
from .solves import Solves

log = logging.getLogger("dmosim")

# the kinds of the DMO's messages that go to every agent, and those that go to the agent they name; the others
# (rejections, network hours) to nobody but the recording, and receipts to the agent's delivery
TO_EVERY_AGENT = ("clock", "call_for_bids", "grid_state", "day_summary")
TO_ITS_AGENT = ("award", "settlement_statement")


# Solves a core runs side by side. Solves differ in length (the default day's three: 15, 33 and 32 CPU seconds), so
# with as many workers as cores the last to start waits for the first to end: on 2 cores that day scheduled in 47.5 s
# with 2 workers and 41-42 s with 3, as 3 processes do. An agent has one solve out at most.
WORKERS_PER_CORE = 2


class AgentFailed(RuntimeError):
    """An agent's machine, or its solve, raised: the run stops, naming it."""


@dataclass
class _Handling:
    """A message an agent's machine handles: when it was handed in, the CPU seconds its handling has taken so far, and
    the actions so far (a ``Solve`` last while the agent waits for the solve)."""

    msg: object
    started_at: int  # ns since the epoch
    started: float  # perf_counter
    cpu_s: float
    actions: list

    def waits(self) -> bool:
        return bool(self.actions) and isinstance(self.actions[-1], Solve)


@dataclass
class _Agent:
    """One agent's machine and what the driver keeps of it: its numbering, its inbox, its counts and the message it
    handles while it waits for a solve."""

    machine: AgentMachine
    sender: Sender
    inbox: collections.deque = field(default_factory=collections.deque)
    joined: bool = False
    left: bool = False
    received: int = 0
    pending: dict[str, tuple[str, int]] = field(default_factory=dict)  # sha256 -> (kind, seq), until receipted
    solving: _Handling | None = None  # the message whose handling waits for its solve


class InProcessMarket:
    """The run's roles in this process. ``agents`` maps each agent to its machine (made, not joined: it joins when
    the DMO's first clock comes); ``writer`` is the recording's, started (None: no recording). ``on_clock`` is
    called with each clock message the DMO sends."""

    def __init__(self, config: DayConfig, run_id: str, agents: dict[str, AgentMachine],
                 writer: RecordingWriter | None = None, on_clock: Callable[[Clock], None] | None = None):
        self.config, self.keys, self.writer = config, Keys(run_id), writer
        self.on_clock = on_clock or (lambda clock: None)
        incarnation = time.time_ns()
        self.dmo = DmoMachine(config, secrets.token_hex(16))
        token = self.dmo.state.run_token
        self._dmo = Sender(self.keys, DMO, incarnation, token)
        self.agents = {name: _Agent(machine, Sender(self.keys, name, incarnation + 1 + i, token))
                       for i, (name, machine) in enumerate(sorted(agents.items()))}
        self._to_dmo: collections.deque = collections.deque()
        self._latest: dict[str, object] = {}  # the DMO's latest message on each key (what an agent may ask for)
        cores = os.cpu_count() or 1  # one core: every solve here, no pool
        self._solves = Solves(min(cores if cores == 1 else WORKERS_PER_CORE * cores, len(self.agents)))

    def run(self) -> RunResult:
        """The run's days, to the DMO's ``Stop``; its result as a DMO process gives it."""
        finished = FinishedDays()
        with self._solves:
            actions = self.dmo.start(time.monotonic())
            while True:
                *done, request = actions
                for action in done:
                    if isinstance(action, Publish):
                        self._from_dmo(action.msg)
                    elif isinstance(action, Realised):
                        finished.realised(action.msg)
                    elif isinstance(action, Settled):
                        finished.day(action.report)
                    elif not isinstance(action, Journaled):  # nothing to resume: the run is this process
                        raise TypeError(f"the in-process market cannot do {action!r}")
                if isinstance(request, Stop):
                    break
                actions = self.dmo.handle(self._answer(request), time.monotonic())
        days, realised = finished.read()
        return RunResult(days, self.config.rule.label, sorted(self.dmo.state.registered), realised, self.dmo.last)

    def transport(self) -> dict:
        """What went through the driver, as a bus's counts (``dmosim run --json``: ``transport``)."""
        return {"published": self._dmo.seq, "received": sum(a.sender.seq for a in self.agents.values()),
                "in_process": True}

    # --- the DMO's side --------------------------------------------------------------------------------------

    def _answer(self, request):
        """The event that answers the DMO machine's request."""
        if isinstance(request, OpenWindow):
            return Dropped({})  # an agent of this process is trusted with no budget
        if isinstance(request, CheckPresence):
            return Present(frozenset(n for n in request.names if n in self.agents and not self.agents[n].left))
        if not isinstance(request, Wait):
            raise TypeError(f"the in-process market cannot answer {request!r}")
        while not self._to_dmo:
            if request.until == -math.inf or not self._step():
                break
        if self._to_dmo:
            return self._to_dmo.popleft()
        if request.until == -math.inf:
            return TimedOut()
        raise RuntimeError(f"the market stalled: the DMO waits for {request.what} from {', '.join(request.waiting)}, "
                           "and no agent has anything to do")

    def _from_dmo(self, msg) -> None:
        key, payload, stamped = self._dmo.stamp(msg, None, time.time_ns())
        self._record(key, payload)
        self._latest[key] = stamped
        if isinstance(stamped, Clock):
            self.on_clock(stamped)
        if stamped.kind in TO_EVERY_AGENT:
            for agent in self.agents.values():
                agent.inbox.append(stamped)
        elif isinstance(stamped, Receipt):
            self._receipt(stamped)
        elif stamped.kind in TO_ITS_AGENT and stamped.agent in self.agents:
            self.agents[stamped.agent].inbox.append(stamped)

    def _receipt(self, receipt: Receipt) -> None:
        agent = self.agents.get(receipt.agent)
        if agent is None:
            return
        kind_seq = agent.pending.pop(receipt.payload_sha256, None)
        if kind_seq is not None and not receipt.accepted:
            agent.inbox.append(RefusedPayload(receipt, *kind_seq))

    # --- the agents' side ------------------------------------------------------------------------------------

    def _step(self) -> bool:
        """Hand the oldest message of the first agent (in name order) that has one, and waits for no solve, to its
        machine; if none has, run the solves the agents wait for. Whether anything was done."""
        for name, agent in self.agents.items():
            if agent.inbox and not agent.left and agent.solving is None:
                self._handle(name, agent, agent.inbox.popleft())
                return True
        return self._solve()

    def _handle(self, name: str, agent: _Agent, msg) -> None:
        m = agent.machine
        if not agent.joined:  # an agent asks the DMO for its clock, then registers (docs/protocol.md, step 3)
            if not isinstance(msg, Clock):
                return
            m.join(msg)
            agent.joined = True
            self._send(name, agent, m.registration())
            return
        agent.received += not isinstance(msg, RefusedPayload)
        started_at, started, cpu = time.time_ns(), time.perf_counter(), time.thread_time()
        with failing_as(name):
            actions = m.handle(msg)
        self._went_on(name, agent, _Handling(msg, started_at, started, time.thread_time() - cpu, actions))

    def _solve(self) -> bool:
        """Run the solves the agents wait for side by side, and hand each result in, in the agents' name order, as it
        comes; whether there were any. The solve's CPU, in its worker or here, counts in its message's handling."""
        waiting = {name: agent for name, agent in self.agents.items() if agent.solving is not None}
        if not waiting:
            return False
        solutions = self._solves.run([agent.solving.actions[-1].job for agent in waiting.values()])
        for name, agent in waiting.items():
            handling, agent.solving = agent.solving, None
            with failing_as(name):
                schedule, solve_cpu_s = next(solutions)
                cpu = time.thread_time()
                handling.actions[-1:] = agent.machine.handle(Solved(schedule))
            handling.cpu_s += solve_cpu_s + time.thread_time() - cpu
            self._went_on(name, agent, handling)
        return True

    def _went_on(self, name: str, agent: _Agent, handling: _Handling) -> None:
        """The agent waits for the solve its machine asked for; or it has handled the message: its computation goes
        in (wall: from handing the message in to the last result handled) and what it decided is carried out."""
        if handling.waits():
            agent.solving = handling
            return
        m, msg, actions = agent.machine, handling.msg, handling.actions
        if not isinstance(msg, RefusedPayload):
            compute = HandlingTime(kind=msg.kind, hour=getattr(msg, "hour", None),
                                   wall_s=time.perf_counter() - handling.started, cpu_s=handling.cpu_s,
                                   started_at=handling.started_at, turn_s=0.0)
            with failing_as(name):
                actions += m.handle(Handled(compute, self._counts(agent)))
        for action in actions:
            if isinstance(action, Send):
                self._send(name, agent, action.msg)
            elif isinstance(action, AskStatement):  # the statement went before the summary: it is the latest
                statement = self._latest.get(self.keys.statement(name))
                agent.inbox.appendleft(statement if statement is not None else NoStatement())
            elif not isinstance(action, AwaitReceipts):  # in order already: what an agent sent is handled first
                raise TypeError(f"the in-process market cannot do {action!r}")
        if m.done:
            agent.left = True
            self._to_dmo.append(Left(name))

    def _send(self, name: str, agent: _Agent, msg) -> None:
        key, payload, stamped = agent.sender.stamp(msg, None, time.time_ns())
        self._record(key, payload)
        agent.pending[sha256(payload)] = (stamped.kind, stamped.seq)
        self._to_dmo.append(Received(key, decode(payload, expected_kind=stamped.kind), payload))

    def _counts(self, agent: _Agent) -> MessageCounts:
        return MessageCounts(published=agent.sender.seq, received=agent.received, rejected={}, handler_errors=0,
                             ignored=dict(agent.machine.ignored), sent_again=0, asked=0, faults_injected={})

    def _record(self, key: str, payload: bytes) -> None:
        if self.writer is not None:
            self.writer.write(key, payload, time.time_ns())
            self.writer.tick()


def run_in_process(e: Experiment, fleet: list[FleetMember], run_id: str, record: Path | None,
                   recording: tuple[dict, list[str]], log_file: Path, on_clock: Callable[[Clock], None]) -> DmoReport:
    """The (resolved) experiment, whose agents are ``fleet``, run in this process (``agents.hosting =
    "in-process"``): the DMO's result as its process writes it (``RunResult.report``); ``record`` is where the recording goes (None: none), ``recording`` its metadata and the files it attaches,
    ``log_file`` where the roles' logs go."""
    from microgrid_agent.agent.strategies import choose_strategy  # noqa: PLC0415  (the solver stack)

    agents = {}
    for member in fleet:
        case = member_case(member)
        config = agent_config(e, member)
        agents[member.id] = AgentMachine(member.id, case, config, e.market_day,
                                         choose_strategy(strategy_of(e, member), case, config.gap))
    writer = None
    if record is not None:
        meta, paths = recording
        writer = RecordingWriter(record, run_id)
        writer.start(meta, read_attachments(paths))
    try:
        with logged_to(log_file):
            market = InProcessMarket(day_config(e), run_id, agents, writer, on_clock)
            result = market.run().report(run_id, market.transport())
    finally:
        if writer is not None:
            writer.close()
    return result


@contextlib.contextmanager
def failing_as(name: str) -> Iterator[None]:
    """What an agent's machine or solve raises in the block ends the run, naming the agent (``AgentFailed``)."""
    try:
        yield
    except Exception as exc:
        raise AgentFailed(f"{name} failed: {exc}") from exc


@contextlib.contextmanager
def logged_to(path: Path) -> Iterator[None]:
    """While the block runs, what the roles log, and what native libraries print (HiGHS's banner, on file
    descriptor 1, which the command line points at stderr), go to ``path``, as each role's goes to its own log when
    it is a process."""
    handler = logging.FileHandler(path, encoding="utf-8")
    handler.setFormatter(logging.Formatter("%(asctime)s %(name)s %(levelname)s %(message)s"))
    roles = [logging.getLogger(name) for name in ROLE_LOGGERS]
    before = [(r.level, r.propagate) for r in roles]
    for r in roles:
        r.addHandler(handler)
        r.setLevel(logging.INFO)
        r.propagate = False
    sys.stdout.flush()
    fd1 = os.dup(1)
    with open(path, "ab") as native:
        os.dup2(native.fileno(), 1)
    try:
        yield
    finally:
        os.dup2(fd1, 1)
        os.close(fd1)
        for r, (level, propagate) in zip(roles, before):
            r.removeHandler(handler)
            r.setLevel(level)
            r.propagate = propagate
        handler.close()


ROLE_LOGGERS = ("dmosim.dmo", "dmosim.agent")  # what the DMO and the agents log under
