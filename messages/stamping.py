"""What a sender puts on every message it sends (docs/protocol.md, "Envelope"): the run's token, its process's
incarnation, its next sequence number and the time it was sent; and the key the message goes on. One definition
for the Bus (transport/bus.py) and for the in-process market, which sends without a network."""

from __future__ import annotations

from dataclasses import dataclass

from .codec import encode
from .keys import Keys, check_route
from .schemas import Envelope, Message


@dataclass
class Sender:
    """One process's numbering of what it sends: ``seq`` counts up from 0, ``incarnation`` names the process (its
    start, ns), ``run_token`` is the run's (the DMO draws it; the others learn it from its clock)."""

    keys: Keys
    name: str
    incarnation: int
    run_token: str = ""
    seq: int = 0

    def stamp(self, msg: Envelope, key: str | None, sent_at: int) -> tuple[str, bytes, Message]:
        """``msg`` stamped with the next number and ``sent_at`` (ns), the key it goes on (``keys.for_message``
        unless given; a given key must fit the message) and its payload. The number is taken: the next message gets
        the one after."""
        if msg.sender != self.name:
            raise ValueError(f"{self.name!r} cannot send a message from {msg.sender!r}")
        stamped = msg.model_copy(update={"run": self.run_token, "incarnation": self.incarnation, "seq": self.seq,
                                         "sent_at": sent_at})
        key = key or self.keys.for_message(stamped)
        check_route(key, stamped, self.keys.run_id)
        payload = encode(stamped)
        self.seq += 1
        return key, payload, stamped
