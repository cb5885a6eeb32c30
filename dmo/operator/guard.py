"""Replay protection and agent identity: which process of each agent the DMO takes messages from (its
``incarnation``), and the sequence numbers and payload hashes of the messages it accepted from it.

An agent's identity is its credentials (only they publish on its keys); which of its processes speaks is the
incarnation every message carries, the process's start time. A later incarnation is a restarted agent: its
registration is a rejoin (``rejoin.py``) and, until it registers, its other messages are refused
(``unregistered``). An earlier one is a process that is gone: what it sent is ``stale``, however it arrives.

Within one incarnation the messages are numbered (``seq``), and the DMO remembers the numbers it accepted, with
their payloads' hashes, over the ``REMEMBERED`` numbers up to the latest. An exact copy of an accepted message
(same number, same bytes) is that message again: a sender that saw no receipt sends it again, and the DMO answers
with the receipt and nothing else (``again``). Another payload under an accepted number is a ``duplicate``. A number
not accepted within that window is new, even if a later one was accepted first: a sender with two messages in
flight (a rejoined agent's schedule and meter report) may lose the first and have it overtaken by the second, and
its copy is still taken (the phase's rules then decide on it). A number older than the window is ``late``: whether
it was accepted can no longer be told. Only accepted messages advance a sender's numbers, so a refused message
(however high its number) cannot lock an agent out.
"""

from __future__ import annotations

from array import array

from ..market.acceptance import Refusal

# How far back, in sequence numbers, the DMO remembers what it accepted: a sender stops sending a message once its
# receipt comes, at most seconds later, long before it has sent this many more (an agent sends about 28 a day); an
# older number is ``late``.
REMEMBERED = 64
DIGEST = 32  # bytes of a SHA-256


class Remembered:
    """One process's accepted numbers and payload digests within ``REMEMBERED`` of its latest, in storage of fixed
    size (number ``seq`` in slot ``seq % REMEMBERED``), allocated once when the process is admitted: what the DMO
    holds per agent does not grow, nor churn small objects, with the days (2.5 KiB an agent)."""

    __slots__ = ("seqs", "digests")

    def __init__(self):
        self.seqs = array("q", [-1]) * REMEMBERED
        self.digests = bytearray(REMEMBERED * DIGEST)

    def __contains__(self, seq: int) -> bool:
        return self.seqs[seq % REMEMBERED] == seq

    def __len__(self) -> int:
        return sum(1 for seq in self.seqs if seq >= 0)

    def holds(self, seq: int, sha256: str) -> bool:
        """Whether number ``seq`` was accepted with a payload hashing to ``sha256`` (hex)."""
        slot = seq % REMEMBERED
        return self.seqs[slot] == seq and self.digests[slot * DIGEST:(slot + 1) * DIGEST] == bytes.fromhex(sha256)

    def keep(self, seq: int, sha256: str) -> None:
        slot = seq % REMEMBERED
        self.seqs[slot] = seq
        self.digests[slot * DIGEST:(slot + 1) * DIGEST] = bytes.fromhex(sha256)


class SequenceGuard:
    """Per agent: the incarnation admitted, the newest heard, and the latest accepted (seq -> payload SHA-256)."""

    def __init__(self):
        self.incarnation: dict[str, int] = {}  # the process the DMO takes messages from
        self.newest: dict[str, int] = {}       # the latest process heard from, admitted or not
        self.last: dict[str, int] = {}         # its latest accepted seq
        self.accepted: dict[str, Remembered] = {}  # its latest accepted seqs and payload SHA-256

    def heard(self, sender: str, incarnation: int) -> None:
        """A message from this process of ``sender`` arrived (accepted or not)."""
        self.newest[sender] = max(incarnation, self.newest.get(sender, incarnation))

    def again(self, sender: str, incarnation: int, seq: int, sha256: str) -> bool:
        """Whether this is an exact copy of a message accepted from the admitted process."""
        return (self.incarnation.get(sender) == incarnation and sender in self.accepted
                and self.accepted[sender].holds(seq, sha256))

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
        if sender in self.accepted and seq in self.accepted[sender]:
            return "duplicate", f"{sender}'s message #{seq} was already accepted, with other content: a replay"
        last = self.last.get(sender)
        if last is not None and seq <= last - REMEMBERED:
            return "late", (f"{sender}'s message #{seq} is {REMEMBERED} or more numbers older than its message "
                            f"#{last}, already accepted: overtaken (delayed or replayed)")
        return None

    def admit(self, sender: str, incarnation: int) -> None:
        """From now on, take messages from this process of ``sender`` (its first, or a restarted one), numbered
        from 0 again."""
        self.incarnation[sender] = incarnation
        self.heard(sender, incarnation)
        self.last.pop(sender, None)
        self.accepted[sender] = Remembered()

    def accept(self, sender: str, seq: int, sha256: str) -> None:
        """From now on a copy of this message is ``again``, another payload under its number a ``duplicate``."""
        self.last[sender] = max(seq, self.last.get(sender, seq))
        self.accepted[sender].keep(seq, sha256)  # its process was admitted first (``admit``)

    def locked_out(self) -> list[str]:
        """Agents of the market a later process of which spoke and was not admitted (its rejoin was refused, or never
        came): running, and out of the market. (A stranger that was never admitted is not of the market: its
        messages are refused as unregistered, or its registration as late, and a dmosim agent exits on that.)"""
        return sorted(a for a, newest in self.newest.items() if a in self.incarnation and newest > self.incarnation[a])
