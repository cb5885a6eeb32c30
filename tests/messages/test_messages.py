"""Message schemas, JSON encoding and key expressions: everything on the wire short of the network."""

from __future__ import annotations

import json

import jsonschema
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from messages import (HOURS, KINDS, MAX_PAYLOAD_BYTES, SCHEMA_VERSION, SCHEMAS, Award, Bid, BidStep, CallForBids,
                      Clock, DaySummary, GridState, Incident, Keys, MessageError, MeterReport, Registration, Schedule,
                      SettlementStatement, StatementLine, check_route, decode, encode, json_schema, make_receipt,
                      make_rejection, new_run_id, parse_key, sender_matches_key)
from messages.transport import BusConfig
from messages.transport.bus import ACCEPT_PENDING, ACCEPT_TIMEOUT_S, MAX_SESSIONS
from messages.schemas import (MAX_BUSES, ACCheck, AgentDay, AgentTotals, HandlingTime, MessageCounts, MidnightUnit,
                              NetworkHour)

DAY = "2024-07-01"
K = 6


def _statement() -> SettlementStatement:
    def line(h: int) -> StatementLine:
        energy, penalty = round(1.5 * (40 + h), 2), (15.0 if h == 5 else 0.0)
        return StatementLine(hour=h, p_sch_mw=1.5, clearing_price_per_mwh=40.0 + h, energy_charge=energy,
                             import_mwh=1.6 if h == 5 else 1.5, deviation_mwh=0.1 if h == 5 else 0.0,
                             under_import_mwh=0.0, deviation_penalty=penalty, deviation_credit=0.0,
                             total=energy + penalty, missing=h == 9, missing_subperiods=K if h == 9 else 0)

    lines = [line(h) for h in range(1, HOURS + 1)]
    energy = sum(line.energy_charge for line in lines)
    return SettlementStatement(sender="dmo", market_day=DAY, agent="mg1", penalty_per_mwh=150.0, credit_per_mwh=0.0,
                               rules_version=1, lines=lines, energy_charge=energy, deviation_penalty=15.0,
                               deviation_credit=0.0, total=energy + 15.0, missing_subperiods=K)


SAMPLES = {
    "registration": Registration(sender="mg1", market_day=DAY, case="paper", max_import_mw=10.0, max_export_mw=5.0),
    "call_for_bids": CallForBids(sender="dmo", market_day=DAY, iso_price_per_mwh=[30.0 + h for h in range(HOURS)],
                                 price_floor_per_mwh=-100.0, price_cap_per_mwh=1000.0, import_limit_mw=10.0,
                                 export_limit_mw=5.0, penalty_per_mwh=150.0, subperiods=K, deadline_s=5.0),
    "bid": Bid(sender="mg1", market_day=DAY,
               hours=[[BidStep(price_per_mwh=50.0, quantity_mw=2.0), BidStep(price_per_mwh=20.0, quantity_mw=-1.0)]
                      if h % 2 else [] for h in range(HOURS)]),
    "award": Award(sender="dmo", market_day=DAY, agent="mg1", p_sch_mw=[1.5] * HOURS,
                   clearing_price_per_mwh=[41.0] * HOURS, penalty_per_mwh=150.0, subperiods=K, rules_version=1,
                   rules="energy charge = price x award; penalty = c x max(P_M - P_sch, 0) x dt",
                   settlement_rule="deadband:rate=150,below_rate=0,band_mw=0.5,band_share=0",
                   deviation_cost=[[[0.0, 0.0], [0.0, 0.0], [150.0, -75.0]]] * HOURS,
                   congestion=["none"] * 12 + ["import"] * 6 + ["none"] * 5 + ["export"]),
    "schedule": Schedule(sender="mg1", market_day=DAY, status="optimal",
                         commitment={"G1": [1] * HOURS, "G2": [0] * HOURS},
                         expected_cost=39566.0, p_m_expected_mw=[1.4] * HOURS, scenarios=10, mip_gap=0.004),
    "clock": Clock(sender="dmo", market_day=DAY, phase="realtime", hour=3, deadline_s=2.0, day=1, days=1),
    "grid_state": GridState(sender="dmo", market_day=DAY, hour=3, subperiods=K, connected=[True] * 4 + [False] * 2,
                            buses=["0", "1", "2"], import_room_mw=[0.0, 0.25, 0.0],
                            export_room_mw=[0.0, 0.5, 0.0]),
    "meter_report": MeterReport(sender="mg1", market_day=DAY, hour=3, subperiods=K, p_m_mw=[1.5] * K,
                                deviation_mw=[0.0] * K),
    "agent_day": AgentDay(sender="mg1", market_day=DAY, generation=30000.0, startup=120.0, curtailment=0.0,
                          penalty=15.0, total=30135.0, curtailment_mwh=0.0, deviation_mwh=0.1,
                          units={"G1": MidnightUnit(on=True, output_mw=2.5, hours=24),
                                 "G2": MidnightUnit(on=False, output_mw=0.0, hours=3)}, stored_mwh=1.2,
                          compute=[HandlingTime(kind="award", hour=None, wall_s=2.5, cpu_s=2.4,
                                                started_at=1_780_000_000 * 10**9, turn_s=0.1),
                                   HandlingTime(kind="grid_state", hour=24, wall_s=0.05, cpu_s=0.04,
                                                started_at=1_780_000_009 * 10**9, turn_s=0.0)],
                          messages=MessageCounts(published=60, received=80, rejected={}, handler_errors=0,
                                                 ignored={"award_again": 1}, sent_again=2, asked=0,
                                                 faults_injected={"drop": 1})),
    "network_hour": NetworkHour(sender="dmo", market_day=DAY, hour=19, stage="plan", network="feeder5",
                                buses=["0", "1", "2"], substation="0", lines=["0-1", "1-2"], substation_mw=1.2, injection_mw=[0.0, 0.5, -0.1],
                                voltage_pu=[1.0, 0.99, 0.985], line_loading=[0.4, 1.0], energy_price_per_mwh=40.0,
                                clearing="ac", bus_price_per_mwh=[40.0, 41.0, 57.0],
                                loss_price_per_mwh=[0.0, 1.0, 1.5], congestion_price_per_mwh=[0.0, 0.0, 15.5],
                                voltage_price_per_mwh=[0.0, 0.0, 0.0], shed_mw=[0.0, 0.0, 0.0],
                                spilled_mw=[0.0, 0.0, 0.0], limit_loading=[0.4, 1.0], binding_facet=[None, 0],
                                line_shadow_price_per_mwh=[0.0, 15.5], binding_voltage=[None, None, "v_min"],
                                voltage_shadow_price_per_pu=[0.0, 0.0, 0.0],
                                ac=ACCheck(converged=True, v_min_pu=0.984, v_min_bus="2", v_max_pu=0.99,
                                           v_max_bus="1", max_loading=1.01, max_loading_line="1-2",
                                           voltage_error_pu=0.001, flow_error_mw=0.01, losses_mw=0.012,
                                           substation_mw=1.212, violations=["overload 1-2 101.0%"],
                                           margin=0.0)),
    "settlement_statement": _statement(),
    "day_summary": DaySummary(sender="dmo", market_day=DAY, agents=["mg1", "mg2"],
                              clearing_price_per_mwh=[41.0] * HOURS,
                              totals={"mg1": AgentTotals(energy_charge=100.0, deviation_penalty=15.0,
                                                         deviation_credit=0.0, total=115.0)},
                              rejected_messages=1,
                              incidents=[Incident(agent="mg2", phase="bidding", hour=None,
                                                  reason="no bid by deadline")]),
    "rejection": make_rejection("dmosim/r1/agent/mg1/bid", b"not json", MessageError("not JSON", "not_json"),
                                market_day=DAY, offender="mg1", received_at=123),
    "receipt": make_receipt("mg1", b'{"kind":"bid","seq":7}', None, market_day=DAY),
}


def _wire(kind: str) -> dict:
    return json.loads(encode(SAMPLES[kind]))


def _bytes(data: dict) -> bytes:
    return json.dumps(data, separators=(",", ":")).encode()


def test_a_sample_for_every_kind():
    assert set(SAMPLES) == set(KINDS) == set(SCHEMAS)


@pytest.mark.parametrize("kind", KINDS)
def test_round_trip(kind):
    msg = SAMPLES[kind]
    payload = encode(msg)
    assert decode(payload) == msg
    assert decode(payload, expected_kind=kind) == msg
    text = payload.decode("utf-8")
    assert text.startswith(f'{{"kind":"{kind}","schema_version":{SCHEMA_VERSION},')
    assert ", " not in text.split('"rules"')[0]  # compact (the award's rules text has its own spaces)


@pytest.mark.parametrize("kind", KINDS)
def test_json_schema_accepts_the_sample_and_rejects_mutations(kind):
    validator = jsonschema.Draft202012Validator(json_schema(kind))
    jsonschema.Draft202012Validator.check_schema(json_schema(kind))
    data = _wire(kind)
    validator.validate(data)
    payload_field = next(name for name in data if name not in ("kind", "schema_version", "sender", "market_day",
                                                               "seq", "sent_at"))
    mutations = [{**data, "bogus": 1}, {**data, "kind": "other"}, {**data, "seq": -1}, {**data, "sender": 7},
                 {**data, "schema_version": SCHEMA_VERSION + 1},
                 {name: value for name, value in data.items() if name != payload_field},
                 {name: value for name, value in data.items() if name != "sent_at"}]
    for mutated in mutations:
        assert not validator.is_valid(mutated), mutated
        with pytest.raises(MessageError):
            decode(_bytes(mutated))


def _rejects(payload: bytes, code: str, *words: str, expected_kind: str | None = None) -> MessageError:
    with pytest.raises(MessageError) as caught:
        decode(payload, expected_kind=expected_kind)
    err = caught.value
    assert err.code == code, str(err)
    assert "\n" not in str(err) and len(str(err)) <= 300
    for word in words:
        assert word in str(err), str(err)
    return err


def _with(kind: str, /, **changes) -> bytes:
    return _bytes({**_wire(kind), **changes})


def _older(kind: str, version: int, *dropped: str) -> bytes:
    return _bytes(_older_dict(kind, version, *dropped))


def _older_dict(kind: str, version: int, *dropped: str) -> dict:
    return {**{k: v for k, v in _wire(kind).items() if k not in dropped}, "schema_version": version}


def _older_within(kind: str, version: int, within: str, *dropped: str) -> bytes:
    data = _wire(kind)
    items = [{k: v for k, v in item.items() if k not in dropped} for item in data[within]]
    return _bytes({**data, within: items, "schema_version": version})


BOUND = ("run", "incarnation")  # version 4's envelope fields


FEEDER = ("bus", "energy_price_per_mwh", "congestion_price_per_mwh", "voltage_price_per_mwh")  # since version 7
LOSS = ("loss_price_per_mwh",)  # since version 10
ROOMS = ("import_room_mw", "export_room_mw")  # since version 11, room_mw before
BINDS = ("limit_loading", "binding_facet", "line_shadow_price_per_mwh", "binding_voltage",
         "voltage_shadow_price_per_pu")  # since version 11


def test_older_messages_read_as_they_were_meant():
    """A version-1 clock is day 1 of 1; a version-2 award or statement names no rule: the paper's at its rates; a
    version-3 message is bound to no run and no process; a version-4 award states no congestion; a version-6 award
    or registration names no bus (the copper plate); a version-7 grid state carries no operating envelope; a version-8
    agent_day says neither when the messages it handled were taken up nor a wait for a turn; a version-9 award or
    network_hour carries no loss component, and the network_hour names no clearing method and no spilled generation;
    a version-10 grid state's one room is its room either way."""
    clock = decode(_older("clock", 1, "day", "days", *BOUND))
    assert (clock.day, clock.days) == (1, 1)
    award = decode(_older("award", 2, "settlement_rule", "deviation_cost", "congestion", *BOUND, *FEEDER, *LOSS))
    assert award.settlement_rule is None and award.deviation_cost is None
    assert award.p_sch_mw == SAMPLES["award"].p_sch_mw
    assert decode(_older("settlement_statement", 2, "settlement_rule", *BOUND)).settlement_rule is None
    award = decode(_older("award", 4, "congestion", *FEEDER, *LOSS))
    assert award.congestion is None and award.settlement_rule == SAMPLES["award"].settlement_rule
    award = decode(_older("award", 6, *FEEDER, *LOSS))
    assert award.bus is None and award.energy_price_per_mwh is None and award.congestion == SAMPLES["award"].congestion
    assert decode(_older("registration", 6, "bus")).bus is None
    grid = decode(_older("grid_state", 7, "buses", *ROOMS))
    assert (grid.buses, grid.import_room_mw, grid.export_room_mw) == ((), (), ())
    assert grid.connected == SAMPLES["grid_state"].connected
    grid = decode(_bytes({**_older_dict("grid_state", 10, *ROOMS), "room_mw": [0.0, 0.75, 0.0]}))
    assert grid.import_room_mw == grid.export_room_mw == (0.0, 0.75, 0.0) and grid.buses == ("0", "1", "2")
    bid = decode(_older("bid", 3, *BOUND))
    assert (bid.run, bid.incarnation) == ("", 0) and bid.hours == SAMPLES["bid"].hours
    day = decode(_older_within("agent_day", 8, "compute", "started_at", "turn_s"))
    assert [(h.started_at, h.turn_s) for h in day.compute] == [(None, 0.0), (None, 0.0)]
    assert decode(_older("award", 9, *LOSS)).loss_price_per_mwh is None
    hour = decode(_older("network_hour", 9, "clearing", "spilled_mw", *LOSS, *BINDS))
    assert (hour.clearing, hour.loss_price_per_mwh, hour.spilled_mw) == (None, None, None)
    hour = decode(_older("network_hour", 10, *BINDS))
    assert all(getattr(hour, name) is None for name in BINDS) and hour.clearing == SAMPLES["network_hour"].clearing
    assert hour.bus_price_per_mwh == (40.0, 41.0, 57.0)
    assert [h.wall_s for h in day.compute] == [h.wall_s for h in SAMPLES["agent_day"].compute]
    # a message of an older version that has a later version's field is not upgraded, and a current one that
    # leaves a field out is refused
    _rejects(_older("award", 2, "deviation_cost"), "invalid", "deviation_cost")
    _rejects(_older("award", 6, "bus"), "invalid", "bus")
    _rejects(_older("grid_state", 7, *ROOMS), "invalid", "import_room_mw")
    _rejects(_bytes({**_older_dict("grid_state", 10, "export_room_mw"), "room_mw": [0.0] * 3}), "invalid",
             "room_mw")
    _rejects(_older("grid_state", SCHEMA_VERSION, "buses", *ROOMS), "invalid", "buses")
    _rejects(_older("bid", 3, "run"), "invalid", "run")
    _rejects(_older("award", SCHEMA_VERSION, "settlement_rule"), "invalid", "settlement_rule")
    _rejects(_older("award", SCHEMA_VERSION, "congestion"), "invalid", "congestion")
    _rejects(_older("bid", SCHEMA_VERSION, "run"), "invalid", "run")
    _rejects(_older_within("agent_day", 8, "compute", "turn_s"), "invalid", "turn_s")
    _rejects(_older_within("agent_day", SCHEMA_VERSION, "compute", "turn_s"), "invalid", "turn_s")


def test_the_wait_for_a_turn_is_a_part_of_the_handling_time():
    day = _wire("agent_day")
    day["compute"][0].update(wall_s=0.5, turn_s=0.75)
    _rejects(_bytes(day), "invalid", "turn_s")


def test_rejects_non_finite_numbers():
    prices = [41.0] * HOURS
    text = _with("award", clearing_price_per_mwh=prices).decode()
    for bad in ("NaN", "Infinity", "-Infinity", "1e999"):
        payload = text.replace('"clearing_price_per_mwh":[41.0,41.0', f'"clearing_price_per_mwh":[41.0,{bad}').encode()
        _rejects(payload, "invalid", "clearing_price_per_mwh[1]", "finite")
    with pytest.raises(ValidationError):
        MeterReport(sender="mg1", market_day=DAY, hour=1, subperiods=1, p_m_mw=[float("nan")], deviation_mw=[0.0])


def test_rejects_wrong_types():
    _rejects(_with("bid", seq="3"), "invalid", "seq", "integer")
    _rejects(_with("grid_state", connected=[1, 1, 1, 1, 0, 0]), "invalid", "connected[0]", "boolean")
    _rejects(_with("meter_report", hour=3.0), "invalid", "hour")
    _rejects(_with("award", p_sch_mw="1.5"), "invalid", "p_sch_mw")
    _rejects(_with("bid", sender="1mg"), "invalid", "sender")
    _rejects(_with("registration", sender="dmo"), "invalid", "reserved")
    _rejects(_with("award", sender="mg1"), "invalid", "sender must be 'dmo'")
    _rejects(_with("clock", market_day="2024-02-30"), "invalid", "market_day")


def test_rejects_wrong_lengths():
    _rejects(_with("award", p_sch_mw=[1.0] * (HOURS - 1)), "invalid", "p_sch_mw", "24")
    _rejects(_with("bid", hours=[[]] * (HOURS + 1)), "invalid", "hours")
    _rejects(_with("meter_report", p_m_mw=[1.0] * (K + 1)), "invalid", "p_m_mw", f"subperiods={K}")
    _rejects(_with("grid_state", connected=[True]), "invalid", "connected")


def test_a_network_hours_binding_limits_name_one_facet_or_voltage_limit_per_line_or_bus():
    _rejects(_with("network_hour", binding_facet=[None]), "invalid", "binding_facet has 1 values for 2 lines")
    _rejects(_with("network_hour", limit_loading=[1.0, 1.0, 1.0]), "invalid", "limit_loading has 3 values for 2 lines")
    _rejects(_with("network_hour", binding_facet=[None, 8]), "invalid", "binding_facet[1]", "less than or equal to 7")
    _rejects(_with("network_hour", binding_facet=[None, 1.0]), "invalid", "binding_facet[1]")
    _rejects(_with("network_hour", binding_voltage=[None, "low", None]), "invalid", "binding_voltage[1]")
    _rejects(_with("network_hour", binding_voltage=[None, None]), "invalid", "binding_voltage has 2 values for 3 buses")
    _rejects(_with("network_hour", voltage_shadow_price_per_pu=[0.0]), "invalid", "voltage_shadow_price_per_pu")


def test_a_grid_states_envelope_gives_two_finite_rooms_of_at_least_0_per_bus():
    _rejects(_with("grid_state", import_room_mw=[0.0, 0.25]), "invalid", "import_room_mw has 2 values for 3 buses")
    _rejects(_with("grid_state", export_room_mw=[0.5]), "invalid", "export_room_mw has 1 values for 3 buses")
    _rejects(_with("grid_state", buses=["0", "1"]), "invalid", "import_room_mw has 3 values for 2 buses")
    _rejects(_with("grid_state", import_room_mw=[0.0, -0.25, 0.0]), "invalid", "import_room_mw[1]",
             "greater than or equal to 0")
    _rejects(_with("grid_state", export_room_mw=[0.0, 0.25, -1.0]), "invalid", "export_room_mw[2]")
    _rejects(_with("grid_state", buses=["0", "1", "1"]), "invalid", "more than once")
    text = _with("grid_state").decode()
    _rejects(text.replace('"import_room_mw":[0.0,0.25', '"import_room_mw":[0.0,Infinity').encode(), "invalid",
             "import_room_mw[1]")
    many = [str(b) for b in range(MAX_BUSES + 1)]
    _rejects(_with("grid_state", buses=many, import_room_mw=[0.0] * len(many), export_room_mw=[0.0] * len(many)),
             "invalid", "buses")
    copper = decode(encode(GridState(sender="dmo", market_day=DAY, hour=1, subperiods=1, connected=[True])))
    assert (copper.buses, copper.import_room_mw, copper.export_room_mw) == ((), (), ())
    lines = _wire("settlement_statement")["lines"]
    _rejects(_with("settlement_statement", lines=lines[:-1]), "invalid", "lines")
    _rejects(_with("settlement_statement", total=1.0), "invalid", "total", "add up")


def test_rejects_bad_envelopes():
    _rejects(_with("bid", kind="offer"), "unknown_kind", "'offer'")
    _rejects(_bytes({"sender": "mg1"}), "unknown_kind", "kind")
    err = _rejects(_with("bid", schema_version=SCHEMA_VERSION + 1, new_field=1), "unsupported_version")
    assert str(err) == f"schema_version {SCHEMA_VERSION + 1} is newer than supported {SCHEMA_VERSION}"
    _rejects(_with("bid", schema_version=0), "invalid", "schema_version")
    _rejects(_with("bid", bogus=1), "invalid", "bogus")
    missing = _wire("bid")
    del missing["seq"]
    _rejects(_bytes(missing), "invalid", "seq")
    _rejects(encode(SAMPLES["bid"]), "wrong_key", "'award'", expected_kind="award")


def test_rejects_non_json_and_oversize():
    _rejects(b"\xff\xfe{", "not_json", "not JSON")
    _rejects(b'{"kind": "bid",', "not_json", "not JSON")
    _rejects(b"", "not_json")
    _rejects(b"[1, 2]", "not_object", "array")
    _rejects(b"[" * 100_000, "not_json")
    big = b'{"kind":"bid","pad":"' + b"x" * MAX_PAYLOAD_BYTES + b'"}'
    _rejects(big, "oversize", str(len(big)))
    with pytest.raises(MessageError):
        decode("a string")


def test_messages_are_frozen():
    with pytest.raises(ValidationError):
        SAMPLES["bid"].seq = 5
    assert isinstance(SAMPLES["award"].p_sch_mw, tuple)
    assert SAMPLES["bid"].agent == "mg1"


# --- property tests: decode refuses everything it cannot accept, and only with MessageError ------------

_json = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
                     lambda inner: st.lists(inner, max_size=5)
                     | st.dictionaries(st.text(max_size=10), inner, max_size=5),
                     max_leaves=30)


def _decodes_or_refuses(payload: bytes) -> None:
    try:
        decode(payload)
    except MessageError as err:
        assert str(err) and "\n" not in str(err)


@settings(max_examples=150, deadline=None)
@given(st.binary(max_size=300))
def test_decode_of_arbitrary_bytes(payload):
    _decodes_or_refuses(payload)


@settings(max_examples=150, deadline=None)
@given(_json)
def test_decode_of_arbitrary_json(value):
    _decodes_or_refuses(json.dumps(value).encode())


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from(KINDS), st.data())
def test_decode_of_messages_with_one_field_replaced(kind, data):
    wire = _wire(kind)
    name = data.draw(st.sampled_from(sorted(wire)))
    _decodes_or_refuses(json.dumps({**wire, name: data.draw(_json)}).encode())


# --- keys ---------------------------------------------------------------------------------------------

def test_every_message_has_one_key_that_parses_back():
    keys = Keys(new_run_id())
    for kind, msg in SAMPLES.items():
        key = keys.for_message(msg)
        parsed = parse_key(key)
        assert (parsed.run_id, parsed.kind) == (keys.run_id, kind)
        assert parsed.role == ("dmo" if msg.sender == "dmo" else "agent")
        assert key.startswith(keys.prefix + ("/dmo/" if parsed.role == "dmo" else "/agent/mg1/"))
        assert check_route(key, msg, keys.run_id) == parsed
    assert keys.award("mg1") == f"dmosim/{keys.run_id}/dmo/award/mg1"
    assert keys.bid("*") == f"dmosim/{keys.run_id}/agent/*/bid"
    assert parse_key(keys.alive("mg3")).topic == "mg3"


def test_a_link_token_names_two_routers_by_their_zenoh_ids():
    keys = Keys("run1")
    assert keys.link("92c914a44fe0da50611f4659bf58f0f9", "ab") == "dmosim/run1/link/92c914a44fe0da50611f4659bf58f0f9/ab"
    assert keys.link("*", "*") == "dmosim/run1/link/*/*"
    for wrong in ("", "host1", "AB12", "a/b", "**", "0" * 33):
        with pytest.raises(ValueError, match="must be hexadecimal"):
            keys.link(wrong, "ab")


def test_route_checks():
    keys, other = Keys("run1"), Keys("run2")
    bid, award = SAMPLES["bid"], SAMPLES["award"]
    assert sender_matches_key(keys.bid("mg1"), bid)
    assert not sender_matches_key(keys.bid("mg2"), bid)
    with pytest.raises(MessageError) as caught:
        check_route(keys.bid("mg2"), bid)
    assert caught.value.code == "unauthorised"
    for key, msg in [(keys.schedule("mg1"), bid), (keys.award("mg2"), award), (other.bid("mg1"), bid)]:
        with pytest.raises(MessageError) as caught:
            check_route(key, msg, "run1")
        assert caught.value.code == "wrong_key"
    for junk in ["", "dmosim", "dmosim/run1/dmo/award", "dmosim/run1/dmo/grid/3", "dmosim/run1/agent/dmo/bid",
                 "other/run1/dmo/grid", "dmosim/run1/agent/mg1/bid/x", "dmosim/run1/agent/mg1/award"]:
        with pytest.raises(MessageError):
            parse_key(junk)
    with pytest.raises(ValueError):
        keys.bid("dmo")
    with pytest.raises(ValueError):
        Keys("bad/run")


def test_run_ids_are_unique_and_valid():
    ids = {new_run_id() for _ in range(100)}
    assert len(ids) == 100
    for run_id in ids:
        Keys(run_id)


# --- configuration --------------------------------------------------------------------------------------

def test_bus_config():
    config = BusConfig(mode="client", connect=["tcp/127.0.0.1:7447"], lease_s=1.5,
                       overrides=[("transport/link/tx/keep_alive", "2")]).to_zenoh()
    assert json.loads(config.get_json("mode")) == "client"
    assert json.loads(config.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False
    assert json.loads(config.get_json("scouting/delay")) == 0
    assert json.loads(config.get_json("transport/link/tx/lease")) == 1500
    assert json.loads(config.get_json("transport/link/tx/keep_alive")) == 2
    assert json.loads(config.get_json("transport/shared_memory/enabled")) is False
    with pytest.raises(ValueError):
        BusConfig(mode="server")
    with pytest.raises(ValueError):
        BusConfig(overrides=[("no/such/setting", "1")]).to_zenoh()


def test_a_listener_takes_a_fleet_joining_at_once_and_a_client_waits_its_timeout_for_the_handshake_too():
    """Zenoh's defaults (1,000 sessions, 100 handshakes under way, 10 s each; a client's handshake 10 s whatever
    its connect timeout) refused agents of a fleet of 1,000 joining three routers on two cores."""
    unicast = lambda config: json.loads(config.to_zenoh().get_json("transport/unicast"))  # noqa: E731
    listener = unicast(BusConfig(mode="router", listen=["tcp/127.0.0.1:0"]))
    assert (listener["max_sessions"], listener["accept_pending"]) == (MAX_SESSIONS, ACCEPT_PENDING)
    assert listener["accept_timeout"] == ACCEPT_TIMEOUT_S * 1000 and MAX_SESSIONS > 1000
    client = unicast(BusConfig(mode="client", connect=["tcp/127.0.0.1:7447"], connect_timeout_s=75))
    assert client["open_timeout"] == 75_000 and client["max_sessions"] == 1000  # a client accepts nobody


def test_a_config_file_of_ones_own_keeps_zenohs_shared_memory(tmp_path):
    own = tmp_path / "zenoh.json5"
    own.write_text('{ transport: { shared_memory: { enabled: true } } }')
    assert json.loads(BusConfig(config_file=str(own)).to_zenoh().get_json("transport/shared_memory/enabled"))
