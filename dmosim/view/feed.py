"""Where the page's messages come from: a run live over Zenoh (``LiveFeed``: the observer subscribes to everything
of the run, as the recorder does, and only queues what arrives, so it never slows the market; past ``QUEUED``
messages waiting, what arrives is dropped and counted) or a recording played at a rate (player.py). Both fold
the same decoded messages into a ``Board``."""

from __future__ import annotations

import logging
import queue
import threading

from messages import MessageError, decode
from messages.keys import check_route, parse_key, relative_key

from .board import Board

log = logging.getLogger("dmosim.view")
VIEWER = "viewer"  # the reader the page's observer logs in and subscribes as (its credentials bundle)
QUEUED = 100_000  # messages received and not yet folded in, at most: a 200-agent day is ~20,000 in all


def decoded(key: str, payload: bytes, run_id: str | None = None):
    """The valid message ``payload`` on ``key`` of the run, as its receivers take it (its key's kind, from its key's
    owner), else None (a liveliness key, an invalid payload, another run's)."""
    try:
        kind = parse_key(key).kind
        if kind is None:
            return None
        msg = decode(payload, expected_kind=kind)
        check_route(key, msg, run_id)
    except MessageError:
        return None
    return msg


class LiveFeed:
    """The run's messages as they arrive on ``bus``, folded into ``board`` on a thread of their own."""

    def __init__(self, bus, board: Board):
        self.bus, self.board = bus, board
        self._queue: queue.Queue = queue.Queue(maxsize=QUEUED)
        self.dropped = 0
        self.present: set[str] = set()
        self._thread: threading.Thread | None = None

    def start(self, stop: threading.Event) -> None:
        self.board.note(mode="live", run_id=self.bus.keys.run_id, dropped=0, present=[])
        self._thread = threading.Thread(target=self._fold, args=(stop,), name="view-fold", daemon=True)
        self._thread.start()
        self.bus.subscribe_raw(self.bus.keys.everything(), self._received)
        self.bus.watch_presence(self._joined, self._left)

    def _received(self, key: str, payload: bytes, at: int) -> None:
        """Zenoh's thread: queue and return, never wait."""
        try:
            self._queue.put_nowait((key, bytes(payload), at))
        except queue.Full:
            self.dropped += 1

    def _joined(self, name: str) -> None:
        self.present.add(name)
        self.board.note(present=sorted(self.present))

    def _left(self, name: str) -> None:
        self.present.discard(name)
        self.board.note(present=sorted(self.present))

    def _fold(self, stop: threading.Event) -> None:
        prefix, run_id = self.bus.keys.prefix, self.bus.keys.run_id
        noted = 0
        while not stop.is_set():
            try:
                key, payload, at = self._queue.get(timeout=0.2)
            except queue.Empty:
                continue
            msg = decoded(key, payload, run_id)
            if msg is not None:
                self.board.take(relative_key(key, prefix), msg, at)
            if self.dropped != noted:
                noted = self.dropped
                self.board.note(dropped=noted)
