"""Settlement: hand-computed statements to the cent, the missing-data rule, and properties of the totals."""

from __future__ import annotations

import json
from decimal import Decimal

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scenarios.horizon import HOURS
from dmo.market.settlement import settle

D = Decimal


def day(value: float) -> list[float]:
    return [value] * HOURS


def line0(award=5.0, price=40.0, readings=(5.0,) * 6, *, subperiods=6, penalty=150.0, credit=0.0, p_m_max=10.0):
    """Settle one agent with ``readings`` in hour 0 (None: hour 0 missing) and the award met in other hours."""
    meter = {h: [min(award, p_m_max)] * subperiods for h in range(1, HOURS)}
    if readings is not None:
        meter[0] = list(readings)
    statements, _ = settle({"mg1": day(award)}, day(price), {"mg1": meter}, subperiods=subperiods,
                           penalty=penalty, p_m_max=p_m_max, credit=credit)
    return statements["mg1"].lines[0]


# --- hand cases -------------------------------------------------------------------------------------------------

def test_energy_charge_and_penalty_to_the_cent():
    line = line0(award=5.0, price=40.25, readings=[6, 6, 4, 5, 5, 5])
    assert line.energy_charge == D("201.25")          # 40.25 $/MWh x 5 MW x 1 h
    assert line.deviation_mwh == pytest.approx(1 / 3)  # (1 + 1) MW x 1/6 h
    assert line.penalty == D("50.00")                  # 150 x 1/3
    assert line.under_import_mwh == pytest.approx(1 / 6)
    assert line.credit == D("0.00")
    assert line.total == D("251.25")
    assert line.import_mwh == pytest.approx(31 / 6) and not line.missing


def test_penalty_is_on_the_positive_part_only():
    # +2 MW in one half-hour and -2 MW in the other do not net: 1 MWh above the award is penalised.
    line = line0(award=5.0, price=40.0, readings=[7, 3], subperiods=2)
    assert line.deviation_mwh == 1.0 and line.under_import_mwh == 1.0
    assert line.penalty == D("150.00") and line.credit == D("0.00")
    assert line.total == D("350.00")


def test_under_import_credit_is_a_setting_and_reduces_the_total():
    line = line0(award=5.0, price=40.25, readings=[6, 6, 4, 5, 5, 5], credit=10.0)
    assert line.credit == D("1.67")                    # 10 x 1/6 = 1.666.. rounded half-even
    assert line.total == D("249.58")                   # 201.25 + 50.00 - 1.67


def test_negative_award_is_a_credit_and_exporting_less_is_penalised():
    line = line0(award=-2.5, price=40.0, readings=[-1.0] * 6)
    assert line.energy_charge == D("-100.00")
    assert line.penalty == D("225.00")                 # 1.5 MW above the award for 1 h at 150
    assert line.total == D("125.00")


@pytest.mark.parametrize("price, cents", [
    (0.125, D("0.12")),   # a half cent rounds to even, not up
    (0.135, D("0.14")),
    (2.675, D("2.68")),   # the recorded decimal 2.675, not the binary 2.67499..., which float round() gives 2.67
    (-0.125, D("-0.12")),
])
def test_rounding_is_half_even_on_the_decimal_as_recorded(price, cents):
    assert line0(award=1.0, price=price, readings=[1.0] * 6).energy_charge == cents


def test_missing_hour_is_settled_at_p_m_max_without_credit():
    line = line0(award=4.0, price=40.0, readings=None, credit=20.0, p_m_max=10.0)
    assert line.missing and line.missing_subperiods == 6
    assert line.import_mwh == 10.0 and line.deviation_mwh == 6.0 and line.under_import_mwh == 0.0
    assert line.penalty == D("900.00") and line.credit == D("0.00")
    assert line.total == D("1060.00")


def test_missing_sub_period_within_a_reported_hour():
    line = line0(award=4.0, price=40.0, readings=[5.0, None], subperiods=2, p_m_max=10.0)
    assert line.missing and line.missing_subperiods == 1
    assert line.deviation_mwh == 3.5 and line.penalty == D("525.00")   # (1 + 6) MW x 1/2 h x 150


def test_missing_agent_is_settled_at_p_m_max_every_hour():
    statements, summary = settle({"mg1": day(4.0), "mg2": day(1.0)}, day(40.0), {"mg2": {0: [1.0]}},
                                 subperiods=1, penalty=100.0, p_m_max={"mg1": 6.0, "mg2": 3.0})
    assert statements["mg1"].missing_subperiods == 24
    assert statements["mg1"].deviation_penalty == D("4800.00")           # 2 MWh x 100 x 24
    assert statements["mg2"].missing_subperiods == 23
    assert statements["mg2"].deviation_penalty == D("4600.00")           # 2 MWh x 100 x 23
    assert summary.agents_without_meter == ("mg1",)
    assert summary.total == D("3840.00") + D("960.00") + D("4800.00") + D("4600.00")


def test_award_above_p_m_max_costs_nothing_extra_when_missing():
    line = line0(award=12.0, price=40.0, readings=None, p_m_max=10.0)
    assert line.penalty == D("0.00") and line.total == D("480.00")


@pytest.mark.parametrize("kwargs, reason", [
    (dict(penalty=float("inf")), "penalty must be a number in 0..1,000,000, got inf"),
    (dict(penalty=float("nan")), "number"),
    (dict(penalty=-1.0), "penalty must be a number in 0..1,000,000, got -1.0"),
    (dict(credit=float("nan")), "number"),
    (dict(subperiods=0), "subperiods"),
    (dict(p_m_max=float("nan")), "p_m_max"),
    (dict(p_m_max={"other": 1.0}), "no p_m_max"),
    (dict(prices=day(40.0)[:23]), "24 hourly"),
    (dict(prices=[float("nan")] * 24), "finite"),
    (dict(awards={"mg1": [1.0] * 24, "": [1.0] * 24}), "non-empty"),
    (dict(meter={"mg1": {0: [float("nan")]}}), "finite"),
    (dict(meter={"mg1": {0: [11.0]}}), "above p_m_max"),
    (dict(meter={"mg1": {0: [1.0, 1.0]}}), "expected 1"),
    (dict(meter={"mg1": {24: [1.0]}}), "hour index"),
    (dict(meter={"mg9": {0: [1.0]}}), "no award"),
])
def test_invalid_input_is_rejected_with_a_one_line_reason(kwargs, reason):
    args = dict(awards={"mg1": day(1.0)}, prices=day(40.0), meter={}, subperiods=1, penalty=150.0,
                p_m_max=10.0) | kwargs
    with pytest.raises(ValueError, match=reason) as e:
        settle(args.pop("awards"), args.pop("prices"), args.pop("meter"), **args)
    assert "\n" not in str(e.value)


# --- properties -------------------------------------------------------------------------------------------------

money = st.floats(-200, 200, allow_nan=False, allow_infinity=False, allow_subnormal=False)
rates = st.floats(0, 1000, allow_nan=False, allow_infinity=False, allow_subnormal=False)
mw = st.floats(-15, 15, allow_nan=False, allow_infinity=False, allow_subnormal=False)


@st.composite
def agent_hours(draw):
    """Award, price, cap and honest readings (<= cap) for a few hours of one agent."""
    k = draw(st.integers(1, 6))
    cap = draw(st.floats(0, 15, allow_nan=False, allow_subnormal=False))
    hours = draw(st.lists(st.integers(0, HOURS - 1), min_size=1, max_size=3, unique=True))
    award = day(draw(mw))
    readings = {h: [min(draw(mw), cap) for _ in range(k)] for h in hours}
    return k, cap, award, readings


@settings(max_examples=60, deadline=None)
@given(agent_hours(), money, rates, rates, st.data())
def test_missing_data_never_costs_less_than_reporting(case, price, penalty, credit, data):
    """Honest reports settle at most as dear as the same reports missing, whole hours or single sub-periods."""
    k, cap, award, readings = case
    hidden = {h: [None if data.draw(st.booleans()) else p for p in r] for h, r in readings.items()}
    dropped = dict(list(readings.items())[1:])
    common = dict(subperiods=k, penalty=penalty, p_m_max=cap, p_m_min=15.0, credit=credit)
    honest, _ = settle({"mg1": award}, day(price), {"mg1": readings}, **common)
    for partial in (hidden, dropped, {}):
        missing, _ = settle({"mg1": award}, day(price), {"mg1": partial}, **common)
        for a, b in zip(honest["mg1"].lines, missing["mg1"].lines):
            assert a.total <= b.total
            assert a.energy_charge == b.energy_charge
        assert honest["mg1"].total <= missing["mg1"].total


@st.composite
def days(draw):
    agents = draw(st.lists(st.sampled_from(["mg1", "mg2", "mg3"]), min_size=1, max_size=3, unique=True))
    k = draw(st.integers(1, 4))
    awards = {a: draw(st.lists(mw, min_size=HOURS, max_size=HOURS)) for a in agents}
    meter = {a: {h: [draw(st.one_of(st.none(), mw)) for _ in range(k)]
                 for h in draw(st.lists(st.integers(0, HOURS - 1), max_size=4, unique=True))} for a in agents}
    prices = draw(st.lists(money, min_size=HOURS, max_size=HOURS))
    return awards, prices, meter, dict(subperiods=k, penalty=draw(rates), credit=draw(rates), p_m_max=15.0)


@settings(max_examples=30, deadline=None)
@given(days())
def test_totals_are_sums_of_cent_lines(case):
    awards, prices, meter, rules = case
    statements, summary = settle(awards, prices, meter, **rules)
    for s in statements.values():
        assert len(s.lines) == HOURS and [line.hour for line in s.lines] == list(range(HOURS))
        for line in s.lines:
            for v in (line.energy_charge, line.penalty, line.credit, line.total):
                assert v.as_tuple().exponent == -2
            assert line.total == line.energy_charge + line.penalty - line.credit
            assert line.penalty >= 0 and line.credit >= 0
        assert s.energy_charge == sum(line.energy_charge for line in s.lines)
        assert s.deviation_penalty == sum(line.penalty for line in s.lines)
        assert s.credit == sum(line.credit for line in s.lines)
        assert s.total == sum(line.total for line in s.lines) == s.energy_charge + s.deviation_penalty - s.credit
    assert summary.agents == tuple(sorted(awards))
    assert summary.total == sum(s.total for s in statements.values())
    assert summary.deviation_penalty == sum(s.deviation_penalty for s in statements.values())


@settings(max_examples=30, deadline=None)
@given(days())
def test_resettling_from_a_json_recording_reproduces_statements(case):
    awards, prices, meter, rules = case
    first = settle(awards, prices, meter, **rules)
    recorded = json.loads(json.dumps({"awards": awards, "prices": prices, "rules": rules,
                                      "meter": {a: {str(h): r for h, r in m.items()} for a, m in meter.items()}}))
    replay_meter = {a: {int(h): r for h, r in reversed(m.items())} for a, m in reversed(recorded["meter"].items())}
    again = settle(dict(reversed(recorded["awards"].items())), recorded["prices"], replay_meter, **recorded["rules"])
    assert again == first
    for s in first[0].values():  # the JSON form carries every cent exactly
        out = json.loads(json.dumps(s.as_dict()))
        assert Decimal(repr(out["total"])) == s.total
        assert [Decimal(repr(line["total"])) for line in out["lines"]] == [line.total for line in s.lines]
    assert Decimal(repr(json.loads(json.dumps(first[1].as_dict()))["total"])) == first[1].total


def test_on_a_feeder_each_agent_is_settled_at_its_own_bus_price():
    from dmo.market.rules import BUILT_IN
    from dmo.market.settlement import settle_day, settlement_day

    awards = {"near": day(2.0), "far": day(2.0)}
    meter = {a: {h: (3.0,) for h in range(HOURS)} for a in awards}  # 1 MW over the award every hour
    own = {"near": day(40.0), "far": day(65.0)}
    for rule, params in ((BUILT_IN["paper"], {"penalty": 100.0}), (BUILT_IN["price-linked"], {"k": 2.0})):
        settled = settlement_day(awards, day(40.0), meter, subperiods=1, p_m_max=10.0, agent_prices=own)
        statements, _ = settle_day(settled, rule, rule.name, **params)
        for agent, price in (("near", 40.0), ("far", 65.0)):
            line = statements[agent].lines[0]
            assert line.price == price and line.energy_charge == Decimal(str(2 * price))
            assert line.penalty == Decimal(str(100.0 if rule.name == "paper" else max(2 * price, 50.0)))
    with pytest.raises(ValueError, match="agent prices must map each awarded agent"):
        settlement_day(awards, day(40.0), meter, subperiods=1, p_m_max=10.0, agent_prices={"near": day(1.0)})
