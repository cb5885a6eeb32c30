"""The live page's pure parts (dmosim/view/): a run's messages folded into what the page shows, a recording played
and moved about in, the page kept small with many agents; and ``dmosim view``'s bad input, one line and exit 2.
No process, no browser: tests/dmosim/test_view_browser.py has the page in a real one."""

from __future__ import annotations

import json
import socket
from pathlib import Path
from types import SimpleNamespace as Msg

import pytest

from dmosim.results.tables import tables
from dmosim.view.board import MAX_BYTES_PER_S, Board
from dmosim.view.page import DETAIL_AGENTS, RANKED_BILLS, accrued, page
from dmosim.view.player import PagePlayer, playable
from dmosim.view.state import Observed
from messages.recording import read_recording

TWO_DAYS = Path(__file__).resolve().parents[1] / "data" / "schema-v2-two-days.mcap"
DAY = "2026-07-06"


def envelope(kind: str, sender: str = "dmo", **fields) -> Msg:
    return Msg(kind=kind, sender=sender, run="token", incarnation=1, market_day=DAY, **fields)


def clock(phase: str, hour: int | None = None) -> Msg:
    return envelope("clock", phase=phase, hour=hour, day=1, days=1, deadline_s=60.0)


def award(agent: str, p_sch: float, price: float = 50.0, bus: str | None = None) -> Msg:
    return envelope("award", agent=agent, p_sch_mw=(p_sch,) * 24, clearing_price_per_mwh=(price,) * 24, bus=bus,
                    subperiods=2, penalty_per_mwh=150.0, credit_per_mwh=10.0, congestion=("none",) * 24)


def meter(agent: str, hour: int, readings: tuple[float, ...]) -> Msg:
    return envelope("meter_report", sender=agent, hour=hour, p_m_mw=readings)


def register(agent: str, incarnation: int = 1) -> Msg:
    msg = envelope("registration", sender=agent, bus=None, strategy=None)
    msg.incarnation = incarnation
    return msg


def fold(*messages: Msg) -> Observed:
    observed = Observed()
    for at, msg in enumerate(messages):
        observed.take("key", msg, at)
    return observed


def test_a_recorded_run_folds_into_the_bills_and_awards_its_tables_give():
    rec = read_recording(TWO_DAYS)
    board = Board()
    for key, msg, at in playable(rec):
        board.take(key, msg, at)
    board.render()
    shown = json.loads(board.latest[1])
    t = tables(rec)
    assert shown["market_day"] == "2026-07-07" and shown["days_done"] == ["2026-07-06"]
    assert shown["clock"]["phase"] == "settlement" and shown["summary"]
    bills = t["days"].groupby("agent")["total"].sum()  # the bills of both days, as the statements say
    assert {a["agent"]: a["bill"]["total"] for a in shown["detail"]} == pytest.approx(bills.to_dict(), abs=0.01)
    assert all(a["bill"]["settled"] for a in shown["detail"])
    last = t["hours"][t["hours"]["market_day"] == "2026-07-07"]
    for a in shown["detail"]:
        awarded = last[last["agent"] == a["agent"]].sort_values("hour")["p_sch_mw"].tolist()
        assert a["award"] == pytest.approx(awarded, abs=1e-3)


def test_what_accrues_before_the_statement_is_the_paper_rule_of_the_readings():
    observed = fold(clock("realtime", 1), award("mg1", 2.0, price=40.0), meter("mg1", 1, (3.0, 1.0)),
                    meter("mg1", 2, (2.5, 2.5)), meter("mg1", 2, (9.0, 9.0)))  # a second report of hour 2 is not taken
    got = accrued(observed.day, "mg1")
    # hour 1: 1 MW over for half an hour and 1 MW under for the other half; hour 2: 0.5 MW over for the hour
    assert got["energy_charge"] == pytest.approx(2 * 40.0 * 2.0)
    assert got["deviation_penalty"] == pytest.approx(150.0 * (0.5 + 0.5))
    assert got["deviation_credit"] == pytest.approx(10.0 * 0.5)
    shown = page(observed)
    assert shown["detail"][0]["import"][:3] == [2.0, 2.5, None]
    assert shown["detail"][0]["bill"]["settled"] is False


def test_the_dmo_waits_for_the_agents_that_have_not_answered_its_phase_or_hour():
    observed = fold(register("mg1"), register("mg2"), clock("bidding"), envelope("bid", sender="mg2"))
    assert observed.waiting_for() == ["mg1"]
    observed.take("key", clock("realtime", 3), 10)
    observed.take("key", meter("mg1", 3, (1.0,)), 11)
    assert observed.waiting_for() == ["mg2"]


def test_a_restart_an_islanded_hour_and_a_rejection_are_incidents():
    observed = fold(register("mg1"), clock("realtime", 4), register("mg1", incarnation=2),
                    envelope("grid_state", hour=4, connected=(True, False)),
                    envelope("rejection", offender="mg2", rejected_kind="meter_report", code="late", reason="too late"))
    reasons = [i["reason"] for i in page(observed)["incidents"]]
    assert len(reasons) == 3 and reasons[0].startswith("rejected meter_report (late)")
    assert "islanded: 1 of 2 sub-period(s) not connected" in reasons
    assert any(r.startswith("restarted") for r in reasons)


def test_a_message_of_another_run_is_not_taken():
    observed = fold(clock("bidding"))
    stranger = award("mg1", 1.0)
    stranger.run = "another"
    assert not observed.take("key", stranger, 5) and observed.day.awards == {}


def feeder_hour(hour: int, buses: int) -> Msg:
    ac = Msg(violations=("v_min 0.94 at bus 7",) if hour == 3 else (), v_min_pu=0.94, max_loading=0.9, converged=True)
    return envelope("network_hour", hour=hour, stage="plan", network="ieee33", buses=tuple(map(str, range(buses))),
                    lines=tuple(f"{b}-{b + 1}" for b in range(buses - 1)), voltage_pu=(0.98,) * buses,
                    line_loading=(0.5,) * (buses - 1), bus_price_per_mwh=tuple(40.0 + b for b in range(buses)),
                    energy_price_per_mwh=40.0, limit_loading=(1.0,) + (0.2,) * (buses - 2), ac=ac)


def test_two_hundred_agents_on_33_buses_are_heat_maps_and_a_page_a_browser_takes_several_times_a_second():
    agents = [f"mg{i}" for i in range(1, 201)]
    messages = [register(a) for a in agents] + [award(a, 1.0 + i % 7, bus=str(i % 33)) for i, a in enumerate(agents)]
    messages += [feeder_hour(h, 33) for h in range(1, 25)]
    messages += [meter(a, h, (1.5 + i % 3, 0.5)) for h in range(1, 25) for i, a in enumerate(agents)]
    messages.append(clock("realtime", 3))
    shown = page(fold(*messages))
    assert shown["detail"] == [] and len(shown["compact"]["agents"]) == 200 > DETAIL_AGENTS
    assert len(shown["compact"]["deviation_mwh"]) == 200 and len(shown["compact"]["penalty"][0]) == 24
    assert len(shown["compact"]["bills"]) == 2 * RANKED_BILLS
    assert len(shown["feeder"]["bus_prices"]) == 33 and shown["feeder"]["bus_prices"][5][0] == 45.0
    assert shown["feeder"]["current"]["hour"] == 3 and shown["feeder"]["current"]["violations"]
    assert shown["feeder"]["current"]["binding_lines"] == [0]
    size = len(json.dumps(shown, separators=(",", ":")))
    assert size < MAX_BYTES_PER_S / 2, size  # at the board's rate cap, a browser gets it twice a second at least


def test_a_replay_moves_to_the_start_of_any_phase_or_hour_and_plays_on_from_there():
    rec = read_recording(TWO_DAYS)
    items = playable(rec)
    board = Board()
    player = PagePlayer(items, board, rate=1.0, paused=True)
    labels = [m["label"] for m in player.marks]
    noon = labels.index("2026-07-06 realtime hour 12")
    player.control(seek=noon)
    board.render()
    shown = json.loads(board.latest[1])
    assert shown["clock"] == {**shown["clock"], "phase": "realtime", "hour": 12}
    assert shown["paused"] and shown["mark"] == noon and not shown["ended"]
    assert not any(a["bill"]["settled"] for a in shown["detail"])
    player.control(seek=0)  # back to the start: what came after is forgotten
    board.render()
    assert json.loads(board.latest[1])["clock"]["phase"] == "registration"


def test_view_refuses_what_is_not_a_recording_in_one_line(cli, tmp_path):
    junk = tmp_path / "day.mcap"
    junk.write_text("not a recording\n")
    done = cli("view", str(junk))
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and str(junk) in done.stderr


def test_view_refuses_a_port_in_use_in_one_line(cli):
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        done = cli("view", str(TWO_DAYS), "--port", str(port))
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and f":{port}" in done.stderr


@pytest.mark.parametrize("flags, said", [
    (["--host", "0.0.0.0"], "--expose"),  # the run's data to whoever reaches it: only when asked for
    (["--run-id", "day"], "not both"),
    (["--rate", "0"], "--rate"),
])
def test_view_refuses_bad_flags_in_one_line(cli, flags, said):
    done = cli("view", str(TWO_DAYS), *flags)
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and said in done.stderr


@pytest.mark.parametrize("flags, said", [
    (["--view", "--in-process"], "in-process"),
    (["--view-port", "8000"], "goes with --view"),
])
def test_run_refuses_a_page_it_cannot_serve(cli, flags, said):
    done = cli("run", "--agents", "2", *flags)
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and said in done.stderr
