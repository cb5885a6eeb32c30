"""Compare recordings by what they say, apart from run ids and clocks."""

from __future__ import annotations

import base64
import collections
import json

from .reader import Recording

# What differs between two runs of one experiment: clocks, the run's token and processes, and so the numbering and
# the hashes of what was sent (a message sent again for want of a receipt shifts its sender's later numbers).
# what differs between two runs of one configuration: stamps, and an agent's measurements of itself (its compute
# times and message counts, on its realised day)
_STAMPS = ("sent_at", "received_at", "run", "incarnation", "seq", "payload_sha256", "compute", "messages")


def content_signature(rec: Recording) -> dict[str, set[str]]:
    """What a recording says, apart from what differs between runs: per key relative to the run prefix, the set
    of its payloads without their stamps (time, run token, incarnation, sequence number, the hash a receipt or a
    rejection names) and an agent's measurements of itself, as canonical JSON. A message sent again says nothing new. Two runs of the same configuration
    and seed give equal signatures; run ids, clocks and retransmissions differ, contents do not."""
    out: dict[str, set[str]] = collections.defaultdict(set)
    for m in rec.messages:
        try:
            data = json.loads(m.payload)
        except (ValueError, RecursionError):
            out[m.relative_key].add(base64.b64encode(m.payload).decode())
            continue
        if isinstance(data, dict):
            for name in _STAMPS:
                data.pop(name, None)
        out[m.relative_key].add(json.dumps(data, sort_keys=True))
    return dict(out)
