"""Code a user names for dmosim to run (a settlement rule, a bidding strategy): ``where:name[:key=value,...]``, split
and checked as a name without importing anything, identified by the code it would run, and loaded.

``where`` is a file (``path/to/code.py``, resolved against the current directory) or a module name; ``name`` the
function or class in it; the parameters are numbers. A ``CodeKind`` names the kind of code in every message
("settlement rule", "strategy"), so each error is one line saying what was named and what is wrong with it. What
may be loaded when a file rather than the user names the code is ``dmo.market.choice.Trust``'s to say, by
``code_of``.
"""

from __future__ import annotations

import importlib
import importlib.util
import math
import sys
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class CodeKind:
    """What kind of code a spec names, for its messages: ``what`` ("settlement rule"), ``thing`` ("function"),
    ``example`` of a file ("path/to/rules.py"), and ``prefix`` of the module name a loaded file gets."""

    what: str
    thing: str
    example: str
    prefix: str


def split_spec(spec: str, kind: CodeKind) -> tuple[str, dict[str, float]]:
    """``target[:key=value,...]`` -> (target, {key: value}); ValueError, one line, for a parameter that is not
    key=number or an empty spec."""
    spec = spec.strip()
    target, _, last = spec.rpartition(":")
    if not target or "=" not in last:
        target, last = spec, ""
    params = {}
    for item in filter(None, (p.strip() for p in last.replace(";", ",").split(","))):
        key, eq, value = item.partition("=")
        try:
            number = float(value)
        except ValueError:
            number = math.nan
        if not eq or not key.strip() or not math.isfinite(number):
            raise ValueError(f"{kind.what} {target}: {item!r} is not key=number")
        params[key.strip()] = number
    if not target:
        raise ValueError(f"no {kind.what} named")
    return target, params


def params_text(params) -> str:
    """Parameters as a spec writes them again, each number at its shortest exact form: ``band_mw=0.5,rate=150``."""
    return ",".join(f"{k}={_number(v)}" for k, v in params.items())


def _number(v: float) -> str:
    text = repr(float(v))
    return text[:-2] if text.endswith(".0") else text


def is_file(where: str) -> bool:
    """Whether a target's ``where`` names a file (path/to/code.py) rather than a module."""
    return where.endswith(".py") or "/" in where


def check_target(target: str, kind: CodeKind) -> None:
    """``where:name`` checked as a name, importing nothing; ValueError, one line, when ``name`` is no identifier or
    ``where`` neither a file nor a module name."""
    where, _, name = target.rpartition(":")
    if not name.isidentifier():
        raise ValueError(f"{kind.what} {target}: {name!r} is not a {kind.thing} name")
    if not where or not (is_file(where) or all(part.isidentifier() for part in where.split("."))):
        raise ValueError(f"{kind.what} {target}: {where!r} is neither {kind.example} nor a module name")


def code_of(target: str) -> str:
    """The code ``where:name`` would run, as loading it would find it: a file resolved against the current
    directory, a module by name. Two targets with the same code run the same function or class."""
    where, _, name = target.rpartition(":")
    return f"{Path(where).resolve()}:{name}" if is_file(where) else target


def load(target: str, kind: CodeKind):
    """The object ``path/to/code.py:name`` or ``module:name`` names, its module imported, so its code runs; ValueError,
    one line, when there is no such file, the module fails to import or has no such callable."""
    where, _, name = target.rpartition(":")
    try:
        if is_file(where):
            path = Path(where)
            if not path.is_file():
                raise ValueError(f"{kind.what} {target}: no file {where}")
            module_name = f"{kind.prefix}{abs(hash(str(path.resolve())))}"
            spec = importlib.util.spec_from_file_location(module_name, path)
            module = importlib.util.module_from_spec(spec)
            sys.modules[module_name] = module  # dataclasses and pickling look the module up by name
            spec.loader.exec_module(module)
        else:
            module = importlib.import_module(where)
    except ValueError:
        raise
    except Exception as err:  # a user's module may fail to import in any way: say how, in one line
        raise ValueError(f"{kind.what} {target}: cannot load {where}: {type(err).__name__}: {err}") from None
    found = getattr(module, name, None)
    if not callable(found):
        raise ValueError(f"{kind.what} {target}: {where} has no {kind.thing} {name!r}")
    return found
