"""A settlement rule and the market's penalty and credit never disagree unseen (docs/settlement.md, "The rule and the
market's penalty"), and every built-in rule's parameter has the range docs/settlement.md gives it."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from dmosim.cli import main
from dmosim.console import UsageError
from dmosim.cli.dmo import day_config_of
from dmosim.cli.settings import role_experiment
from dmosim.cli.main import build_parser
from dmosim.experiment.spec import Experiment, ExperimentError, parse_experiment, settled_by, with_settings
from dmosim.experiment.sweep import parse_setting, variants
from dmo.market.choice import choose
from dmo.market.rules import BUILT_IN, market_parameters

ROOT = Path(__file__).resolve().parents[2]
CASE_PENALTY = 150.0  # the paper case's


def test_the_table_of_parameters_and_their_ranges_is_the_code():
    doc = (ROOT / "docs" / "settlement.md").read_text()
    section = doc.split("### Parameters and their ranges", 1)[1].split("\n#", 1)[0]
    rows = re.findall(r"^\| `([\w-]+)` \| `(\w+)` \| ([\d.]+) \| ([\d,.]+)\.\.([\d,.]+) \|", section, re.M)
    number = lambda text: float(text.replace(",", ""))  # noqa: E731
    documented = {(rule, key): (number(default), number(low), number(high)) for rule, key, default, low, high in rows}
    code = {(rule.name, key): (rule.defaults[key], *rule.ranges[key]) for rule in BUILT_IN.values()
            for key in rule.defaults}
    assert documented == code
    assert all(set(rule.ranges) == set(rule.defaults) for rule in BUILT_IN.values())


@pytest.mark.parametrize("spec, says", [
    ("deadband:band_share=2", "deadband: band_share must be a number in 0..1, got 2.0"),
    ("price-linked:k=101", "price-linked: k must be a number in 0..100"),
    ("symmetric:below=1e7", "symmetric: below must be a number in 0..1,000,000"),
    ("paper:penalty=-1", "paper: penalty must be a number in 0..1,000,000"),
])
def test_a_parameter_outside_its_range_is_refused(spec, says, capsys):
    with pytest.raises(ValueError, match=re.escape(says)):
        choose(spec)
    assert main(["run", "--settlement", spec, "--check"]) == 2
    err = capsys.readouterr().err
    assert says in err and err.count("\n") == 1


def paper(given=None, penalty=None, credit=0.0):
    return market_parameters(BUILT_IN["paper"], given or {}, penalty, credit, CASE_PENALTY)


def test_paper_takes_what_it_is_not_given_from_the_market_and_refuses_a_rate_given_twice_differently():
    assert paper() == {"penalty": CASE_PENALTY, "credit": 0.0}
    assert paper(penalty=50.0, credit=5.0) == {"penalty": 50.0, "credit": 5.0}
    assert paper({"penalty": 80.0}) == {"penalty": 80.0, "credit": 0.0}
    assert paper({"penalty": 50.0}, penalty=50.0) == {"penalty": 50.0, "credit": 0.0}  # the same, given twice
    assert paper({"credit": 10.0}, penalty=50.0) == {"penalty": 50.0, "credit": 10.0}
    with pytest.raises(ValueError, match="paper:penalty=100 and a market penalty of 50 \\$/MWh disagree"):
        paper({"penalty": 100.0}, penalty=50.0)
    with pytest.raises(ValueError, match="paper:credit=10 and a market credit of 5"):
        paper({"credit": 10.0}, credit=5.0)


@pytest.mark.parametrize("name", ["symmetric", "deadband", "price-linked"])
def test_another_built_in_refuses_a_penalty_or_credit_it_would_ignore(name):
    rule = BUILT_IN[name]
    assert market_parameters(rule, {}, None, 0.0, CASE_PENALTY) == {}
    for penalty, credit in ((50.0, 0.0), (None, 5.0)):
        with pytest.raises(ValueError, match=f"settlement rule {name} prices every deviation by its own"):
            market_parameters(rule, {}, penalty, credit, CASE_PENALTY)


def test_a_rule_that_is_not_convex_takes_the_penalty_the_agents_schedule_against():
    rule = BUILT_IN["price-linked"]
    assert rule.always_convex({"credit": 50.0}) and not rule.always_convex({"credit": 60.0})
    assert not BUILT_IN["paper"].always_convex({"penalty": 10.0, "credit": 20.0})
    assert market_parameters(rule, {"credit": 60.0}, 50.0, 0.0, CASE_PENALTY) == {"credit": 60.0}
    for name in ("symmetric", "deadband"):  # convex whatever their parameters
        assert BUILT_IN[name].always_convex({key: high for key, (_, high) in BUILT_IN[name].ranges.items()})


@pytest.mark.parametrize("market, label", [
    ({}, "paper:penalty=150,credit=0"),
    ({"penalty": 50.0}, "paper:penalty=50,credit=0"),
    ({"settlement": "paper", "penalty": 50.0}, "paper:penalty=50,credit=0"),
    ({"settlement": "paper", "credit": 7.0}, "paper:penalty=150,credit=7"),
    ({"settlement": "paper:penalty=80"}, "paper:penalty=80,credit=0"),
    ({"settlement": "deadband"}, "deadband:rate=150,below_rate=0,band_mw=0,band_share=0.1"),
])
def test_an_experiment_says_which_rule_settles_it(market, label):
    assert settled_by(parse_experiment({"market": market}).market, CASE_PENALTY) == label
    own = Experiment().market.model_copy(update={"settlement": "rules.py:mine", "penalty": 50.0})
    assert settled_by(own, CASE_PENALTY) == "rules.py:mine"  # a rule of one's own settles as it is written


@pytest.mark.parametrize("market, says", [
    ({"settlement": "paper:penalty=100", "penalty": 50.0}, "paper:penalty=100 and a market penalty of 50"),
    ({"settlement": "deadband", "penalty": 150.0}, "settlement rule deadband prices every deviation"),
    ({"settlement": "symmetric", "credit": 5.0}, "settlement rule symmetric prices every deviation"),
])
def test_an_experiment_whose_rule_and_rates_disagree_is_refused(market, says):
    with pytest.raises(ExperimentError, match=re.escape(says)) as err:
        parse_experiment({"market": market}, "exp.toml")
    assert str(err.value).startswith("exp.toml: market: ") and "\n" not in str(err.value)


def test_run_check_names_the_rule_the_days_are_settled_by(capsys):
    assert main(["run", "--settlement", "paper", "--penalty", "50", "--check"]) == 0
    assert "settled by paper:penalty=50,credit=0" in capsys.readouterr().out
    assert main(["run", "--settlement", "deadband", "--penalty", "50", "--check"]) == 2
    err = capsys.readouterr().err
    assert "settlement rule deadband prices every deviation" in err and err.count("\n") == 1


def test_a_sweep_of_the_penalty_under_a_named_rule_settles_each_run_at_its_own_rate_or_is_refused():
    under_paper = with_settings(Experiment(), {"market.settlement": "paper"}, "test")
    runs = variants(under_paper, [parse_setting("market.penalty=50,150,300")])
    assert [settled_by(v.experiment.market, CASE_PENALTY) for v in runs] == [
        "paper:penalty=50,credit=0", "paper:penalty=150,credit=0", "paper:penalty=300,credit=0"]
    under_deadband = with_settings(Experiment(), {"market.settlement": "deadband"}, "test")
    with pytest.raises(ExperimentError, match="settlement rule deadband prices every deviation"):
        variants(under_deadband, [parse_setting("market.penalty=50,150")])


def dmo_config(*flags: str):
    """The DMO's days as ``dmosim dmo`` reads them from its flags."""
    return day_config_of(role_experiment(build_parser("dmo").parse_args(["dmo", "--agents", "1", *flags])), None)


def test_the_dmo_settles_by_the_rule_with_the_markets_rates():
    config = dmo_config("--settlement", "paper", "--penalty", "50", "--credit", "5")
    assert config.rule.label == "paper:penalty=50,credit=5" and config.rates == (50.0, 5.0)
    assert dmo_config("--settlement", "paper").rule.label == "paper:penalty=150,credit=0"
    assert dmo_config("--settlement", "paper:penalty=70").rates == (70.0, 0.0)
    assert dmo_config("--settlement", "symmetric:below=10").rule.label == "symmetric:above=150,below=10"
    for flags in (("--settlement", "paper:penalty=70", "--penalty", "50"),
                  ("--settlement", "deadband", "--penalty", "50")):
        with pytest.raises(UsageError, match="flags: market: settlement rule"):
            dmo_config(*flags)
