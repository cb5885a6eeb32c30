"""TOML text from plain data (what a case, a fleet or an experiment file holds), which ``tomllib`` reads back to the
same data: tables as ``[name]``, lists of tables as ``[[name]]``, tables inside those inline; None is left out.
"""

from __future__ import annotations

import json
import math
import re

_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


def toml_text(data: dict, comment: str = "") -> str:
    """``data`` as a TOML document, opening with ``comment`` (one ``#`` line per line of it)."""
    lines = [f"# {line}".rstrip() for line in comment.splitlines()]
    lines += _table(data, ())
    return "\n".join(lines).lstrip("\n") + "\n"


def toml_value(value) -> str:
    """One value as TOML writes it inline (a table as ``{ key = value, ... }``)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return json.dumps(value)
    if isinstance(value, str):  # JSON's escapes are TOML's, but for surrogate pairs (kept raw here) and DEL
        return json.dumps(value, ensure_ascii=False).replace("\x7f", "\\u007f")
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else ("nan" if math.isnan(value) else "inf" if value > 0 else "-inf")
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        inner = ", ".join(f"{_key(k)} = {toml_value(v)}" for k, v in value.items() if v is not None)
        return "{ " + inner + " }" if inner else "{}"
    raise TypeError(f"cannot write {value!r} to TOML")


def _key(key: str) -> str:
    return key if _BARE_KEY.fullmatch(key) else json.dumps(key, ensure_ascii=False)


def _tables(value) -> bool:
    return isinstance(value, list) and bool(value) and all(isinstance(v, dict) for v in value)


def _table(data: dict, path: tuple[str, ...]) -> list[str]:
    """The lines of a table: its plain keys, then its tables and lists of tables (whose own tables are inline)."""
    lines = [f"{_key(k)} = {toml_value(v)}" for k, v in data.items()
             if v is not None and not isinstance(v, dict) and not _tables(v)]
    for k, v in data.items():
        name = ".".join(map(_key, (*path, k)))
        if isinstance(v, dict):
            lines += ["", f"[{name}]", *_table(v, (*path, k))]
        elif _tables(v):
            for item in v:
                lines += ["", f"[[{name}]]"] + [f"{_key(ik)} = {toml_value(iv)}" for ik, iv in item.items()
                                                if iv is not None]
    return lines
