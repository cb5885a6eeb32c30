"""Encode messages as compact UTF-8 JSON and decode received bytes, refusing anything invalid with a one-line reason."""

from __future__ import annotations

import hashlib
import json
import time

from pydantic import ValidationError

from .schemas import DMO, KINDS, MESSAGE_ADAPTER, SCHEMA_VERSION, Envelope, Message, Receipt, Rejection

MAX_PAYLOAD_BYTES = 1 << 20
_MAX_REASON = 300


class MessageError(ValueError):
    """A payload or key that cannot be accepted. ``str(err)`` is the one-line reason, ``err.code`` its category
    (one of schemas.REJECT_CODES), so receivers can count rejections by category and log the reason."""

    def __init__(self, reason: str, code: str = "invalid"):
        reason = " ".join(reason.split())
        if len(reason) > _MAX_REASON:
            reason = reason[:_MAX_REASON - 3] + "..."
        super().__init__(reason)
        self.reason = reason
        self.code = code


def encode(msg: Envelope) -> bytes:
    """The wire form of a message: compact UTF-8 JSON with every field present."""
    payload = msg.__pydantic_serializer__.to_json(msg)
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise MessageError(_oversize(len(payload)), "oversize")
    return payload


def decode(payload: bytes, expected_kind: str | None = None) -> Message:
    """Parse and validate one received payload; raises MessageError (and nothing else) when it is unacceptable."""
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise MessageError(f"payload must be bytes, not {type(payload).__name__}", "not_json")
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise MessageError(_oversize(len(payload)), "oversize")
    try:
        msg = MESSAGE_ADAPTER.validate_json(payload)
    except ValidationError as err:
        upgraded = _upgrade(bytes(payload))
        if upgraded is None:
            raise _diagnose(bytes(payload), err) from None
        try:
            msg = MESSAGE_ADAPTER.validate_json(upgraded)
        except ValidationError:
            raise _diagnose(bytes(payload), err) from None
    if expected_kind is not None and msg.kind != expected_kind:
        raise MessageError(f"expected kind {expected_kind!r}, got {msg.kind!r}", "wrong_key")
    return msg


# What each version added to a kind ("*": to every kind), at its top level or to each item of one of its lists,
# and what an older message means by their absence.
ADDED = ((2, "clock", None, {"day": 1, "days": 1}),
         (3, "award", None, {"settlement_rule": None, "deviation_cost": None}),
         (3, "settlement_statement", None, {"settlement_rule": None}),
         (4, "*", None, {"run": "", "incarnation": 0}),
         (5, "award", None, {"congestion": None}),
         (6, "registration", None, {"strategy": None}),
         (7, "registration", None, {"bus": None}),
         (7, "award", None, {"bus": None, "energy_price_per_mwh": None, "congestion_price_per_mwh": None,
                             "voltage_price_per_mwh": None}),
         (8, "grid_state", None, {"buses": [], "room_mw": []}),
         (9, "agent_day", "compute", {"started_at": None, "turn_s": 0.0}),
         (10, "award", None, {"loss_price_per_mwh": None}),
         (10, "network_hour", None, {"clearing": None, "loss_price_per_mwh": None, "spilled_mw": None}),
         (11, "network_hour", None, {"limit_loading": None, "binding_facet": None, "line_shadow_price_per_mwh": None,
                                     "binding_voltage": None, "voltage_shadow_price_per_pu": None}))
# What each version split from one field of a kind into others, each taking its value; applied after ADDED (a field
# it split may be one ADDED supplies).
SPLIT = ((11, "grid_state", "room_mw", ("import_room_mw", "export_room_mw")),)


def _upgrade(payload: bytes) -> bytes | None:
    """A message of an older schema version as this version reads it, or None if there is nothing to upgrade.
    Version 1 -> 2: a clock, which had no day, is day 1 of a one-day run. Version 2 -> 3: an award or a statement
    names no settlement rule, which is the paper's at its penalty and credit rates. Version 3 -> 4: a message is
    bound to no run token and no incarnation (empty, 0), which a live DMO refuses and a recording reader accepts.
    Version 4 -> 5: an award states no congestion (null), which the tables show as unknown. Version 5 -> 6: a
    registration names no bidding strategy (null). Version 6 -> 7: a registration and an award name no bus and
    the award no price components (null): the copper plate. Version 7 -> 8: a grid state carries no operating
    envelope (no buses, no rooms), as on the copper plate. Version 8 -> 9: the messages an agent_day says its
    agent handled say neither when each was taken up (null) nor a wait for a turn (0). Version 9 -> 10: an award
    and a network_hour carry no loss component, and a network_hour names no clearing method and no spilled
    generation (null). Version 10 -> 11: a grid state's one room either way (``room_mw``) is its room above
    the awards and below them alike, and a network_hour says nothing of what binds (null). An older message that
    already has a field of a later version is left as it is, for validation to refuse."""
    try:
        data = json.loads(payload)
    except (ValueError, RecursionError):
        return None
    if not isinstance(data, dict):
        return None
    version = data.get("schema_version")
    if not isinstance(version, int) or isinstance(version, bool) or version >= SCHEMA_VERSION:
        return None
    upgraded = dict(data)
    for since, kind, within, fields in ADDED:
        if kind not in (data.get("kind"), "*") or version >= since:
            continue
        if within is None:
            if any(name in data for name in fields):
                return None
            upgraded.update(fields)
        elif isinstance(data.get(within), list):
            items = data[within]
            if any(not isinstance(item, dict) or any(name in item for name in fields) for item in items):
                return None
            upgraded[within] = [{**item, **fields} for item in items]
    for since, kind, old, new in SPLIT:
        if kind != data.get("kind") or version >= since or old not in upgraded:
            continue
        if any(name in data for name in new):
            return None
        value = upgraded.pop(old)
        upgraded.update({name: value for name in new})
    return json.dumps(upgraded).encode() if upgraded != data else None


def _oversize(size: int) -> str:
    return f"payload is {size} bytes, over the {MAX_PAYLOAD_BYTES}-byte limit"


def _diagnose(payload: bytes, err: ValidationError) -> MessageError:
    """Turn a validation failure into the most useful single reason: the envelope first, then the first bad field."""
    errors = err.errors(include_url=False, include_input=False)
    if errors[0]["type"] == "json_invalid":
        return MessageError(f"not JSON: {errors[0]['ctx'].get('error', errors[0]['msg'])}", "not_json")
    kind = None
    try:
        data = json.loads(payload)
    except (ValueError, RecursionError):
        pass  # the two parsers disagree on an edge case: report pydantic's finding below
    else:
        if not isinstance(data, dict):
            return MessageError(f"not a JSON object but {_json_type(data)}", "not_object")
        if "kind" not in data:
            return MessageError("missing field 'kind'", "unknown_kind")
        kind = data["kind"]
        if not isinstance(kind, str) or kind not in KINDS:
            return MessageError(f"unknown kind {_short(kind)}; kinds are {', '.join(KINDS)}", "unknown_kind")
        version = data.get("schema_version")
        if isinstance(version, int) and not isinstance(version, bool) and version > SCHEMA_VERSION:
            return MessageError(f"schema_version {version} is newer than supported {SCHEMA_VERSION}",
                                "unsupported_version")
    first = errors[0]
    loc = first["loc"][1:] if first["loc"] and first["loc"][0] == kind else first["loc"]
    where = _field_path(loc)
    what = str(first["ctx"]["error"]) if first["type"] == "value_error" else first["msg"]
    more = len(errors) - 1
    text = f"invalid {kind or 'message'}: {where + ': ' if where else ''}{what}"
    return MessageError(text + (f" (and {more} more)" if more else ""), "invalid")


def _field_path(loc: tuple) -> str:
    path = ""
    for part in loc:
        path += f"[{part}]" if isinstance(part, int) else (f".{part}" if path else str(part))
    return path


def _json_type(value) -> str:
    return {list: "an array", str: "a string", bool: "a boolean", int: "a number", float: "a number",
            type(None): "null"}.get(type(value), type(value).__name__)


def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def claimed(payload: bytes) -> tuple[str | None, int | None]:
    """The kind and seq a payload claims, as far as it can be read (None where it cannot)."""
    try:
        data = json.loads(bytes(payload).decode("utf-8"))
    except (ValueError, RecursionError):
        return None, None
    if not isinstance(data, dict):
        return None, None
    kind = data["kind"][:64] if isinstance(data.get("kind"), str) else None
    seq = data.get("seq")
    return kind, seq if isinstance(seq, int) and not isinstance(seq, bool) and 0 <= seq < 2**63 else None


def sha256(payload: bytes) -> str:
    """The hex SHA-256 of a payload's bytes as received: what rejections and receipts name it by."""
    return hashlib.sha256(payload).hexdigest()


def make_rejection(key: str, payload: bytes, error: MessageError, *, market_day: str,
                   offender: str | None = None, received_at: int | None = None) -> Rejection:
    """The Rejection the DMO publishes for a refused payload (the bytes as received), so the recording keeps it with
    its reason."""
    return Rejection(sender=DMO, market_day=market_day, key=key[:512], code=error.code, reason=error.reason,
                     offender=offender, rejected_kind=claimed(payload)[0], payload_size=len(payload),
                     payload_sha256=sha256(payload), received_at=time.time_ns() if received_at is None else received_at)


def make_receipt(agent: str, payload: bytes, error: MessageError | None, *, market_day: str) -> Receipt:
    """The Receipt the DMO sends ``agent`` for a payload received from it (the bytes as received): accepted when
    ``error`` is None, else refused with its code and reason."""
    kind, seq = claimed(payload)
    return Receipt(sender=DMO, market_day=market_day, agent=agent, payload_sha256=sha256(payload),
                   received_kind=kind, received_seq=seq, accepted=error is None,
                   code=None if error is None else error.code, reason="" if error is None else error.reason)
