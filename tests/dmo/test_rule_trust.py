"""A rule's name is checked without loading it, and a rule that a file names is loaded only when trusted
(dmo/market/choice.py ``rule_name``, ``Trust``): parsing any experiment imports nothing."""

from __future__ import annotations

import pytest

from dmosim.experiment.spec import ExperimentError, parse_experiment
from dmo.market.choice import Trust, UntrustedRule, choose, rule_name

RULE = '''from pathlib import Path

Path(__file__).with_name("imported.txt").write_text("imported")

from dmo.market.rules import BUILT_IN


def rule(day, **params):
    return BUILT_IN["paper"](day, penalty=150.0, credit=0.0)
'''


@pytest.fixture
def own(tmp_path, monkeypatch):
    """A rule of one's own in the current directory, whose import leaves imported.txt beside it."""
    (tmp_path / "mine.py").write_text(RULE)
    monkeypatch.chdir(tmp_path)
    return tmp_path


def test_a_name_is_checked_without_importing_anything(own):
    assert rule_name("mine.py:rule:cap=5").params == {"cap": 5.0} and not rule_name("mine.py:rule").built_in
    assert rule_name("deadband:band_mw=0.5").built_in
    experiment = parse_experiment({"market": {"settlement": "mine.py:rule"}})  # a run directory's, a recording's
    assert experiment.market.settlement == "mine.py:rule"
    assert not (own / "imported.txt").exists()
    choose("mine.py:rule")  # the user names it: loaded and tried
    assert (own / "imported.txt").exists()


@pytest.mark.parametrize("spec, reason", [
    ("mine.py:not-a-name", "'not-a-name' is not a function name"),
    ("bad module:f", "'bad module' is neither path/to/rules.py nor a module name"),
    (":f", "'' is neither path/to/rules.py nor a module name"),
    (" ", "no settlement rule named"),
    ("nosuch", "unknown settlement rule 'nosuch'"),
    ("deadband:width=1", "deadband has no parameter 'width'"),
    ("paper:penalty=-1", "penalty must be a number in 0..1,000,000, got -1.0"),
])
def test_a_malformed_name_is_one_line_in_an_experiment_too(own, spec, reason):
    with pytest.raises(ValueError, match=reason):
        rule_name(spec)
    with pytest.raises(ExperimentError, match=f"market.settlement: .*{reason}"):
        parse_experiment({"market": {"settlement": spec}}, "exp.toml")
    assert not (own / "imported.txt").exists()


def test_a_rule_a_file_names_is_loaded_only_when_trusted(own):
    with pytest.raises(UntrustedRule) as err:
        Trust().choose("mine.py:rule:cap=1")
    assert err.value.spec == "mine.py:rule:cap=1" and not (own / "imported.txt").exists()
    assert Trust().choose("deadband").name == "deadband"  # a built-in runs no code of the file's
    assert not Trust.of(False, ["paper", "mine.py:other"]).allows("mine.py:rule")  # another function
    assert not Trust.of(False, ["elsewhere/mine.py:rule"]).allows("mine.py:rule")  # another file
    assert not (own / "imported.txt").exists()
    assert Trust.of(False, [f"{own}/mine.py:rule:cap=2"]).allows("./mine.py:rule:cap=1")  # the same code
    Trust(everything=True).choose("mine.py:rule")
    assert (own / "imported.txt").exists()
