"""The experiment loader under random input (hypothesis): random TOML documents and structures, deep nesting, huge
numbers, wrong types and unicode. ``parse_experiment``, ``load_experiment`` and ``dmosim run --check`` in-process
either accept the input or refuse it with one ``ExperimentError`` line (exit 2): never a traceback, never an
exception of another kind, and never stuck on an example (hypothesis' deadline: 30 s, a guard against a hang, not a
timing; an example takes milliseconds, seconds on a loaded machine). A search of 750 documents takes several seconds:
the slow tier, beside the processes' fuzzing (tests/system/test_fuzz.py); tests/dmosim/test_experiment.py checks
the loader's refusals one by one in the fast tier."""

from __future__ import annotations

import copy
import datetime as dt
import json
import math
import tempfile
import tomllib
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dmosim.cli import main
from dmosim.experiment.spec import Experiment, ExperimentError, load_experiment, parse_experiment, to_toml
from dmo.market.rules import BUILT_IN

pytestmark = pytest.mark.slow

FUZZ = settings(deadline=dt.timedelta(seconds=30), max_examples=150,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
DEFAULTS = json.loads(Experiment().model_dump_json(exclude_none=True))
PATHS = [(key,) for key, value in DEFAULTS.items() if not isinstance(value, dict)] + [
    (section, key) for section, table in DEFAULTS.items() if isinstance(table, dict)
    for key in {**table, **dict.fromkeys(Experiment.model_fields[section].annotation.model_fields)}]
KEYS = sorted({part for path in PATHS for part in path})

huge = st.sampled_from([2**31, 2**32, 2**63, -2**63 - 1, 10**30, 10**4000, -1, 0, 1024, 1025, 3660, 3661])
scalars = st.one_of(st.booleans(), st.integers(), huge, st.floats(), st.text(max_size=30),
                    st.sampled_from(["paper", "deadband:band_share=2", "kill:mg1:3", "9999-12-31", "2026-07-01",
                                     "\u00b2", "mg\u0663", "", "../../etc/passwd", "/dev/zero", "\x7f\x00"]),
                    st.dates())
keys = st.one_of(st.sampled_from(KEYS), st.text(max_size=8))
values = st.recursive(scalars, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(keys, inner, max_size=4),
                      max_leaves=12)


def harmless(data):
    """``data`` with any settlement rule of one's own replaced: a random ``module:function`` could name something
    that must not be called on a trial day (a rule of one's own is loaded only when the user names it)."""
    if isinstance(data, dict):
        return {k: ("paper" if k == "settlement" and isinstance(v, str) and ":" in v
                    and v.split(":", 1)[0].strip() not in BUILT_IN else harmless(v)) for k, v in data.items()}
    if isinstance(data, list):
        return [harmless(v) for v in data]
    return data


@st.composite
def mutated(draw):
    """A valid experiment with one to three of its settings, at any depth, replaced by anything."""
    data = copy.deepcopy(DEFAULTS)
    for _ in range(draw(st.integers(1, 3))):
        *where, last = draw(st.sampled_from(PATHS))
        node = data
        for part in where:
            node = node[part] if isinstance(node.get(part), dict) else node.setdefault(part, {})
        node[last] = draw(values)
    return harmless(data)


documents = st.one_of(mutated(), st.dictionaries(keys, values, max_size=6).map(harmless))


def toml_string(text: str) -> str:
    return json.dumps(text, ensure_ascii=False).replace("\x7f", "\\u007f")


def toml_value(value) -> str:
    """Any of the values above as TOML (inline tables and arrays), so that every document can be written."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf") if math.isinf(value) else repr(value)
    if isinstance(value, str):
        return toml_string(value)
    if isinstance(value, dt.date):
        return value.isoformat()
    if isinstance(value, list):
        return "[" + ", ".join(map(toml_value, value)) + "]"
    return "{" + ", ".join(f"{toml_string(k)} = {toml_value(v)}" for k, v in value.items()) + "}"


def toml_document(data: dict) -> str:
    return "".join(f"{toml_string(k)} = {toml_value(v)}\n" for k, v in data.items())


def accepted_or_one_line(parse) -> Experiment | None:
    try:
        return parse()
    except ExperimentError as exc:
        assert str(exc) and "\n" not in str(exc), repr(exc)
        return None


def check_on_the_command_line(path: Path, capsys) -> None:
    code = main(["run", str(path), "--check"])
    out, err = capsys.readouterr()
    assert code in (0, 2), err
    assert "Traceback" not in err and (code == 0 or err.count("\n") == 1), err


# Each setting at each of these, not left to chance: wrong types, edges and values far past any bound.
EDGES = [-1, 0, 1, 2, 2**31, 2**32, 2**63, 10**9, 10**30, -1.0, 0.5, 1e300, math.inf, -math.inf, math.nan, True, "",
         "x" * 5000, "a\nb", "9999-12-31", "2026-07-01", "paper", [], [1.0] * 1000, [[[[]]]], {}, {"a": 1}]


def test_every_setting_at_every_edge_is_an_experiment_or_one_line(capsys):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "edge.toml"
        for *where, last in PATHS:
            for value in EDGES:
                data = copy.deepcopy(DEFAULTS)
                (data[where[0]] if where else data)[last] = value
                if accepted_or_one_line(lambda: parse_experiment(data, "edge.toml")) is not None:
                    path.write_text(toml_document(data))  # what parses must also pass or fail --check in one line
                    check_on_the_command_line(path, capsys)


@FUZZ
@given(data=documents)
def test_any_structure_is_an_experiment_or_one_line(data):
    experiment = accepted_or_one_line(lambda: parse_experiment(data, "fuzz.toml"))
    if experiment is not None:  # what is accepted is written and read back as the same experiment
        assert parse_experiment(tomllib.loads(to_toml(experiment))) == experiment


@FUZZ
@given(data=documents)
def test_any_toml_document_is_an_experiment_or_one_line_on_the_command_line_too(data, capsys):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "fuzz.toml"
        path.write_text(toml_document(data))
        accepted_or_one_line(lambda: load_experiment(path))
        check_on_the_command_line(path, capsys)


@FUZZ
@given(text=st.one_of(st.text(max_size=300), st.binary(max_size=300).map(lambda b: b.decode("latin-1"))))
def test_any_text_is_an_experiment_or_one_line(text, capsys):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "fuzz.toml"
        path.write_bytes(text.encode("utf-8", "surrogatepass"))
        accepted_or_one_line(lambda: load_experiment(path))
        check_on_the_command_line(path, capsys)


@FUZZ
@given(st.integers(1, 20_000), st.sampled_from(["[", "{a = ", "[{b = "]), st.sampled_from(["", "seed = 1\n"]))
def test_deep_nesting_is_refused_in_one_line(depth, opener, before):
    closer = {"[": "]", "{a = ": "}", "[{b = ": "}]"}[opener]
    text = before + "x = " + opener * depth + "1" + closer * depth + "\n"
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "deep.toml"
        path.write_text(text)
        accepted_or_one_line(lambda: load_experiment(path))
