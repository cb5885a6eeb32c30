"""Compare recordings by what they say, apart from run ids and clocks."""

from __future__ import annotations

import base64
import collections
import json

from .reader import Recording

_TIMESTAMPS = ("sent_at", "received_at")


def content_signature(rec: Recording) -> dict[str, collections.Counter[str]]:
    """What a recording says, apart from timestamps: per key relative to the run prefix, the multiset of its
    payloads with ``sent_at`` (and a rejection's ``received_at``) removed, as canonical JSON. Two runs of the same
    configuration and seed give equal signatures; run ids and clocks differ, contents do not."""
    out: dict[str, collections.Counter[str]] = collections.defaultdict(collections.Counter)
    for m in rec.messages:
        try:
            data = json.loads(m.payload)
        except (ValueError, RecursionError):
            out[m.relative_key][base64.b64encode(m.payload).decode()] += 1
            continue
        if isinstance(data, dict):
            for name in _TIMESTAMPS:
                data.pop(name, None)
        out[m.relative_key][json.dumps(data, sort_keys=True)] += 1
    return dict(out)
