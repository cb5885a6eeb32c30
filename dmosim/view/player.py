"""A recording played into the page (``dmosim view RECORDING``): its valid messages of the run, in the order they
were recorded, with their recorded spacing divided by a rate; paused, played, and moved to the start of any phase
or hour (``seek``: the state is folded again from the first message up to there, at once)."""

from __future__ import annotations

import threading
import time

from messages.recording import Recording

from .board import Board
from .feed import decoded


def playable(rec: Recording) -> list[tuple[str, object, int]]:
    """(relative key, message, log time) of every valid message of the recording's run, in log order."""
    items = []
    for m in rec.in_log_order():
        if m.invalid is not None or m.kind is None:
            continue
        msg = decoded(m.key, m.payload)
        if msg is not None:
            items.append((m.relative_key, msg, m.log_time))
    return items


def marks(items: list[tuple[str, object, int]]) -> list[dict]:
    """Where each phase and real-time hour starts: the index of its clock message, and its label."""
    out = []
    for i, (_, msg, _) in enumerate(items):
        if msg.kind == "clock":
            label = f"{msg.market_day} {msg.phase}" + (f" hour {msg.hour}" if msg.hour else "")
            if not out or out[-1]["label"] != label:
                out.append({"index": i, "label": label})
    return out


class PagePlayer:
    """Plays ``items`` into ``board`` on a thread of its own (``start``), as ``pause``, ``play``, ``rate`` and
    ``seek`` say (each from the page, through server.py)."""

    def __init__(self, items: list[tuple[str, object, int]], board: Board, rate: float, paused: bool = False):
        self.items, self.board = items, board
        self.marks = marks(items)
        self.position = 0  # the next item to fold in
        self.rate, self.paused = rate, paused
        self._changed = threading.Condition()
        self._origin: tuple[float, int] | None = None  # (monotonic s, log time ns) the pacing counts from
        self._note()

    def _note(self) -> None:
        mark = max((i for i, m in enumerate(self.marks) if m["index"] < self.position), default=None)
        self.board.note(mode="replay", paused=self.paused, rate=self.rate, position=self.position,
                        total=len(self.items), marks=[m["label"] for m in self.marks], mark=mark,
                        ended=self.position >= len(self.items))

    # --- control (any thread) -------------------------------------------------------------------------------------
    def control(self, pause: bool | None = None, rate: float | None = None, seek: int | None = None) -> None:
        with self._changed:
            if rate is not None:
                self.rate = rate
            if pause is not None:
                self.paused = pause
            if seek is not None:
                self._seek(self.marks[seek]["index"] if self.marks else 0)
            self._origin = None
            self._note()
            self._changed.notify_all()

    def _seek(self, index: int) -> None:
        self.board.reset()
        for key, msg, at in self.items[:index + 1]:
            self.board.take(key, msg, at)
        self.position = index + 1

    # --- the playing thread -----------------------------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            with self._changed:
                if self.paused or self.position >= len(self.items):
                    self._changed.wait(0.5)
                    continue
                key, msg, at = self.items[self.position]
                if self._origin is None:
                    self._origin = (time.monotonic(), at)
                due = self._origin[0] + (at - self._origin[1]) / 1e9 / self.rate
                wait = due - time.monotonic()
                if wait > 0:
                    self._changed.wait(min(wait, 0.5))
                    continue
                self.board.take(key, msg, at)
                self.position += 1
                if msg.kind == "clock" or self.position >= len(self.items):
                    self._note()

    def start(self, stop: threading.Event) -> threading.Thread:
        thread = threading.Thread(target=self.run, args=(stop,), name="view-player", daemon=True)
        thread.start()
        return thread
