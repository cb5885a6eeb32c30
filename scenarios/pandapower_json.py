"""A pandapower net's tables as plain data, read from its JSON file with the standard json module or taken from a net
in memory: never by a deserialiser that imports or builds what a file names (docs/network.md, "A pandapower net as
a feeder").

pandapower writes a net (``pandapower.to_json``) as one JSON object ``{"_module": "pandapower.auxiliary", "_class":
"pandapowerNet", "_object": {...}}`` whose ``_object`` holds each table as ``{"_module": "pandas.core.frame",
"_class": "DataFrame", "_object": "<the table as JSON text>", "orient": "split", "dtype": {...}}``, the text being
pandas' "split" form ``{"columns": [...], "index": [...], "data": [[...], ...]}``. pandapower's own reader imports
whatever module a ``_module`` names before it checks anything; here a ``_module`` or ``_class`` other than those two
is refused, and only the tables and columns of ``TABLES_READ`` are parsed at all.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from scenarios.case import read_text

# The largest network file read as JSON: a 5,000-bus feeder (scenarios.network.MAX_BUSES) with the geodata of its
# buses and lines, its loads and its static generators is about 2.5 MB. A larger file is refused from its size,
# before it is read; one this size parses into at most about 130 MB, however it is made.
MAX_NETWORK_BYTES = 4 << 20
NET = ("pandapower.auxiliary", "pandapowerNet")
TABLE = ("pandas.core.frame", "DataFrame")
# The tables read and the columns read of each; every other table and column of the file is left as it is, unparsed.
TABLES_READ = {
    "bus": ("vn_kv", "in_service", "min_vm_pu", "max_vm_pu"),
    "ext_grid": ("bus", "in_service"),
    "line": ("from_bus", "to_bus", "length_km", "r_ohm_per_km", "x_ohm_per_km", "max_i_ka", "parallel",
             "in_service"),
    "load": ("bus", "p_mw", "q_mvar", "scaling", "in_service"),
    "sgen": ("bus", "p_mw", "q_mvar", "scaling", "in_service"),
    "trafo": (),  # refused if it has a row: only its rows are counted
    "trafo3w": (),
}
REQUIRED_TABLES = ("bus", "ext_grid", "line")  # a table of TABLES_READ missing from the file is otherwise empty
OPTIONAL_COLUMNS = ("min_vm_pu", "max_vm_pu")  # a column of TABLES_READ missing from its table is otherwise refused


@dataclass(frozen=True)
class Table:
    """One table of a net: its row labels (``index``) and the columns read, each a list of one value per row as JSON
    has it (a number, a string, true or false); pandas' NaN, JSON's null, is ``math.nan``."""

    index: tuple
    columns: Mapping[str, list]

    def __len__(self) -> int:
        return len(self.index)


def net_tables(net) -> dict[str, Table]:
    """The tables of a pandapower net in memory (pandapower's own feeders, ``pandapower.networks``), as a file's
    would be read: the same columns, the same values."""
    out = {}
    for name in TABLES_READ:
        frame = getattr(net, name, None)
        if frame is not None:
            out[name] = _table(name, frame.index.tolist(), list(frame.columns), lambda c: frame[c].tolist(), ValueError)
    return _complete(out, ValueError)


def read_tables(path: Path, error: type[Exception]) -> dict[str, Table]:
    """The tables of ``TABLES_READ`` of the pandapower net that the JSON file ``path`` holds; ``error``, one line naming
    the file, when it is larger than ``MAX_NETWORK_BYTES`` (said before reading it), not JSON, not a pandapower net
    as ``pandapower.to_json`` writes one, names a ``_module`` or ``_class`` other than its net's and its tables', or
    lacks a table or column that is read."""
    where = f"network file {path}"

    def fail(why: str) -> Exception:
        return error(f"{where}: {why}")

    named = {NET: 0, TABLE: 0}  # how many objects name each, wherever they are
    doc = _loads(read_text(path, "network", error, MAX_NETWORK_BYTES), fail, named)
    if not isinstance(doc, dict) or (doc.get("_module"), doc.get("_class")) != NET or not isinstance(
            doc.get("_object"), dict):
        raise fail('not a pandapower JSON: its top level must be {"_module": "pandapower.auxiliary", "_class": '
                   '"pandapowerNet", "_object": {...}}, as pandapower.to_json writes a net')
    tables = sum(isinstance(t, dict) and (t.get("_module"), t.get("_class")) == TABLE for t in doc["_object"].values())
    if named != {NET: 1, TABLE: tables}:
        raise fail("a pandapower net or table inside something else: only the net at the top level, and its tables "
                   "right inside it, are read")
    out = {}
    for name in TABLES_READ:
        if name in doc["_object"]:
            out[name] = _split(name, doc["_object"][name], fail)
    return _complete(out, error, where)


class _Named(Exception):
    """An object named a ``_module`` or ``_class`` it may not: raised from inside the JSON parser, at once."""


def _loads(text: str, fail, named: dict[tuple, int]) -> object:
    """JSON text as Python data: dicts, lists, strings, numbers, booleans and None, nothing else. Every object that
    names a ``_module`` or ``_class`` is counted in ``named`` if it names one of its keys (NET, TABLE), and refused
    as it is parsed otherwise: the hooks by which a deserialiser would import or build something. (A table's cells
    are never built into anything either: one that is not the number or flag a column read needs is refused where
    it is read.)"""

    def hook(obj: dict) -> dict:
        if "_module" in obj or "_class" in obj:
            pair = (obj.get("_module"), obj.get("_class"))
            known = next((key for key in named if key == pair), None)  # a pair of lists is no key, nor hashable
            if known is None:
                raise _Named(pair)
            named[known] += 1
        return obj

    try:
        return json.loads(text, object_hook=hook)
    except _Named as exc:
        module, cls = (repr(v)[:80] for v in exc.args[0])
        raise fail(f"an object names _module {module}, _class {cls}: a feeder is data, and only pandapower's net "
                   f"({'.'.join(NET)}) and its tables ({'.'.join(TABLE)}) are read") from None
    except RecursionError:
        raise fail("not a pandapower JSON: nested too deep") from None
    except ValueError as exc:  # JSONDecodeError, and an integer of more digits than Python converts
        raise fail(f"not a pandapower JSON: {exc}") from None


def _split(name: str, frame: object, fail) -> Table:
    """Table ``name`` from its DataFrame object: the JSON text of its "split" form, parsed and checked."""
    if not isinstance(frame, dict) or not isinstance(frame.get("_object"), str):
        raise fail(f"table {name}: not a pandas DataFrame as pandapower writes one")
    if frame.get("orient") != "split" or frame.get("is_multiindex") or frame.get("is_multicolumn"):
        raise fail(f"table {name}: written in orient {frame.get('orient')!r} or with a multi-index; pandapower "
                   "writes its tables as \"split\" with a plain index and plain columns")
    data = _loads(frame["_object"], fail, {})  # a table is plain data: no object in it may name a class
    if not isinstance(data, dict) or not all(isinstance(data.get(k), list) for k in ("columns", "index", "data")):
        raise fail(f"table {name}: not a table in pandas' \"split\" form (columns, index, data)")
    columns, index, rows = data["columns"], data["index"], data["data"]
    if len(rows) != len(index) or not all(isinstance(r, list) and len(r) == len(columns) for r in rows):
        raise fail(f"table {name}: {len(index)} row labels and {len(rows)} rows, each of which must have one value "
                   f"per column ({len(columns)})")
    at = {c: k for k, c in enumerate(columns) if isinstance(c, str)}
    if len(at) != len(columns):
        raise fail(f"table {name}: its columns must be distinct strings")
    return _table(name, index, columns, lambda c: [row[at[c]] for row in rows], lambda why: fail(why))


def _table(name: str, index: list, columns: list, values, error) -> Table:
    """A Table of the columns of ``TABLES_READ[name]`` that ``columns`` has (``values(column)`` gives one), null and NaN
    as NaN; ``error`` when a column read is missing."""
    missing = [c for c in TABLES_READ[name] if c not in columns and c not in OPTIONAL_COLUMNS]
    if missing:
        raise error(f"table {name}: no column {missing[0]!r} (dmosim reads {', '.join(TABLES_READ[name])})")
    read = {c: [math.nan if v is None else v for v in values(c)] for c in TABLES_READ[name] if c in columns}
    return Table(tuple(index), read)


def _complete(tables: dict[str, Table], error, where: str = "pandapower net") -> dict[str, Table]:
    """Every table of ``TABLES_READ``: one missing is empty, unless it is required."""
    missing = [t for t in REQUIRED_TABLES if t not in tables]
    if missing:
        raise error(f"{where}: no table {missing[0]!r} (a feeder needs {', '.join(REQUIRED_TABLES)})")
    return {name: tables.get(name, Table((), {})) for name in TABLES_READ}
