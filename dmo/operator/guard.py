"""Replay protection: each sender's messages are numbered (``seq``, stamped by its bus), and a number the DMO has
accepted, or one older than the latest it accepted, is refused.

A copy of an accepted message is a ``duplicate`` (a network duplicate, or a replay); an older one is ``late``
(delayed, or replayed, and overtaken). A sender that restarts numbers from 0 again: the DMO ``forget``s its
numbers when it lets it rejoin.
"""

from __future__ import annotations

from ..market.acceptance import Refusal


class SequenceGuard:
    """The sequence numbers of the messages accepted from each sender."""

    def __init__(self):
        self.last: dict[str, int] = {}       # per sender, its latest accepted seq
        self.seen: dict[str, set[int]] = {}  # per sender, every accepted seq

    def check(self, sender: str, seq: int) -> Refusal | None:
        if seq in self.seen.get(sender, ()):
            return "duplicate", f"{sender}'s message #{seq} was already accepted: a duplicate or a replay"
        last = self.last.get(sender)
        if last is not None and seq < last:
            return "late", (f"{sender}'s message #{seq} is older than its message #{last}, already accepted: "
                            "overtaken (delayed or replayed)")
        return None

    def accept(self, sender: str, seq: int) -> None:
        """From now on a copy of this message, or anything older from its sender, is refused."""
        self.last[sender] = max(seq, self.last.get(sender, seq))
        self.seen.setdefault(sender, set()).add(seq)

    def forget(self, sender: str) -> None:
        """The sender restarted: it numbers its messages from 0 again."""
        self.last.pop(sender, None)
        self.seen.pop(sender, None)
