"""Settlement rules (dmo/market/rules.py, choice.py): the built-ins by hand, their properties for any day
(hypothesis), and rules of one's own, refused in one line when they cannot settle."""

from __future__ import annotations

import json
import math
from decimal import Decimal
from fractions import Fraction
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dmosim.cli.main import main
from dmo.market.choice import choose, trial_day
from dmo.market.money import exact, to_cents
from dmo.market.rules import BUILT_IN, Charges
from dmo.market.settlement import settle
from scenarios.horizon import HOURS

D = Decimal
CAP = 8.0


def hour0(rule, readings, award=4.0, price=40.0, subperiods=2, **params):
    """Hour 0 of one agent under ``rule``, the other hours met exactly."""
    meter = {h: [award] * subperiods for h in range(1, HOURS)}
    if readings is not None:
        meter[0] = list(readings)
    statements, _ = settle({"mg1": [award] * HOURS}, [price] * HOURS, {"mg1": meter}, subperiods=subperiods,
                           p_m_max=CAP, rule=BUILT_IN[rule], **params)
    return statements["mg1"].lines[0]


# --- the built-ins, by hand ---------------------------------------------------------------------------------------

def test_symmetric_charges_both_sides_at_their_rates():
    line = hour0("symmetric", [6.0, 3.0], above=100.0, below=40.0)  # +2 MW and -1 MW, half an hour each
    assert line.penalty == D("100.00") + D("20.00") and line.credit == D("0.00")


def test_deadband_charges_only_beyond_the_band():
    # band = max(0.5 MW, 10% of 4 MW) = 0.5 MW: +2 MW costs 1.5 MW x 1/2 h x $150; -1 MW is below the award
    line = hour0("deadband", [6.0, 3.0], band_mw=0.5)
    assert line.penalty == D("112.50") and line.credit == D("0.00")
    wide = hour0("deadband", [6.0, 3.0], band_share=0.6, below_rate=10.0)  # band 2.4 MW: nothing is charged
    assert wide.penalty == D("0.00")


def test_price_linked_follows_the_price_above_its_floor():
    assert hour0("price-linked", [6.0, 4.0], price=80.0).penalty == D("120.00")   # 1.5 x 80 x 1 MWh
    assert hour0("price-linked", [6.0, 4.0], price=-20.0).penalty == D("50.00")   # the floor


def test_a_missing_sub_period_costs_the_worst_within_the_registered_limits():
    # symmetric, award 4, limits [-8, 8]: the worst is exporting 8 MW, 12 MW below, at $75 for half an hour
    assert hour0("symmetric", [4.0, None]).penalty == D("450.00")
    assert hour0("paper", [4.0, None]).penalty == D("300.00")  # importing 8 MW, 4 above, at $150


# --- properties of every built-in ---------------------------------------------------------------------------------

mw = st.floats(-CAP, CAP, allow_nan=False, allow_subnormal=False)
rates = st.floats(0, 500, allow_nan=False, allow_subnormal=False)


@st.composite
def rule_and_params(draw):
    rule = draw(st.sampled_from(sorted(BUILT_IN)))
    params = {k: draw(st.floats(0, min(500.0, BUILT_IN[rule].ranges[k][1]), allow_subnormal=False))
              for k in BUILT_IN[rule].defaults}  # rates up to $500/MWh, each within its range
    return rule, params


@st.composite
def one_hour(draw):
    k = draw(st.integers(1, 4))
    return k, draw(mw), draw(st.floats(-100, 300, allow_nan=False, allow_subnormal=False)), \
        [draw(mw) for _ in range(k)]


@settings(max_examples=80, deadline=None)
@given(rule_and_params(), one_hour(), st.data())
def test_every_built_in_adds_up_and_is_monotone_and_withholding_never_pays(chosen, hour, data):
    (rule, params), (k, award, price, readings) = chosen, hour
    line = hour0(rule, readings, award=award, price=price, subperiods=k, **params)
    assert line.total == line.energy_charge + line.penalty - line.credit
    for v in (line.energy_charge, line.penalty, line.credit, line.total):
        assert v.as_tuple().exponent == -2
    # moving one reading further from the award never makes the hour cheaper on a penalised side (above the award
    # for every rule, below it for symmetric and deadband); on the credit side, it never makes it dearer
    i, step = data.draw(st.integers(0, k - 1)), data.draw(st.floats(0, 4, allow_subnormal=False))
    further, above = list(readings), readings[i] >= award
    further[i] = min(CAP, readings[i] + step) if above else max(-CAP, readings[i] - step)
    moved = hour0(rule, further, award=award, price=price, subperiods=k, **params).total
    if above or rule in ("symmetric", "deadband"):
        assert moved >= line.total
    else:
        assert moved <= line.total
    # withholding a sub-period, or the hour, never costs less than reporting it
    for partial in ([None if j == i else p for j, p in enumerate(readings)], None):
        assert hour0(rule, partial, award=award, price=price, subperiods=k, **params).total >= line.total


@settings(max_examples=60, deadline=None)
@given(one_hour(), rates, rates)
def test_the_paper_rule_settles_as_the_paper_formula(hour, penalty, credit):
    """c x max(P_M - P_sch, 0) x dt and the credit below, each rounded once: the settlement dmosim always made."""
    k, award, price, readings = hour
    line = hour0("paper", readings, award=award, price=price, subperiods=k, penalty=penalty, credit=credit)
    p_sch, dt = exact(award), Fraction(1, k)
    over = sum((max(exact(p) - p_sch, 0) for p in readings), Fraction(0)) * dt
    under = sum((max(p_sch - exact(p), 0) for p in readings), Fraction(0)) * dt
    assert line.penalty == Decimal(to_cents(exact(penalty) * over)).scaleb(-2)
    assert line.credit == Decimal(to_cents(exact(credit) * under)).scaleb(-2)
    assert line.energy_charge == Decimal(to_cents(exact(price) * p_sch)).scaleb(-2)


@settings(max_examples=80, deadline=None)
@given(rule_and_params(), mw, st.floats(-100, 300, allow_nan=False, allow_subnormal=False), mw)
def test_the_pieces_an_award_carries_are_the_rule_itself(chosen, award, price, d):
    """What the agent's model maximises over is what the DMO charges, at any deviation."""
    rule, params = chosen
    f = BUILT_IN[rule].hourly(params, [award] * HOURS, [price] * HOURS)[0]
    pieces = BUILT_IN[rule].deviation_cost(params, [award] * HOURS, [price] * HOURS)
    if f.convex:
        assert max(slope * d + intercept for slope, intercept in pieces[0]) == pytest.approx(
            float(f.at(exact(d))), rel=1e-9, abs=1e-9)
    else:
        assert pieces is None


def test_the_built_ins_that_the_model_can_carry_are_convex():
    day = trial_day()
    for name, rule in BUILT_IN.items():
        assert all(price.convex for price in rule.hourly({}, day.awards["mg1"], day.prices)), name
        assert rule.deviation_cost({}, day.awards["mg1"], day.prices) is not None
    paper = {"penalty": 10.0, "credit": 20.0}  # a credit above the penalty
    assert not BUILT_IN["paper"].hourly(paper, day.awards["mg1"], day.prices)[0].convex
    assert BUILT_IN["paper"].deviation_cost(paper, day.awards["mg1"], day.prices) is None


# --- choosing a rule, and rules of one's own ----------------------------------------------------------------------

def test_a_rule_is_named_with_its_parameters_and_defaults_fill_the_rest():
    chosen = choose("deadband:band_mw=0.5,rate=100")
    assert chosen.label == "deadband:rate=100,below_rate=0,band_mw=0.5,band_share=0.1"
    assert choose("paper").parameters == {"penalty": 150.0, "credit": 0.0}


@pytest.mark.parametrize("spec, reason", [
    ("nosuch", "unknown settlement rule 'nosuch'"),
    ("deadband:width=1", "deadband has no parameter 'width'"),
    ("paper:penalty=-1", "penalty must be a number in 0..1,000,000"),
    ("paper:penalty=abc", "'penalty=abc' is not key=number"),
    ("paper:penalty=inf", "is not key=number"),
    ("tests/dmo/no_such_file.py:f", "no file tests/dmo/no_such_file.py"),
    ("examples/settlement_rule.py:nothing", "has no function 'nothing'"),
    ("no_such_module_here:f", "cannot load no_such_module_here"),
])
def test_a_rule_that_cannot_be_chosen_gets_one_line(spec, reason):
    with pytest.raises(ValueError, match=reason) as err:
        choose(spec)
    assert "\n" not in str(err.value)


def _raises(day, **params):
    raise KeyError("mg1")


def _not_finite(day, **params):
    return {a: [Charges(0, math.inf, 0)] * HOURS for a in day.awards}


def _does_not_add_up(day, **params):
    return {a: [Charges(10.0, 1.0, 0.0, total=10.0)] * HOURS for a in day.awards}


def _forgets_an_agent(day, **params):
    return {"mg1": [Charges(0, 0)] * HOURS}


def _pays_by_penalty(day, **params):
    return {a: [Charges(0, -1.0, 0)] * HOURS for a in day.awards}


@pytest.mark.parametrize("rule, reason", [
    ("_raises", "raised KeyError: 'mg1'"),
    ("_not_finite", "penalty is inf, not a finite amount"),
    ("_does_not_add_up", "total 10.00 is not energy_charge \\+ penalty - credit \\(11.00\\)"),
    ("_forgets_an_agent", "returned \\['mg1'\\]; it must map each awarded agent"),
    ("_pays_by_penalty", "a negative penalty"),
])
def test_a_rule_that_fails_on_the_trial_day_is_refused_in_one_line(rule, reason):
    with pytest.raises(ValueError, match=reason) as err:
        choose(f"tests.dmo.test_rules:{rule}")
    assert str(err.value).startswith(f"settlement rule tests.dmo.test_rules:{rule}")
    assert "\n" not in str(err.value) and "synthetic day" in str(err.value)


def test_the_example_rule_caps_each_agents_daily_penalty():
    day = trial_day()
    paper, _ = choose("paper").settle(day)
    capped, _ = choose("examples/settlement_rule.py:capped_penalty:cap=200").settle(day)
    for agent, statement in capped.items():
        assert statement.deviation_penalty == min(paper[agent].deviation_penalty, D("200.00"))
        assert statement.energy_charge == paper[agent].energy_charge


# --- recordings made before settlement rules -----------------------------------------------------------------------

V2_RECORDING = Path(__file__).parents[1] / "data" / "schema-v2-two-days.mcap"  # two days, two agents, schemas v2


def test_the_paper_rule_settles_a_recording_made_before_rules_existed_exactly_as_it_was(capsys):
    assert main(["settle", str(V2_RECORDING), "--json"]) == 0
    settled = json.loads(capsys.readouterr().out)
    assert settled["identical"] and settled["lines"] == 2 * 2 * HOURS
    assert main(["settle", str(V2_RECORDING), "--rule", "paper", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)["rows"]
    assert [r["change"] for r in rows] == [0.0, 0.0] and {r["rule"] for r in rows} == {"paper:penalty=150,credit=0"}


def test_the_islanding_rule_differs_from_the_paper_rule_only_in_islanded_sub_periods():
    """On the trial day, hour by hour: the same energy charge everywhere, the same penalty and credit in every hour
    the grid left connected, and in an islanded sub-period nothing beyond what its connected sub-periods cost."""
    day = trial_day()
    paper, _ = choose("paper").settle(day)
    exempt, _ = choose("examples/islanding_rule.py:islanding_exempt").settle(day)
    for agent, statement in exempt.items():
        for own, theirs in zip(statement.lines, paper[agent].lines):
            assert own.energy_charge == theirs.energy_charge
            if not day.grid[own.hour].islanded:
                assert (own.penalty, own.credit) == (theirs.penalty, theirs.credit)
            elif all(not up for up in day.grid[own.hour].connected):
                assert own.penalty == own.credit == 0
    assert exempt["mg2"].deviation_penalty < paper["mg2"].deviation_penalty  # mg2 exports: islanding was charged


def test_a_rule_of_ones_own_is_named_with_the_defaults_it_settles_by():
    """Its full name, as ``dmosim settle`` prints it and the award announces it, lists every parameter the function
    settles with, as a built-in's does: those given over the numeric defaults of its signature."""
    assert choose("examples/settlement_rule.py:capped_penalty:cap=200").label == (
        "examples/settlement_rule.py:capped_penalty:penalty=150,credit=0,cap=200")
    assert choose("examples/settlement_rule.py:capped_penalty:penalty=90").label == (
        "examples/settlement_rule.py:capped_penalty:penalty=90,credit=0,cap=500")
    assert choose("deadband:rate=100").label == "deadband:rate=100,below_rate=0,band_mw=0,band_share=0.1"
