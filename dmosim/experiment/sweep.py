"""A sweep: one experiment run once per combination of values of some of its settings (``dmosim sweep``).

``--set market.penalty=100,150,300 --set schedule.scenarios=1,3`` gives six variants, every combination, in the
order the values were given (the last key varying fastest). Each variant is the experiment with those settings
replaced and validated again, so a bad value is refused before anything runs.
"""

from __future__ import annotations

import itertools
import math
import re
from dataclasses import dataclass

from scenarios.case import parse_toml

from .spec import Experiment, ExperimentError, with_settings

# Runs of one sweep: each is a whole ``dmosim run`` (a week of 3 agents took 80 s, docs/settlement.md), so 1,000
# is a day of runs at that size; the combinations are counted before any is made.
MAX_VARIANTS = 1000


@dataclass(frozen=True)
class Variant:
    """One run of a sweep: its settings (dotted key -> value), its experiment and a name for its directory."""

    settings: dict[str, object]
    experiment: Experiment
    label: str


def parse_setting(text: str) -> tuple[str, list]:
    """``KEY=V1,V2,...`` -> (key, values). Values are read as TOML (numbers, true/false, quoted strings, arrays such
    as ``[1,0.8],[1,0.9]``); values that are not TOML are taken as bare strings (``market.mode=bids,fixed``)."""
    key, sep, rhs = text.partition("=")
    key = key.strip()
    if not sep or not re.fullmatch(r"[a-z_]+(\.[a-z_]+)*", key) or not rhs.strip():
        raise ExperimentError(f"--set {text!r}: expected KEY=V1,V2,... with a dotted key, e.g. market.penalty=100,300")
    if rhs.strip().startswith(",") or rhs.strip().endswith(",") or re.search(r",\s*,", rhs):
        raise ExperimentError(f"--set {text!r}: an empty value")
    try:
        values = parse_toml(f"v = [{rhs}]", f"--set {key}", ExperimentError)["v"]
    except ExperimentError:  # not TOML (or nested too deep for it): bare words
        values = [v.strip() for v in rhs.split(",")]
    if len(values) > MAX_VARIANTS:
        raise ExperimentError(f"--set {key}: {len(values)} values; a sweep has at most {MAX_VARIANTS} runs")
    if not values or any(v == "" for v in values):
        raise ExperimentError(f"--set {text!r}: an empty value")
    if len(set(map(repr, values))) != len(values):
        raise ExperimentError(f"--set {text!r}: a value is given twice")
    return key, values


def variants(experiment: Experiment, settings: list[tuple[str, list]]) -> list[Variant]:
    """Every combination of the swept values, each validated (``ExperimentError`` names the first bad one)."""
    keys = [key for key, _ in settings]
    if len(set(keys)) != len(keys):
        raise ExperimentError(f"--set: {next(k for k in keys if keys.count(k) > 1)} is swept twice")
    runs = math.prod(len(values) for _, values in settings)
    if runs > MAX_VARIANTS:
        raise ExperimentError(f"--set: {runs:,} runs; a sweep has at most {MAX_VARIANTS}")
    combinations = list(itertools.product(*(values for _, values in settings)))
    out = []
    for i, combination in enumerate(combinations, start=1):
        chosen = dict(zip(keys, combination))
        label = f"{i:03d}-" + "-".join(f"{k.rsplit('.', 1)[-1]}={_short(v)}" for k, v in chosen.items())
        out.append(Variant(chosen, with_settings(experiment, chosen, f"--set {_describe(chosen)}"), label))
    return out


def _short(value) -> str:
    """A value as it can stand in a directory name."""
    text = ",".join(map(str, value)) if isinstance(value, list) else str(value)
    return re.sub(r"[^A-Za-z0-9.,_+-]", "_", text)[:40]


def _describe(settings: dict) -> str:
    return " ".join(f"{k}={v!r}" for k, v in settings.items())
