"""docs/network.md is the network file's contract: a row for every field the reader accepts and none for a field it
refuses, per table, the default load profile and the limits as the code has them, and every pandapower table and
column the JSON reader reads."""

import importlib
import re
from pathlib import Path

import pytest

import scenarios.network as network
import scenarios.pandapower_json as pandapower_json

DOC = (Path(__file__).resolve().parents[2] / "docs" / "network.md").read_text()
FILE_FORMAT = DOC.split("\n## The network file\n", 1)[1].split("\n## ", 1)[0]


def _rows(heading: str) -> list[str]:
    section = FILE_FORMAT.split(f"\n### {heading}\n", 1)[1].split("\n### ", 1)[0]
    return re.findall(r"^\| `(\w+)` \|", section, flags=re.MULTILINE)


@pytest.mark.parametrize("heading, fields", [("Top level", network._TOP), ("`[[buses]]`", network._BUS),
                                             ("`[[lines]]`", network._LINE)])
def test_every_field_has_one_row_and_every_row_is_a_field(heading, fields):
    rows = _rows(heading)
    assert sorted(rows) == sorted(fields), f"docs/network.md, {heading}: rows {rows}, fields {fields}"


def test_the_default_load_profile_is_the_code_s():
    section = DOC.split("\n## The default load profile\n", 1)[1].split("\n## ", 1)[0]
    values = [float(v) for row in re.findall(r"^\| multiplier \|(.*)\|$", section, flags=re.MULTILINE)
              for v in row.split("|")]
    assert tuple(values) == network.LOAD_PROFILE


def _limits() -> dict[str, str]:
    section = FILE_FORMAT.split("\n### Limits\n", 1)[1]
    return dict(re.findall(r"^\| `([\w.]+)` \| ([^|]+?) \|", section, flags=re.MULTILINE))


def _value(text: str):
    """A value as the table writes it: 5,000; 1e-6; 0.1 to 1,000; 8 MiB."""
    if " to " in text:
        return tuple(_value(part) for part in text.split(" to "))
    number, _, unit = text.partition(" ")
    return float(number.replace(",", "")) * {"": 1, "MiB": 1 << 20}[unit]


def test_the_limits_table_is_the_code_s():
    limits = _limits()
    for dotted, text in limits.items():
        module, name = dotted.rsplit(".", 1)
        assert getattr(importlib.import_module(module), name) == _value(text), f"docs/network.md, Limits: {dotted}"
    # every bound of a feeder's names and numbers is in the table (the rating rule's floor is a default, not a bound)
    bounds = {f"scenarios.network.{n}" for n in vars(network) if re.fullmatch(r"(MAX|MIN)_\w+|\w+_RANGE", n)}
    assert bounds - {"scenarios.network.MIN_RATING_MVA"} <= set(limits), bounds - set(limits)


def test_the_pandapower_section_names_every_table_and_column_read():
    section = DOC.split("\n## A pandapower net as a feeder\n", 1)[1].split("\n## ", 1)[0]
    for table, columns in pandapower_json.TABLES_READ.items():
        assert f"`{table}`" in section, table
        for column in columns:
            assert f"`{column}`" in section, f"{table}.{column}"
