"""The recorder's loop: every payload under one run prefix, as it arrived, valid or not, into a RecordingWriter."""

from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Callable

from .writer import RecordingWriter

log = logging.getLogger("dmosim.recorder")


class Recorder:
    """Records every payload under one run prefix, as it arrived, valid or not: Zenoh's threads only enqueue,
    and ``run`` writes on the calling thread until ``stop`` is set, then drains the queue and closes the file.

    The liveliness token ``alive/recorder`` is declared after the subscription, so whoever sees the recorder
    present (the DMO waits for it) knows that it is already listening.
    """

    def __init__(self, bus, writer: RecordingWriter, announce: bool = True):
        self.bus, self.writer, self.announce = bus, writer, announce
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._subscription = None
        self._token = None
        self.first_received_ns = 0   # receipt of the first message, and the end of the last write: the span the
        self.last_written_ns = 0     # recorder kept up with (its sustained rate is messages / span)

    def start(self) -> None:
        self._subscription = self.bus.subscribe_raw(self.bus.keys.everything(),
                                                    lambda key, payload, at: self._queue.put((key, payload, at)))
        if self.announce:
            self._token = self.bus.session.liveliness().declare_token(self.bus.keys.alive("recorder"))

    def run(self, stop: threading.Event, on_write: Callable[[str, bool], None] | None = None) -> None:
        writer, q = self.writer, self._queue
        try:
            while not stop.is_set():
                try:
                    item = q.get(timeout=min(0.1, writer.flush_interval_s))
                except queue.Empty:
                    writer.tick()
                    continue
                self._write(*item, on_write)
                for _ in range(writer.chunk_messages):  # drain a burst before looking at the clock again
                    try:
                        item = q.get_nowait()
                    except queue.Empty:
                        break
                    self._write(*item, on_write)
                writer.tick()
        finally:
            self.stop()
            while True:
                try:
                    item = q.get_nowait()
                except queue.Empty:
                    break
                self._write(*item, on_write)
            writer.close()

    def _write(self, key: str, payload: bytes, at: int, on_write) -> None:
        valid = self.writer.write(key, payload, at)
        self.first_received_ns = self.first_received_ns or at
        self.last_written_ns = time.time_ns()
        if on_write is not None:
            on_write(key, valid)

    @property
    def busy_s(self) -> float:
        return max(0.0, (self.last_written_ns - self.first_received_ns) / 1e9)

    def stop(self) -> None:
        token, self._token = self._token, None
        if token is not None:
            try:
                token.undeclare()
            except Exception:  # the session may be closing already
                log.debug("could not undeclare the recorder's token", exc_info=True)
        subscription, self._subscription = self._subscription, None
        if subscription is not None:
            subscription.close()
