"""The traffic of the DMO's day, kept so that a process that joins late learns what it missed: every payload the
DMO put on the wire and every one it received, in order, with its time (docs/recording.md, "Late joiners").

Zenoh delivers a message to the subscribers present when it is sent, and to nobody else. A recorder started after
the agents registered would miss their registrations, and the recording could not be re-settled. The DMO sees
the whole day (it is the one every agent talks to), so it answers queries on its run's keys: the latest message
on each of its keys, or, with the parameter ``history``, the whole traffic. This works for any Zenoh client, with
or without ``zenoh.ext``; a DMO resumed from its journal answers with the traffic it journaled.
"""

from __future__ import annotations

import threading

import zenoh

from messages.keys import HISTORY, parse_key
from messages.transport.bus import Entry


class DayHistory:
    """Every payload the DMO sent or received, as (key, payload, ns); thread-safe (Zenoh's threads record)."""

    def __init__(self, entries: list[Entry] | None = None):
        self.entries: list[Entry] = list(entries or ())
        self._lock = threading.Lock()

    def record(self, key: str, payload: bytes, at: int) -> None:
        with self._lock:
            self.entries.append((key, bytes(payload), at))

    def answer(self, key_expr: str, parameters: str) -> list[Entry]:
        """The replies to a query: with ``history`` among the parameters every entry on a matching key, in order;
        otherwise the latest message the DMO published on each matching key."""
        asked = zenoh.KeyExpr(key_expr)
        with self._lock:
            matching = [e for e in self.entries if asked.intersects(zenoh.KeyExpr(e[0]))]
        if HISTORY in (p.split("=", 1)[0] for p in parameters.split(";") if p):
            return matching
        latest = {}
        for entry in matching:
            if _published_by_dmo(entry[0]):
                latest[entry[0]] = entry
        return sorted(latest.values(), key=lambda e: e[2])


def _published_by_dmo(key: str) -> bool:
    try:
        return parse_key(key).role == "dmo"
    except ValueError:
        return False
