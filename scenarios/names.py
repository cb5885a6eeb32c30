"""Names of the processes of a run: the agent-id rule that fleet files, the wire and access control all apply.

An agent id names a microgrid in a fleet file, on its keys (``agent/<id>/...``), as a message's sender and as a
Zenoh user; the DMO and the recorder have reserved names no agent may take.
"""

from __future__ import annotations

import re

NAME_PATTERN = r"^[A-Za-z][A-Za-z0-9_-]{0,31}$"
DMO = "dmo"
RECORDER = "recorder"
RESERVED_NAMES = (DMO, RECORDER)  # process names that no agent may take (compared case-insensitively)
_NAME = re.compile(NAME_PATTERN)


def is_name(name: object) -> bool:
    """Whether ``name`` is a valid process name (an agent id, or a reserved one)."""
    return isinstance(name, str) and bool(_NAME.match(name))


def is_agent_id(name: object) -> bool:
    return is_name(name) and name.lower() not in RESERVED_NAMES


def check_agent_id(agent: object) -> str:
    """``agent`` if it is a valid agent id; ValueError with a one-line reason otherwise."""
    if not is_name(agent):
        raise ValueError(f"agent id {agent!r} must match {NAME_PATTERN}")
    if agent.lower() in RESERVED_NAMES:
        raise ValueError(f"agent id {agent!r} is reserved")
    return agent
