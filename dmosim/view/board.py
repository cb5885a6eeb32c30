"""The page every browser is sent: one ``Board`` holds what the observer has seen, and renders it as JSON at most
so often that a browser never receives more than ``MAX_BYTES_PER_S`` (a browser that cannot keep up gets the latest
page when it can, never a queue of old ones: ``server.py``). The feed (live or a recording) only folds messages in;
rendering happens on a thread of its own (``run``), so neither waits for the other, nor for a browser."""

from __future__ import annotations

import json
import threading

from .page import page
from .state import Observed

MAX_BYTES_PER_S = 200_000  # what one browser is sent at most, on average: a page of 200 agents is ~80 KB
RENDER_EVERY_S = 0.25  # the page is rendered at most this often (less often when it is large)


class Board:
    """What the observer has seen (``observed``, behind ``lock``) and its latest page (``latest``: version, JSON
    bytes). ``extra`` holds what the feed adds to the page (live or replay, and the replay's position)."""

    def __init__(self, extra: dict | None = None):
        self.lock = threading.Lock()
        self.observed = Observed()
        self.extra: dict = dict(extra or {})
        self._changed = True
        self.latest: tuple[int, bytes] = (0, b"{}")
        self.rendered = threading.Event()  # set once a first page is there

    def take(self, key: str, msg, at_ns: int) -> None:
        """Fold one valid message of the run in (``Observed.take``)."""
        with self.lock:
            self.observed.take(key, msg, at_ns)
            self._changed = True

    def reset(self) -> None:
        """Forget everything seen (a replay that seeks back starts again from the recording's first message)."""
        with self.lock:
            self.observed = Observed()
            self._changed = True

    def note(self, **extra) -> None:
        """Change what the feed adds to the page."""
        with self.lock:
            self.extra.update(extra)
            self._changed = True

    def render(self) -> int:
        """Render the page if anything changed since the last; the bytes rendered (0: nothing to do)."""
        with self.lock:
            if not self._changed:
                return 0
            shown = page(self.observed)
            shown.update(self.extra)
            self._changed = False
        data = json.dumps(shown, separators=(",", ":"), allow_nan=False).encode()
        self.latest = (self.latest[0] + 1, data)
        self.rendered.set()
        return len(data)

    def run(self, stop: threading.Event) -> None:
        """Render until ``stop``: as often as ``RENDER_EVERY_S``, less often when the page is large (its size over
        ``MAX_BYTES_PER_S``)."""
        while not stop.is_set():
            size = self.render()
            stop.wait(max(RENDER_EVERY_S, size / MAX_BYTES_PER_S))

    def start(self, stop: threading.Event) -> threading.Thread:
        thread = threading.Thread(target=self.run, args=(stop,), name="view-render", daemon=True)
        thread.start()
        return thread
