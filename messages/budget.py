"""What one sender may send in one window of the market day (a phase, or a real-time hour) before what it sends
more is dropped unread: the bound on what the DMO and the recorder hold and write for one agent, whatever it sends
(docs/protocol.md, "Budgets").

An honest agent sends a few messages a window (its registration, bid, schedule or meter report, a realised day,
and each again if its receipt is lost), the largest a realised day of about 10 KB; the budget is ten times that.
A sender over its budget in a window has the rest of that window's messages dropped before they are decoded,
journalled or recorded, and counted; a new window starts it afresh. Thread-safe: Zenoh's threads ask, the owner's
thread starts the windows.
"""

from __future__ import annotations

import threading
from collections import Counter

BUDGET_MESSAGES = 32  # messages one sender may send in one window
BUDGET_BYTES = 128 << 10  # bytes of payload one sender may send in one window


class SenderBudget:
    """Per sender, the messages and bytes it sent in the current window; ``admit`` charges one payload and says
    whether it is within the budget. ``dropped`` counts, per sender, what the current window dropped."""

    def __init__(self, messages: int = BUDGET_MESSAGES, size: int = BUDGET_BYTES):
        self.messages, self.size = messages, size
        self._sent: Counter[str | None] = Counter()
        self._bytes: Counter[str | None] = Counter()
        self.dropped: Counter[str | None] = Counter()
        self._lock = threading.Lock()

    def admit(self, sender: str | None, size: int) -> int:
        """Charge a payload of ``size`` bytes from ``sender`` (None: a key that names no agent, one budget for all
        such): 0 if it is within the window's budget, else how many of the sender's payloads the window has dropped
        with this one (1: the first)."""
        with self._lock:
            if self._sent[sender] < self.messages and self._bytes[sender] + size <= self.size:
                self._sent[sender] += 1
                self._bytes[sender] += size
                return 0
            self.dropped[sender] += 1
            return self.dropped[sender]

    def next_window(self) -> Counter[str | None]:
        """Start a new window; what the one that ends dropped, per sender."""
        with self._lock:
            dropped = self.dropped
            self._sent, self._bytes, self.dropped = Counter(), Counter(), Counter()
            return dropped
