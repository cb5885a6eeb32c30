"""The layout of a dmosim MCAP recording: names, encodings and schemas that the writer and the reader share.

A recording is self-describing and opens in any MCAP reader with no code of ours:

- one channel per key expression, topic = the key as it travelled (``dmosim/<run>/dmo/grid``), message encoding
  ``json``, schema encoding ``jsonschema`` with the JSON Schema of the key's kind (``schemas.json_schema``);
- a payload that fails its key's schema (not JSON, wrong kind, a missing field...) is never written on that
  channel, so every message of a channel validates against the channel's schema. It goes, with the reason it
  failed, to the one channel ``<prefix>/recorder/invalid`` (schema ``dmosim.invalid_payload``: the key, the
  rejection code and reason, and the payload in base64). Payloads the DMO refuses for what they mean (late,
  duplicate, unregistered...) are valid and stay on their key's channel; the DMO's ``Rejection`` on
  ``dmo/rejected`` says which and why;
- ``log_time`` is the recorder's receive time, ``publish_time`` the sender's ``sent_at``, ``sequence`` its ``seq``;
- zstd-compressed chunks, message and chunk indexes, a summary section with statistics;
- one metadata record ``dmosim`` (run id, key prefix, message schema version, versions, and what the caller adds:
  configuration, seed, market day, agents) and the case and fleet files as attachments, both written first so
  that a cut file still has them.
"""

from __future__ import annotations

import re
import sys
from importlib import metadata as _metadata

from ..schemas import SCHEMA_VERSION

MAGIC = b"\x89MCAP0\r\n"
MESSAGE_ENCODING = "json"
SCHEMA_ENCODING = "jsonschema"
METADATA_NAME = "dmosim"
BACKFILL_METADATA = "dmosim.backfill"  # a late recorder's record of what the DMO's history gave it
DROPPED_METADATA = "dmosim.dropped"  # sender -> payloads the recorder dropped unread, the sender over its budget
INVALID_KEY = "recorder/invalid"        # relative to the run prefix; not a key anyone publishes on
INVALID_SCHEMA_NAME = "dmosim.invalid_payload"
ANY_SCHEMA_NAME = "dmosim.any"
CHUNK_MESSAGES = 500
FLUSH_INTERVAL_S = 1.0
CHUNK_BYTES = 1 << 20
# An invalid payload is kept whole up to this size (ten times an honest message's), a larger one to its first this
# many bytes; once a file holds KEPT_INVALID_TOTAL bytes of invalid payloads, later ones keep none (their key, code,
# reason, size and SHA-256 only).
KEPT_INVALID_BYTES = 64 << 10
KEPT_INVALID_TOTAL = 16 << 20

# What reading a file may take, whatever it declares (docs/recording.md, "Reading is bounded and checked"). The
# writer's chunks close at CHUNK_BYTES, so the largest holds 1 MiB plus one message; its largest message is a valid
# one at the wire's MAX_PAYLOAD_BYTES (an invalid one keeps at most KEPT_INVALID_BYTES). Measured on real recordings:
# a chunk compresses 3.5x to 6.5x, and a whole file expands to 1.0-3.7x its size (to 24x for a day under a flood of
# oversized junk, every message charged MESSAGE_COST_BYTES), so the budget below leaves room for what dmosim
# writes while a 26 KB file can no longer expand to gigabytes.
MAX_CHUNK_BYTES = 16 << 20
MAX_MESSAGE_BYTES = 4 << 20
MESSAGE_COST_BYTES = 512        # what holding one message costs beyond its data (its RecordedMessage)
READ_BUDGET_RATIO = 32          # a file expands to at most this many times its size...
READ_BUDGET_FLOOR_BYTES = 64 << 20  # ...or this, whichever is more
_DRAFT = "https://json-schema.org/draft/2020-12/schema"

# A payload on a key outside the layout (no kind): any JSON value.
ANY_SCHEMA = {"$schema": _DRAFT, "$id": f"urn:dmosim:any:v{SCHEMA_VERSION}", "title": "Unchecked",
              "description": "a JSON payload on a key outside the dmosim layout, recorded as it arrived"}
INVALID_SCHEMA = {
    "$schema": _DRAFT, "$id": f"urn:dmosim:invalid_payload:v{SCHEMA_VERSION}", "title": "InvalidPayload",
    "description": "a payload that failed its key's schema, recorded with the reason",
    "type": "object", "additionalProperties": False,
    "required": ["key", "code", "reason", "payload_size", "payload_base64"],
    "properties": {"key": {"type": "string"}, "code": {"type": "string"}, "reason": {"type": "string"},
                   "payload_size": {"type": "integer", "minimum": 0},
                   "payload_sha256": {"type": "string", "pattern": "^[0-9a-f]{64}$",
                                      "description": "of the whole payload as received (absent in older files)"},
                   "payload_base64": {"type": "string", "contentEncoding": "base64",
                                      "description": f"the payload, whole up to {KEPT_INVALID_BYTES} bytes, else its "
                                                     f"first {KEPT_INVALID_BYTES}; empty once the file holds "
                                                     f"{KEPT_INVALID_TOTAL} bytes of invalid payloads (payload_size "
                                                     "is its whole size)"}},
}
SCHEMA_ID = re.compile(r"^urn:dmosim:[a-z_]+:v([0-9]+)$")


def versions() -> dict[str, str]:
    """Versions of what shapes a recording's contents: this package, Python and the libraries on the path."""
    out = {"dmosim": _version("dmosim"), "python": sys.version.split()[0]}
    for name in ("mcap", "eclipse-zenoh", "pydantic", "numpy", "cvxpy", "highspy"):
        out[name] = _version(name)
    return out


def _version(dist: str) -> str:
    try:
        return _metadata.version(dist)
    except _metadata.PackageNotFoundError:
        return "unknown"


def library() -> str:
    return f"dmosim {_version('dmosim')} (message schemas v{SCHEMA_VERSION}); mcap-python {_version('mcap')}"
