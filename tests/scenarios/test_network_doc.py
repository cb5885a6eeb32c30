"""docs/network.md is the network file's contract: a row for every field the reader accepts and none for a field it
refuses, per table, and the default load profile as the code has it."""

import re
from pathlib import Path

import pytest

import scenarios.network as network

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
