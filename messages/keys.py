"""Zenoh key expressions of one run: build them, parse a received one, and check that a message may travel on it.

Layout (``<run>`` is the run id, ``<agent>`` an agent id)::

    dmosim/<run>/dmo/call_for_bids | clock | grid | network | summary | rejected
    dmosim/<run>/dmo/award/<agent> | statement/<agent> | receipt/<agent>
    dmosim/<run>/agent/<agent>/register | bid | schedule | meter | day
    dmosim/<run>/alive/<name>            liveliness tokens: "dmo", "recorder" or an agent id
    dmosim/<run>/link/<router>/<peer>    liveliness tokens: a router's link to another router (Zenoh ids)

The DMO publishes only under ``dmo/``, an agent only under its own ``agent/<agent>/``, so access control can be
a per-process key prefix. Everything sits under one run prefix, so concurrent runs never see each other.

The DMO answers queries (``get``) on any key of its run: with no parameters, the latest message it published on
each matching key (a late agent asks ``dmo/clock`` where the day stands); with the parameter ``history``, every
payload it sent or received on the matching keys, in order (a late recorder asks for ``**?history``), and with
``since=NS`` as well only those it saw at or after NS (a recorder checks each day for what it lacks).
"""

from __future__ import annotations

import re
import secrets
import time
from dataclasses import dataclass

from scenarios.names import DMO, NAME_PATTERN, RESERVED_NAMES, check_agent_id, is_agent_id, is_name

from .codec import MessageError
from .schemas import Envelope

ROOT = "dmosim"
HISTORY = "history"  # the query parameter that asks the DMO for the whole traffic of its day, not the latest
SINCE = "since"  # with ``history``: only what the DMO saw at or after this time (ns since the Unix epoch)
RUN_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_-]{0,63}$"
_RUN_ID = re.compile(RUN_ID_PATTERN)
_ZID = re.compile(r"[0-9a-f]{1,32}")  # a Zenoh id as Zenoh writes it: up to 16 bytes, in lower-case hexadecimal

# kind -> (role, topic, whether the key names an agent)
ROUTES: dict[str, tuple[str, str, bool]] = {
    "call_for_bids": ("dmo", "call_for_bids", False),
    "clock": ("dmo", "clock", False),
    "grid_state": ("dmo", "grid", False),
    "network_hour": ("dmo", "network", False),
    "award": ("dmo", "award", True),
    "settlement_statement": ("dmo", "statement", True),
    "day_summary": ("dmo", "summary", False),
    "rejection": ("dmo", "rejected", False),
    "receipt": ("dmo", "receipt", True),
    "registration": ("agent", "register", True),
    "bid": ("agent", "bid", True),
    "schedule": ("agent", "schedule", True),
    "meter_report": ("agent", "meter", True),
    "agent_day": ("agent", "day", True),
}
TOPIC_KINDS: dict[tuple[str, str], str] = {(role, topic): kind for kind, (role, topic, _) in ROUTES.items()}


def new_run_id() -> str:
    """A fresh run id, unique on this machine and readable: UTC start time plus 6 random hex digits."""
    return time.strftime("%Y%m%dT%H%M%S", time.gmtime()) + "-" + secrets.token_hex(3)


def check_run_id(run_id: str) -> str:
    if not isinstance(run_id, str) or not _RUN_ID.match(run_id):
        raise ValueError(f"run id {run_id!r} must match {RUN_ID_PATTERN}")
    return run_id


@dataclass(frozen=True)
class Keys:
    """Key expressions of one run. Pass ``agent="*"`` to any per-agent key for the pattern over all agents."""

    run_id: str

    def __post_init__(self):
        check_run_id(self.run_id)

    @property
    def prefix(self) -> str:
        return f"{ROOT}/{self.run_id}"

    def everything(self) -> str:
        return f"{self.prefix}/**"

    def _dmo(self, topic: str, agent: str | None = None) -> str:
        return f"{self.prefix}/dmo/{topic}" + ("" if agent is None else f"/{_agent_or_star(agent)}")

    def _agent(self, agent: str, topic: str) -> str:
        return f"{self.prefix}/agent/{_agent_or_star(agent)}/{topic}"

    def call_for_bids(self) -> str:
        return self._dmo("call_for_bids")

    def clock(self) -> str:
        return self._dmo("clock")

    def grid(self) -> str:
        return self._dmo("grid")

    def award(self, agent: str) -> str:
        return self._dmo("award", agent)

    def statement(self, agent: str) -> str:
        return self._dmo("statement", agent)

    def receipt(self, agent: str) -> str:
        return self._dmo("receipt", agent)

    def summary(self) -> str:
        return self._dmo("summary")

    def rejected(self) -> str:
        return self._dmo("rejected")

    def dmo_all(self) -> str:
        return f"{self.prefix}/dmo/**"

    def register(self, agent: str) -> str:
        return self._agent(agent, "register")

    def bid(self, agent: str) -> str:
        return self._agent(agent, "bid")

    def schedule(self, agent: str) -> str:
        return self._agent(agent, "schedule")

    def meter(self, agent: str) -> str:
        return self._agent(agent, "meter")

    def agent_day(self, agent: str) -> str:
        return self._agent(agent, "day")

    def agent_all(self, agent: str) -> str:
        return f"{self.prefix}/agent/{_agent_or_star(agent)}/**"

    def alive(self, name: str) -> str:
        if name != "*" and not is_name(name):
            raise ValueError(f"process name {name!r} must match {NAME_PATTERN}")
        return f"{self.prefix}/alive/{name}"

    def link(self, router: str, peer: str) -> str:
        """The liveliness token a router of a mesh holds while it has a link to the router ``peer`` (both by Zenoh
        id, hexadecimal; ``*`` for any), docs/hosts.md."""
        for zid in (router, peer):
            if zid != "*" and not _ZID.fullmatch(zid):
                raise ValueError(f"Zenoh id {zid!r} must be hexadecimal")
        return f"{self.prefix}/link/{router}/{peer}"

    def for_message(self, msg: Envelope) -> str:
        """The one key this message travels on."""
        role, topic, per_agent = ROUTES[msg.kind]
        if role == "dmo":
            return self._dmo(topic, msg.agent if per_agent else None)
        return self._agent(msg.sender, topic)


def _agent_or_star(agent: str) -> str:
    return agent if agent == "*" else check_agent_id(agent)


@dataclass(frozen=True)
class ParsedKey:
    """A received key split into its parts. role is "dmo", "agent" or "alive"; agent is the agent the key names
    (None on DMO broadcast keys); topic is e.g. "bid", "award", or for "alive" the process name."""

    run_id: str
    role: str
    agent: str | None
    topic: str

    @property
    def kind(self) -> str | None:
        """The message kind that belongs on this key (None for liveliness keys)."""
        return TOPIC_KINDS.get((self.role, self.topic))


def parse_key(key: str) -> ParsedKey:
    """Split a concrete key of the layout above; raises MessageError(code="wrong_key") for anything else."""
    parts = str(key).split("/")
    if len(parts) < 4 or parts[0] != ROOT or not _RUN_ID.match(parts[1]):
        raise MessageError(f"key {key!r} is not under {ROOT}/<run_id>/", "wrong_key")
    run_id, role, rest = parts[1], parts[2], parts[3:]
    if role == "dmo":
        if len(rest) == 1 and (role, rest[0]) in TOPIC_KINDS and not ROUTES[TOPIC_KINDS[role, rest[0]]][2]:
            return ParsedKey(run_id, role, None, rest[0])
        if len(rest) == 2 and (role, rest[0]) in TOPIC_KINDS and ROUTES[TOPIC_KINDS[role, rest[0]]][2] \
                and is_agent_id(rest[1]):
            return ParsedKey(run_id, role, rest[1], rest[0])
    elif role == "agent":
        if len(rest) == 2 and is_agent_id(rest[0]) and (role, rest[1]) in TOPIC_KINDS:
            return ParsedKey(run_id, role, rest[0], rest[1])
    elif role == "alive":
        if len(rest) == 1 and is_name(rest[0]):
            return ParsedKey(run_id, role, None if rest[0].lower() in RESERVED_NAMES else rest[0], rest[0])
    raise MessageError(f"key {key!r} is not a dmosim key", "wrong_key")


def agent_of(key: str) -> str | None:
    """The agent whose ``agent/<agent>/...`` key this is, if it is one and names a valid agent id (anything can
    arrive on the wire: only a valid id may go into an incident, a Rejection or a budget); else None."""
    parts = str(key).split("/", 4)
    if len(parts) > 3 and parts[2] == "agent" and is_agent_id(parts[3]):
        return parts[3]
    return None


def sender_matches_key(key: str, msg: Envelope) -> bool:
    """Whether the message's sender (and, on per-agent DMO keys, its addressee) is the one its key names."""
    try:
        check_route(key, msg)
    except MessageError:
        return False
    return True


def check_route(key: str, msg: Envelope, run_id: str | None = None) -> ParsedKey:
    """Refuse a message that does not belong on the key it arrived on: another run (code "wrong_key"), a kind
    that does not go there ("wrong_key"), or a sender other than the key's owner ("unauthorised")."""
    parsed = parse_key(key)
    if run_id is not None and parsed.run_id != run_id:
        raise MessageError(f"key {key!r} belongs to run {parsed.run_id!r}, not {run_id!r}", "wrong_key")
    if parsed.kind != msg.kind:
        raise MessageError(f"a {msg.kind} message does not belong on {key!r}", "wrong_key")
    owner = DMO if parsed.role == "dmo" else parsed.agent
    if msg.sender != owner:
        raise MessageError(f"sender {msg.sender!r} may not publish on {key!r}", "unauthorised")
    if parsed.role == "dmo" and parsed.agent is not None and msg.agent != parsed.agent:
        raise MessageError(f"{msg.kind} for {msg.agent!r} published on {key!r}", "wrong_key")
    return parsed


def relative_key(key: str, prefix: str) -> str:
    """``key`` without the run prefix ``prefix`` (``dmosim/<run>``), e.g. ``agent/mg1/meter``; another key as is."""
    return key[len(prefix) + 1:] if prefix and key.startswith(prefix + "/") else key


def key_pattern(pattern: str) -> re.Pattern:
    """A key pattern relative to the run prefix: ``*`` matches within one level, ``**`` across levels, ``?`` one
    character; e.g. ``dmo/*``, ``agent/*/meter``, ``dmo/award/mg*``, ``**/mg1/**``. Zenoh's key expressions
    (whole-level ``*`` and ``**``) mean the same here."""
    text = pattern.strip().strip("/")
    out, i = [], 0
    while i < len(text):
        if text.startswith("**/", i):
            out.append("(?:.*/)?")
            i += 3
        elif text.startswith("**", i):
            out.append(".*")
            i += 2
        elif text[i] == "*":
            out.append("[^/]*")
            i += 1
        elif text[i] == "?":
            out.append("[^/]")
            i += 1
        else:
            out.append(re.escape(text[i]))
            i += 1
    return re.compile("^" + "".join(out) + "$")
