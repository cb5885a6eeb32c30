"""Replay protection and agent identity: which process of each agent the DMO takes messages from (its
``incarnation``), and the sequence numbers and payload hashes of the messages it accepted from it.

An agent's identity is its credentials (only they publish on its keys); which of its processes speaks is the
incarnation every message carries, the process's start time. A later incarnation is a restarted agent: its
registration is a rejoin (``rejoin.py``) and, until it registers, its other messages are refused
(``unregistered``). An earlier one is a process that is gone: what it sent is ``stale``, however it arrives.

Within one incarnation the messages are numbered (``seq``). An exact copy of an accepted message (same number,
same bytes) is that message again: a sender that saw no receipt sends it again, and the DMO answers with the
receipt and nothing else (``again``). Another payload under an accepted number is a ``duplicate``; a number older
than the latest accepted one is ``late`` (delayed, or replayed, and overtaken). Only accepted messages advance a
sender's numbers, so a refused message (however high its number) cannot lock an agent out.
"""

from __future__ import annotations

from collections import OrderedDict

from ..market.acceptance import Refusal

# Accepted payloads remembered per agent to recognise one sent again: a sender stops sending a message once its
# receipt comes, at most seconds later, long before this many later messages of it are accepted (an agent sends
# about 28 a day); an older copy is ``late``. Kept small: the DMO holds this many hashes of every agent, and until
# they are all there its memory grows with the days (about 0.2 KiB per message).
REMEMBERED = 64


class SequenceGuard:
    """Per agent: the incarnation admitted, the newest heard, and the latest accepted (seq -> payload SHA-256)."""

    def __init__(self):
        self.incarnation: dict[str, int] = {}  # the process the DMO takes messages from
        self.newest: dict[str, int] = {}       # the latest process heard from, admitted or not
        self.last: dict[str, int] = {}         # its latest accepted seq
        self.accepted: dict[str, OrderedDict[int, str]] = {}  # its latest accepted seqs -> payload SHA-256

    def heard(self, sender: str, incarnation: int) -> None:
        """A message from this process of ``sender`` arrived (accepted or not)."""
        self.newest[sender] = max(incarnation, self.newest.get(sender, incarnation))

    def again(self, sender: str, incarnation: int, seq: int, sha256: str) -> bool:
        """Whether this is an exact copy of a message accepted from the admitted process."""
        return (self.incarnation.get(sender) == incarnation
                and self.accepted.get(sender, {}).get(seq) == sha256)

    def check(self, sender: str, incarnation: int, seq: int, registration: bool) -> Refusal | None:
        """The refusal of a message from ``sender``'s process ``incarnation`` numbered ``seq``, or None. A
        registration from a later process is let through: it is a rejoin, decided by ``rejoin.py``."""
        admitted = self.incarnation.get(sender)
        if admitted is not None and incarnation < admitted:
            return "stale", (f"{sender}'s message #{seq} comes from an earlier process of it (incarnation "
                             f"{incarnation}, now {admitted}): that process is gone")
        if admitted is not None and incarnation > admitted:
            return None if registration else (
                "unregistered", f"{sender}'s process {incarnation} has not registered: a restarted agent registers "
                                "again before anything else")
        if seq in self.accepted.get(sender, {}):
            return "duplicate", f"{sender}'s message #{seq} was already accepted, with other content: a replay"
        last = self.last.get(sender)
        if last is not None and seq < last:
            return "late", (f"{sender}'s message #{seq} is older than its message #{last}, already accepted: "
                            "overtaken (delayed or replayed)")
        return None

    def admit(self, sender: str, incarnation: int) -> None:
        """From now on, take messages from this process of ``sender`` (its first, or a restarted one), numbered
        from 0 again."""
        self.incarnation[sender] = incarnation
        self.heard(sender, incarnation)
        self.last.pop(sender, None)
        self.accepted.pop(sender, None)

    def accept(self, sender: str, seq: int, sha256: str) -> None:
        """From now on a copy of this message is ``again``, another under its number or anything older is refused."""
        self.last[sender] = max(seq, self.last.get(sender, seq))
        kept = self.accepted.setdefault(sender, OrderedDict())
        kept[seq] = sha256
        while len(kept) > REMEMBERED:
            kept.popitem(last=False)

    def locked_out(self) -> list[str]:
        """Agents of the market a later process of which spoke and was not admitted (its rejoin was refused, or never
        came): running, and out of the market. (A stranger that was never admitted is not of the market: its
        messages are refused as unregistered, or its registration as late, and a dmosim agent exits on that.)"""
        return sorted(a for a, newest in self.newest.items() if a in self.incarnation and newest > self.incarnation[a])
