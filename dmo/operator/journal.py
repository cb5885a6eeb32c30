"""The DMO's journal of its day, and how a restarted DMO rebuilds the day from it (docs/faults.md).

One JSON object a line, written as it goes: the run's token, every clock step, every payload the DMO accepted (as
received), every incident and rejection, and its traffic (every payload sent or received, for late joiners:
history.py). Each line reaches the OS at once, so a DMO killed with SIGKILL loses nothing it had acted on. A DMO
restarted on the same journal, run and market day reads it back (``restore``, ``traffic``) and runs again the
phase, or the real-time hour, it had reached; a journal of another run or day is started afresh.
"""

from __future__ import annotations

import base64
import json
import threading
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

from messages import Bid, Incident, MeterReport, Registration, Schedule, decode, sha256
from messages.schemas import AgentDay

from . import rejoin
from .state import DayState


class Journal:
    """An open journal file. ``entries`` are those read back from a journal of the same run and day."""

    def __init__(self, path: str | Path, run_id: str, market_day: str):
        self.path, self.head = Path(path), {"journal": 1, "run_id": run_id, "market_day": market_day}
        self.entries: list[dict] = []
        whole = 0  # bytes of the whole lines read back
        if self.path.exists():
            *lines, _ = self.path.read_bytes().split(b"\n")  # the last piece: b"", or a line cut by the kill
            try:
                same = bool(lines) and json.loads(lines[0]) == self.head
            except ValueError:
                same = False
            whole = len(lines[0]) + 1 if same else 0
            for line in lines[1:] if same else ():
                try:
                    self.entries.append(json.loads(line))
                except ValueError:  # cut by the kill: the lines before it stand
                    break
                whole += len(line) + 1
        self._file = open(self.path, "ab" if self.entries else "wb")  # noqa: SIM115  (closed by close)
        self._file.truncate(whole if self.entries else 0)  # what follows is written after whole lines
        self.size = whole if self.entries else 0  # bytes of whole lines in the file: each line reaches the OS whole
        self._lock = threading.Lock()  # traffic is written from Zenoh's threads, the rest from the DMO's
        if not self.entries:
            self.write(self.head)

    def write(self, entry: dict) -> int:
        """Append ``entry`` as a line; the offset at which it starts."""
        line = line_of(entry)
        with self._lock:
            at = self.size
            if not self._file.closed:
                self._file.write(line)
                self._file.flush()
                self.size += len(line)
            return at

    def traffic(self, key: str, payload: bytes, at: int) -> int:
        """Append a payload sent or received; the offset of its line."""
        return self.write(traffic_entry(key, payload, at))


    def close(self) -> None:
        with self._lock:
            self._file.close()


def clock_entry(phase: str, hour: int | None, day: int = 1, market_day: str | None = None) -> dict:
    """A clock step: the phase (and real-time hour) of day ``day`` the DMO opened."""
    return {"clock": phase, "hour": hour, "day": day, "market_day": market_day}


def run_token_entry(token: str) -> dict:
    return {"run_token": token}


def accepted_entry(key: str, payload: bytes) -> dict:
    """A payload the DMO accepted, as it received it (valid JSON, so UTF-8 text)."""
    return {"accepted": key, "message": bytes(payload).decode()}


def incident_entry(incident: Incident) -> dict:
    return {"incident": incident.model_dump()}


def rejected_entry(code: str) -> dict:
    return {"rejected": code}


def restore(state: DayState, entries: list[dict], realised: Callable[[AgentDay], None] | None = None
            ) -> tuple[tuple[str, int | None] | None, list[DayState]]:
    """Rebuild ``state`` from journal entries: what the DMO accepted, its incidents and rejections, day by day; each
    realised day accepted also goes to ``realised`` (the run's result: finished.py). Returns the last clock step,
    (phase, hour) of ``state.day``, which the DMO then runs again from its start (None if it had not started), and
    the states of the days it had finished, to give their results again."""
    clock, finished = None, []
    for entry in entries:
        if "run_token" in entry:
            state.run_token = entry["run_token"]
        elif "clock" in entry:
            day, market_day = entry.get("day", 1), entry.get("market_day") or state.market_day
            if day > state.day:
                finished.append(state.start_day(day, market_day))
            state.market_day = market_day
            clock = state.phase, state.hour = (entry["clock"], entry["hour"])
        elif "incident" in entry:
            state.log.incidents.append(Incident(**entry["incident"]))
        elif "rejected" in entry:
            state.log.count_rejection(entry["rejected"])
        elif "accepted" in entry:
            payload = entry["message"].encode()
            msg = decode(payload)
            if isinstance(msg, Registration) and msg.sender in state.registered:
                rejoin.readmit(state, msg)  # a restarted agent's, taken as the live DMO took it
            elif isinstance(msg, Registration):
                state.registered[msg.sender] = msg
                state.meter.setdefault(msg.sender, {})
            elif isinstance(msg, Bid):
                state.bids[msg.sender] = msg
            elif isinstance(msg, Schedule):
                state.schedules[msg.sender] = msg
                state.rescheduling.discard(msg.sender)
            elif isinstance(msg, MeterReport):
                state.meter[msg.sender][msg.hour - 1] = msg.p_m_mw
            elif isinstance(msg, AgentDay):
                state.realised.setdefault(msg.sender, set()).add(msg.market_day)
                if realised is not None:
                    realised(msg)
            state.count_accepted(msg, sha256(payload))
    return clock, finished


def line_of(entry: dict) -> bytes:
    """A journal entry as its line in the file (ASCII JSON: its length is its bytes)."""
    return (json.dumps(entry, separators=(",", ":")) + "\n").encode()


def traffic_entry(key: str, payload: bytes, at: int) -> dict:
    """A payload sent or received, as a journal line."""
    return {"traffic": key, "at": at, "payload": base64.b64encode(payload).decode("ascii")}


def traffic(entries: Iterable[dict]) -> Iterator[tuple[str, bytes, int]]:
    """The traffic among journal entries, as (key, payload, ns) in the order it happened."""
    return ((e["traffic"], base64.b64decode(e["payload"]), e["at"]) for e in entries if "traffic" in e)
