"""The order in which agents are listed in tables, summaries and figures: by name, with the numbers in a name read
as numbers, so that mg2 comes before mg10."""

from __future__ import annotations

import re


def natural(name: str) -> tuple:
    """The sort key of an agent's name: its text with its numbers read as numbers."""
    return tuple((0, int(part), "") if part.isdigit() else (1, 0, part) for part in re.split(r"(\d+)", name))


def by_agent(column):
    """A ``key`` for ``DataFrame.sort_values``: an ``agent`` column in natural order, every other as it is."""
    if column.name != "agent":
        return column
    rank = {name: i for i, name in enumerate(sorted(column.unique(), key=natural))}
    return column.map(rank)
