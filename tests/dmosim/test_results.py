"""Recordings as tables, JSON lines and a figure: ``dmosim.results.tables``, ``dmosim export``, ``cat`` and ``plot``.

Every recording here is written in the test with ``RecordingWriter`` from ``synthetic_day`` (a realistic day, built
without solving anything), with the faults a real day may hold put in by hand: a meter report the DMO refused, a
copy of one, a partly islanded hour, incidents, a payload the recorder filed as invalid.
"""

from __future__ import annotations

import base64
import json
import os
import subprocess
import sys
from decimal import Decimal
from pathlib import Path

import matplotlib.pyplot as plt
import pandas as pd
import pytest

from dmosim.bench.recording import synthetic_day
from dmosim.cli import main
from dmo.replay.resettle import as_message, recorded_day, resettle
from dmo.market.clearing import BidCurve, Step, clear
from dmo.operator import outbox
from dmo.operator.config import DayConfig
from dmosim.results.figures import recording_figure, stopped_short
from dmosim.results.tables import TABLE_COLUMNS, open_recording, tables
from messages import HOURS, Incident, Keys, MessageError, decode, encode, make_rejection
from messages.schemas import AgentDay, HandlingTime, MessageCounts
from messages.keys import new_run_id
from messages.recording import RecordingWriter, read_recording, select
from tests.dmosim.synthetic import typed

ROOT = Path(__file__).resolve().parents[2]
DAY, NEXT_DAY = "2026-07-01", "2026-07-02"
K = 3  # sub-periods per hour
REFUSED_MW = 9.5  # the readings of the refused meter report: never in the tables, never settled


def write(path: Path, run_id: str, messages: list[tuple[str, bytes]], metadata: dict | None = None) -> Path:
    with RecordingWriter(path, run_id) as writer:
        writer.start(metadata or {})
        for i, (key, payload) in enumerate(messages):
            writer.write(key, payload, 1_800_000_000_000_000_000 + i * 1_000_000)
    return path


def find(messages: list[tuple[str, bytes]], suffix: str, **fields) -> int:
    """The index of the first message on a key ending in ``suffix`` whose decoded fields are ``fields``."""
    for i, (key, payload) in enumerate(messages):
        if key.endswith(suffix) and all(getattr(decode(payload), k) == v for k, v in fields.items()):
            return i
    raise LookupError(suffix, fields)


def faulty_day(run_id: str, market_day: str = DAY, agents: int = 2) -> list[tuple[str, bytes]]:
    """A synthetic day with: a refused meter report of mg1 hour 5 arriving before the accepted one; an identical
    copy of mg2's hour 6 report, refused as a duplicate; hour 7 islanded in its second sub-period only (hour 12 is
    islanded throughout, as synthetic_day has it); two incidents in the day summary; mg2's schedule stopped at a time
    limit."""
    day = synthetic_day(run_id, agents, K, market_day=market_day)
    i = find(day, "agent/mg1/meter", hour=5)
    key, good = day[i]
    bad = encode(decode(good).model_copy(update={"p_m_mw": (REFUSED_MW,) * K, "deviation_mw": (0.0,) * K}))
    day.insert(i, (key, bad))
    j = find(day, "agent/mg2/meter", hour=6)
    day.insert(j + 1, day[j])
    g = find(day, "dmo/grid", hour=7)
    day[g] = (day[g][0], encode(decode(day[g][1]).model_copy(update={"connected": (True, False, True)})))
    c = find(day, "agent/mg2/schedule")
    day[c] = (day[c][0], encode(decode(day[c][1]).model_copy(update={"status": "time_limit", "mip_gap": 0.0125})))
    s = find(day, "dmo/summary")
    incidents = (Incident(agent="mg2", phase="realtime", hour=6, reason="duplicate meter report"),
                 Incident(agent=None, phase="bidding", hour=None, reason="a bid came late"))
    day[s] = (day[s][0], encode(decode(day[s][1]).model_copy(update={"incidents": incidents, "rejected_messages": 2})))
    for n, (refused_key, payload) in enumerate(((key, bad), day[j])):
        rejection = make_rejection(refused_key, payload, MessageError("a second answer", "duplicate"),
                                   market_day=market_day, offender=refused_key.split("/")[3], received_at=7)
        day.insert(s + n, (f"dmosim/{run_id}/dmo/rejected", encode(rejection)))
    return day


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    run_id = new_run_id()
    path = tmp_path_factory.mktemp("results") / "day.mcap"
    return write(path, run_id, faulty_day(run_id), {"market_day": DAY, "agents": "mg1,mg2"})


@pytest.fixture(scope="module")
def frames(recording) -> dict[str, pd.DataFrame]:
    return open_recording(recording)


def cents(x: float) -> Decimal:
    return Decimal(str(x)).quantize(Decimal("0.01"))


# --- the tables ------------------------------------------------------------------------------------------------

def test_the_schedules_table_says_whose_schedule_stopped_short_and_the_figure_names_it(frames):
    schedules = frames["schedules"]
    assert list(schedules["agent"]) == ["mg1", "mg2"] and (schedules["market_day"] == DAY).all()
    assert list(schedules["stopped_short"]) == [False, True] and list(schedules["status"]) == ["optimal", "time_limit"]
    assert schedules["mip_gap"].iloc[1] == 0.0125
    assert stopped_short(schedules, 1) == "\nschedules stopped short of their gap: mg2 (time_limit, gap 1.25%)"
    many = pd.concat([schedules.assign(agent=schedules["agent"] + str(i), stopped_short=True) for i in range(3)])
    text = stopped_short(many, 2)  # six stopped short: four named, with their day, and how many more
    assert f"mg20 {DAY} (time_limit, gap 1.25%)" in text and text.endswith(" and 2 more") and text.count("(") == 4
    assert stopped_short(schedules.iloc[:1], 1) == stopped_short(None, 1) == ""
    fig = recording_figure(frames)
    assert fig._suptitle.get_text().endswith("mg2 (time_limit, gap 1.25%)")
    plt.close(fig)


def test_every_table_has_its_columns_in_order(frames):
    assert list(frames) == list(TABLE_COLUMNS)
    for name, frame in frames.items():
        assert list(frame.columns) == list(TABLE_COLUMNS[name]), name
        assert (frame["market_day"] == DAY).all(), name


def test_hours_add_up_to_the_recorded_statements_and_to_what_resettle_gives(recording, frames):
    rec = read_recording(recording)
    statements = {msg.agent: msg for _, msg in rec.decoded("settlement_statement")}
    day = recorded_day(rec)
    again = {agent: as_message(day, st) for agent, st in resettle(day).items()}
    hours = frames["hours"]
    assert len(hours) == 2 * 24 and sorted(hours["agent"].unique()) == ["mg1", "mg2"]
    for agent, st in statements.items():
        own = hours[hours["agent"] == agent].sort_values("hour")
        assert own["hour"].tolist() == list(range(1, 25))
        for column in ("energy_charge", "deviation_penalty", "deviation_credit", "total"):
            summed = cents(sum(Decimal(str(v)) for v in own[column]))
            assert summed == cents(getattr(st, column)) == cents(getattr(again[agent], column)), (agent, column)
        assert own["missing_subperiods"].sum() == st.missing_subperiods == 0
        lines = pd.DataFrame([line.model_dump() for line in again[agent].lines])
        for column in ("p_sch_mw", "clearing_price_per_mwh", "import_mwh", "deviation_mwh", "under_import_mwh",
                       "deviation_penalty", "total"):
            assert own[column].tolist() == lines[column].tolist(), (agent, column)
    days = frames["days"].set_index("agent")
    for agent, st in statements.items():
        assert days.loc[agent, "total"] == st.total and days.loc[agent, "deviation_penalty"] == st.deviation_penalty
        own = hours[hours["agent"] == agent]
        assert days.loc[agent, "import_mwh"] == pytest.approx(own["import_mwh"].sum())
        assert days.loc[agent, "award_mwh"] == pytest.approx(sum(day.awards[agent].p_sch_mw))


def test_a_refused_meter_report_is_not_in_the_meter_table_nor_settled(recording, frames):
    meter = frames["meter"]
    assert len(meter) == 2 * 24 * K  # one report per agent and hour: the refused one and the refused copy are out
    assert not meter.duplicated(["agent", "hour", "subperiod"]).any()
    assert REFUSED_MW not in meter["p_m_mw"].tolist()
    rec = read_recording(recording)
    accepted = next(msg for _, msg in rec.decoded("meter_report") if msg.sender == "mg1" and msg.hour == 5
                    and msg.p_m_mw[0] != REFUSED_MW)
    five = meter[(meter["agent"] == "mg1") & (meter["hour"] == 5)]
    assert five["p_m_mw"].tolist() == list(accepted.p_m_mw) and five["subperiod"].tolist() == [1, 2, 3]
    award = next(msg for _, msg in rec.decoded("award") if msg.agent == "mg1")
    assert (five["p_sch_mw"] == award.p_sch_mw[4]).all()
    assert recorded_day(rec).left_out == 2
    assert main(["settle", str(recording)]) == 0  # re-settles identically without the refused report


def test_islanded_hours_and_sub_periods_are_flagged(frames):
    hours, meter = frames["hours"], frames["meter"]
    assert sorted(hours.loc[hours["islanded"], "hour"].unique()) == [7, 12]
    assert hours.groupby("agent")["islanded"].sum().tolist() == [2, 2]
    cut = meter[~meter["connected"].astype(bool)]
    assert sorted(set(zip(cut["hour"], cut["subperiod"]))) == [(7, 2), (12, 1), (12, 2), (12, 3)]


def test_bids_incidents_and_rejections(recording, frames):
    rec = read_recording(recording)
    bid = next(msg for _, msg in rec.decoded("bid") if msg.sender == "mg2")
    bids = frames["bids"]
    own = bids[(bids["agent"] == "mg2") & (bids["hour"] == 3)]
    assert own["step"].tolist() == list(range(1, len(bid.hours[2]) + 1))
    assert own["price_per_mwh"].tolist() == [s.price_per_mwh for s in bid.hours[2]]
    assert own["quantity_mw"].tolist() == [s.quantity_mw for s in bid.hours[2]]
    assert len(bids) == sum(len(steps) for _, msg in rec.decoded("bid") for steps in msg.hours)
    incidents = frames["incidents"]
    assert incidents["reason"].tolist() == ["duplicate meter report", "a bid came late"]
    assert incidents["hour"].iloc[0] == 6 and pd.isna(incidents["hour"].iloc[1]) and pd.isna(incidents["agent"].iloc[1])
    rejections = frames["rejections"]
    assert rejections["key"].tolist() == ["agent/mg1/meter", "agent/mg2/meter"]
    assert rejections["code"].tolist() == ["duplicate", "duplicate"]
    assert rejections["offender"].tolist() == ["mg1", "mg2"]
    assert (rejections["rejected_kind"] == "meter_report").all() and (rejections["received_at"] == 7).all()


def test_empty_tables_keep_their_columns(tmp_path):
    run_id = new_run_id()
    clock_only = synthetic_day(run_id, 1, 1)[:1]
    frames = open_recording(write(tmp_path / "empty.mcap", run_id, clock_only))
    for name, frame in frames.items():
        assert frame.empty and list(frame.columns) == list(TABLE_COLUMNS[name]), name


def test_rows_belong_to_the_market_day_each_message_carries_not_to_the_metadata(tmp_path):
    run_id = new_run_id()
    two = synthetic_day(run_id, 2, K, market_day=DAY) + synthetic_day(run_id, 2, K, market_day=NEXT_DAY, seed=1)
    frames = tables(read_recording(write(tmp_path / "two.mcap", run_id, two, {"market_day": DAY})))
    assert frames["days"][["market_day", "agent"]].values.tolist() == [
        [DAY, "mg1"], [DAY, "mg2"], [NEXT_DAY, "mg1"], [NEXT_DAY, "mg2"]]
    assert frames["hours"].groupby("market_day").size().tolist() == [48, 48]
    assert frames["meter"].groupby("market_day").size().tolist() == [48 * K, 48 * K]
    for day, statement in ((msg.market_day, msg) for msg in (decode(p) for k, p in two if "/statement/" in k)):
        row = frames["days"][(frames["days"]["market_day"] == day) & (frames["days"]["agent"] == statement.agent)]
        assert row["total"].item() == statement.total


# --- dmosim export ---------------------------------------------------------------------------------------------

def test_export_writes_csvs_that_pandas_reads_back_unchanged(recording, frames, tmp_path, capsys):
    out = tmp_path / "tables"
    assert main(["export", str(recording), "--out", str(out)]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert len(printed) == len(TABLE_COLUMNS)
    for name, line in zip(TABLE_COLUMNS, printed):
        assert line.startswith(str(out / f"{name}.csv"))
        back = pd.read_csv(out / f"{name}.csv")
        assert list(back.columns) == list(TABLE_COLUMNS[name]) and len(back) == len(frames[name]), name
    hours = pd.read_csv(out / "hours.csv")
    rec = read_recording(recording)
    for _, st in rec.decoded("settlement_statement"):
        assert cents(hours.loc[hours["agent"] == st.agent, "total"].sum()) == cents(st.total)
    assert hours["islanded"].dtype == bool
    pd.testing.assert_frame_equal(pd.read_csv(out / "meter.csv")[["p_m_mw", "p_sch_mw"]],
                                  frames["meter"][["p_m_mw", "p_sch_mw"]])


def test_export_goes_beside_the_recording_by_default_and_replaces_old_tables(recording, tmp_path, capsys):
    copy = tmp_path / "copy.mcap"
    copy.write_bytes(recording.read_bytes())
    (tmp_path / "copy-tables").mkdir()
    (tmp_path / "copy-tables" / "hours.csv").write_text("stale\n")
    assert main(["export", str(copy)]) == 0
    assert len(capsys.readouterr().out.splitlines()) == len(TABLE_COLUMNS)
    assert list(pd.read_csv(tmp_path / "copy-tables" / "hours.csv").columns) == list(TABLE_COLUMNS["hours"])


def test_parquet_needs_pyarrow(recording, tmp_path, capsys):
    try:
        import pyarrow  # noqa: F401, PLC0415
    except ImportError:
        assert main(["export", str(recording), "--out", str(tmp_path), "--format", "parquet"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "pip install 'dmosim[parquet]'" in err
        return
    assert main(["export", str(recording), "--out", str(tmp_path), "--format", "parquet"]) == 0
    assert list(pd.read_parquet(tmp_path / "hours.parquet").columns) == list(TABLE_COLUMNS["hours"])


# --- dmosim cat ------------------------------------------------------------------------------------------------

def test_cat_prints_one_json_line_per_message_in_log_order(recording, capsys):
    assert main(["cat", str(recording)]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    rec = read_recording(recording)
    assert len(lines) == len(rec.messages)
    assert [x["log_time_ns"] for x in lines] == sorted(m.log_time for m in rec.messages)
    assert all(set(x) == {"log_time_ns", "key", "kind", "message"} for x in lines)
    first = lines[0]
    assert first["key"] == "dmo/clock" and first["kind"] == "clock" and first["message"]["phase"] == "registration"


def test_cat_topics_select_keys_as_replay_does(recording, capsys):
    assert main(["cat", str(recording), "--topics", "agent/*/meter"]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert len(lines) == 2 * 24 + 2  # the refused report and the refused copy were recorded too
    assert {x["key"] for x in lines} == {"agent/mg1/meter", "agent/mg2/meter"}
    assert {x["kind"] for x in lines} == {"meter_report"}
    assert main(["cat", str(recording), "--topics", "dmo/award/*", "--topics", "dmo/summary"]) == 0
    keys = [json.loads(line)["key"] for line in capsys.readouterr().out.splitlines()]
    assert keys == ["dmo/award/mg1", "dmo/award/mg2", "dmo/summary"]


def test_cat_prints_an_invalid_payload_as_base64_with_its_reason(tmp_path, capsys):
    run_id = new_run_id()
    day = synthetic_day(run_id, 1, 1)
    day.insert(3, (f"dmosim/{run_id}/agent/mg1/meter", b"not json at all"))
    path = write(tmp_path / "invalid.mcap", run_id, day)
    assert main(["cat", str(path), "--topics", "agent/mg1/meter"]) == 0
    first = json.loads(capsys.readouterr().out.splitlines()[0])
    assert first["key"] == "agent/mg1/meter" and first["invalid"]["code"] == "not_json" and first["invalid"]["reason"]
    assert base64.b64decode(first["payload_base64"]) == b"not json at all" and "message" not in first


def test_cat_into_a_closed_pipe_stops_quietly(recording, tmp_path, monkeypatch, capsys):
    sink = open(tmp_path / "sink", "w")  # noqa: SIM115

    class ClosedAfterOneLine:
        """A stdout whose reader goes away after the first line, as ``| head -1`` does."""

        def __init__(self):
            self.lines = 0

        def write(self, text):
            self.lines += 1
            if self.lines > 1:
                raise BrokenPipeError(32, "Broken pipe")
            return len(text)

        def flush(self):
            pass

        def fileno(self):
            return sink.fileno()

    monkeypatch.setattr(sys, "stdout", ClosedAfterOneLine())
    assert main(["cat", str(recording)]) == 141
    assert capsys.readouterr().err == ""
    sink.close()


@pytest.mark.slow  # what a real pipe does to a real process, to its very exit (the one above is in-process)
def test_cat_piped_to_head_prints_no_traceback(tmp_path):
    run_id = new_run_id()
    path = write(tmp_path / "big.mcap", run_id, synthetic_day(run_id, 6, K))  # far more than a pipe's buffer
    out = subprocess.run(f"{sys.executable} -m dmosim cat {path} | head -n 1", shell=True, capture_output=True,
                         text=True, timeout=120, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert json.loads(out.stdout)["key"] == "dmo/clock"
    assert out.stderr == "", out.stderr


# --- dmosim plot -----------------------------------------------------------------------------------------------

def test_plot_writes_a_png_beside_the_recording(recording, tmp_path, capsys):
    copy = tmp_path / "plotted.mcap"
    copy.write_bytes(recording.read_bytes())
    assert main(["plot", str(copy)]) == 0
    png = tmp_path / "plotted.png"
    assert capsys.readouterr().out.strip() == str(png)
    data = png.read_bytes()
    assert data.startswith(b"\x89PNG\r\n\x1a\n") and len(data) > 20_000


def test_plot_of_several_days_has_their_totals(tmp_path, capsys):
    run_id = new_run_id()
    two = synthetic_day(run_id, 2, K, market_day=DAY) + synthetic_day(run_id, 2, K, market_day=NEXT_DAY, seed=1)
    path = write(tmp_path / "two.mcap", run_id, two)
    assert main(["plot", str(path), "--out", str(tmp_path / "two-days.png")]) == 0
    assert (tmp_path / "two-days.png").stat().st_size > 20_000


def test_plot_of_a_recording_without_statements_is_refused(tmp_path, capsys):
    run_id = new_run_id()
    path = write(tmp_path / "early.mcap", run_id, synthetic_day(run_id, 1, 1)[:5])
    assert main(["plot", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no settlement statement" in err
    assert not (tmp_path / "early.png").exists()


# --- bad input -------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("verb", ["export", "cat", "plot"])
@pytest.mark.parametrize("what", ["missing", "not mcap"])
def test_bad_files_exit_2_with_one_line(verb, what, tmp_path, capsys):
    path = tmp_path / "day.mcap"
    if what == "not mcap":
        path.write_text("a,b\n1,2\n")
    assert main([verb, str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: ") and str(path) in err
    assert ("no such file" if what == "missing" else "not an MCAP file") in err


def test_an_unknown_format_exits_2_with_one_line(recording, capsys):
    assert main(["export", str(recording), "--format", "xlsx"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "xlsx" in err


def test_a_recording_of_two_days_is_settled_exported_and_printed_day_by_day(tmp_path, capsys):
    run_id = new_run_id()
    two = synthetic_day(run_id, 2, K, market_day=DAY) + synthetic_day(run_id, 2, K, market_day=NEXT_DAY, seed=1)
    path = str(write(tmp_path / "two.mcap", run_id, two, {"market_day": DAY, "days": "2"}))
    capsys.readouterr()
    assert main(["settle", path, "--json"]) == 0
    settled = json.loads(capsys.readouterr().out)
    assert settled["identical"] and settled["market_days"] == [DAY, NEXT_DAY] and len(settled["days"]) == 2
    assert settled["lines"] == 2 * 2 * 24
    assert main(["settle", path, "--day", NEXT_DAY, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["market_days"] == [NEXT_DAY]
    assert main(["export", path, "--day", NEXT_DAY, "--out", str(tmp_path / "t")]) == 0
    assert set(pd.read_csv(tmp_path / "t" / "hours.csv")["market_day"]) == {NEXT_DAY}
    capsys.readouterr()
    assert main(["cat", path, "--day", DAY]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert lines and {line["message"]["market_day"] for line in lines} == {DAY}
    replayed = select(read_recording(path), ["dmo/**"], market_day=NEXT_DAY)  # what replay --day publishes
    assert replayed and {json.loads(m.payload)["market_day"] for m in replayed} == {NEXT_DAY}
    for verb in (["settle", path], ["export", path, "--out", str(tmp_path / "u")], ["cat", path]):
        assert main([*verb, "--day", "2031-01-01"]) == 2
        err = capsys.readouterr().err
        assert err == f"error: --day 2031-01-01: {path} is of {DAY}, {NEXT_DAY}\n"
    assert not (tmp_path / "u").exists()


def test_a_day_settled_by_a_rule_that_cannot_be_loaded_here_is_refused_in_one_line(tmp_path, capsys):
    """The awards name a rule of one's own from a file this machine does not have: re-settling or playing the
    DMO's side cannot honour it, and says so before anything starts."""
    run_id = new_run_id()
    day = synthetic_day(run_id, 1, K, market_day=DAY)
    for i, (key, payload) in enumerate(day):
        message = decode(payload)
        if hasattr(message, "settlement_rule"):
            day[i] = (key, encode(message.model_copy(update={"settlement_rule": "gone/rules.py:mine"})))
    path = write(tmp_path / "day.mcap", run_id, day, {"market_day": DAY, "agents": "mg1"})
    for verb in (["settle"], ["replay", "--as-dmo"]):
        assert main([*verb[:1], str(path), *verb[1:]]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "gone/rules.py:mine" in err, err


def test_bids_summing_exactly_to_the_limit_congest_nothing_in_the_clearing_the_award_and_the_tables(tmp_path):
    """The clearing alone decides congestion and the award carries it: bids that at the ISO price take exactly the
    feeder's import limit ration nothing, so every hour is "none" in the clearing, on the award and in the tables
    (which used to say "import", seeing the awards at the limit)."""
    run_id = new_run_id()
    day = synthetic_day(run_id, 2, K)
    call = decode(day[find(day, "dmo/call_for_bids")][1])
    limit, iso = call.import_limit_mw, call.iso_price_per_mwh
    wants = {"mg1": 0.75 * limit, "mg2": 0.25 * limit}  # 3/4 and 1/4 of it: exactly the limit together
    bids = [BidCurve(a, tuple((Step(p + 50.0, q),) for p in iso)) for a, q in wants.items()]
    clearing = clear(bids, iso, limit, call.export_limit_mw)
    assert clearing.congested == ("none",) * HOURS and clearing.net_import(0) == limit
    config = DayConfig(market_day=DAY, agents=2, iso_price=iso, import_limit=limit, export_limit=call.export_limit_mw,
                       penalty=150.0, credit=0.0, subperiods=K, islanded_hours=(12,), registration_s=60.0,
                       bids_s=60.0, schedule_s=60.0, hour_s=60.0)
    for agent in wants:
        i = find(day, f"dmo/award/{agent}")
        award = outbox.award(config, 1, clearing, agent)
        assert award.congestion == ("none",) * HOURS
        day[i] = (day[i][0], encode(award))
    # the statements settled against these awards, as the DMO would have sent them
    recorded = recorded_day(read_recording(write(tmp_path / "awarded.mcap", run_id, day)))
    for agent, st in resettle(recorded).items():
        i = find(day, f"dmo/statement/{agent}")
        day[i] = (day[i][0], encode(as_message(recorded, st)))
    hours = tables(read_recording(write(tmp_path / "day.mcap", run_id, day)))["hours"]
    assert hours.groupby("hour")["p_sch_mw"].sum().to_numpy() == pytest.approx([limit] * HOURS)  # at the limit
    assert (hours["congestion"] == "none").all()


def test_an_award_older_than_version_5_states_no_congestion_and_the_tables_do_not_guess_it():
    frames = open_recording(ROOT / "tests" / "data" / "schema-v2-two-days.mcap")
    assert len(frames["hours"]) == 2 * 2 * HOURS and frames["hours"]["congestion"].isna().all()
    recording_figure(frames)  # unknown congestion is simply not marked


def test_the_agents_realised_days_are_a_table_of_what_the_dmo_accepted(tmp_path):
    run_id = new_run_id()
    day = synthetic_day(run_id, 2, K)
    realised = {agent: AgentDay(
        sender=agent, market_day=DAY, generation=100.0 * n, startup=10.0, curtailment=0.0, penalty=5.0,
        total=100.0 * n + 15.0, curtailment_mwh=0.0, deviation_mwh=0.5 * n, units={},
        stored_mwh=None if n == 1 else 2.0,
        compute=(HandlingTime(kind="award", hour=None, wall_s=1.5, cpu_s=1.0, started_at=10**18, turn_s=0.5),
                 HandlingTime(kind="grid_state", hour=24, wall_s=0.5, cpu_s=0.25, started_at=10**18 + 10**9, turn_s=0.0)),
        messages=MessageCounts(published=50, received=60, rejected={}, handler_errors=0, ignored={}, sent_again=n,
                               asked=0, faults_injected={}), seq=1000) for n, agent in enumerate(("mg1", "mg2"), 1)}
    at = find(day, "dmo/summary")
    key = Keys(run_id).agent_day
    day[at:at] = [(key(a), encode(msg)) for a, msg in realised.items()]
    other = realised["mg2"].model_copy(update={"total": 1e6 + 15.0, "generation": 1e6, "seq": 1001})
    day[at + 2:at + 2] = [(key("mg2"), encode(other))]  # a second one of the day: refused, recorded as such
    day.insert(at + 3, (f"dmosim/{run_id}/dmo/rejected", encode(make_rejection(
        key("mg2"), encode(other), MessageError("second agent_day", "duplicate"), market_day=DAY, offender="mg2"))))
    frame = tables(read_recording(write(tmp_path / "day.mcap", run_id, day)))["agent_days"]
    assert list(frame.columns) == list(TABLE_COLUMNS["agent_days"])
    assert frame["agent"].tolist() == ["mg1", "mg2"] and frame["total"].tolist() == [115.0, 215.0]
    assert frame["wall_s"].tolist() == [2.0, 2.0] and frame["cpu_s"].tolist() == [1.25, 1.25]
    assert frame["sent_again"].tolist() == [1, 2] and frame["stored_mwh"].isna().tolist() == [True, False]


def test_plot_of_a_run_directory_writes_its_run_png_inside_it(recording, tmp_path, monkeypatch, capsys):
    run_dir = tmp_path / "runs" / "r1"
    run_dir.mkdir(parents=True)
    (run_dir / "recording.mcap").write_bytes(recording.read_bytes())
    monkeypatch.chdir(tmp_path)
    assert main(["plot", "runs/r1"]) == 0
    assert capsys.readouterr().out.strip() == str(Path("runs/r1/run.png"))
    assert (run_dir / "run.png").read_bytes().startswith(b"\x89PNG") and not (tmp_path / "runs" / "r1.png").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["runs"]


def test_every_table_has_a_timestamp_that_pandas_resamples(tmp_path):
    run_id = new_run_id()
    two = synthetic_day(run_id, 2, K, market_day=DAY) + synthetic_day(run_id, 2, K, market_day=NEXT_DAY, seed=1)
    frames = tables(read_recording(write(tmp_path / "two.mcap", run_id, two)))
    hours = frames["hours"]
    assert str(hours["timestamp"].dtype) == "datetime64[ns]" and hours["timestamp"].dt.tz is None
    first = hours[(hours["market_day"] == NEXT_DAY) & (hours["hour"] == 1)]["timestamp"]
    assert (first == pd.Timestamp(f"{NEXT_DAY} 00:00")).all()
    assert (hours["timestamp"] == pd.to_datetime(hours["market_day"].astype(str))
            + pd.to_timedelta(hours["hour"] - 1, unit="h")).all()
    daily = hours.set_index("timestamp").resample("D")["total"].sum()
    assert list(daily.index.strftime("%Y-%m-%d")) == [DAY, NEXT_DAY]
    assert daily.round(2).tolist() == frames["days"].groupby("market_day")["total"].sum().round(2).tolist()
    meter = frames["meter"]
    second = meter[(meter["market_day"] == DAY) & (meter["hour"] == 5) & (meter["subperiod"] == 2)]["timestamp"]
    assert (second == pd.Timestamp(f"{DAY} 04:20")).all()  # the second of K = 3 sub-periods of hour 5
    assert meter.set_index("timestamp").resample("h")["p_m_mw"].count().max() == 2 * K
    for name, frame in frames.items():
        assert "timestamp" in frame and str(frame["timestamp"].dtype) == "datetime64[ns]", name


def test_docs_api_names_every_column_of_every_table():
    text = (ROOT / "docs" / "api.md").read_text()
    for name, columns in TABLE_COLUMNS.items():
        row = next(line for line in text.splitlines() if line.startswith(f"| `{name}` |"))
        assert [c for c in columns if f"`{c}`" not in row] == [], name


def test_the_figure_names_the_rule_marks_restarts_and_missing_hours_and_stays_a_sane_size(tmp_path):
    """Five agents; mg2's process restarted before its hour-10 report (a later incarnation) and its hour-11 report
    lost; no credit anywhere. The figure is titled by the settlement rule, marks both, names no credit, and is at
    most 1,400 px wide."""
    from PIL import Image  # noqa: PLC0415

    from dmosim.results.figures import figure_of, restarts  # noqa: PLC0415
    from dmosim.studies.figures import save  # noqa: PLC0415

    run_id = new_run_id()
    day = synthetic_day(run_id, 5, K, market_day=DAY)
    for i, (key, payload) in enumerate(day):
        msg = decode(payload)
        if "/agent/mg2/" in key:
            later = key.endswith("/meter") and msg.hour >= 10
            day[i] = (key, encode(msg.model_copy(update={"incarnation": 2_000 if later else 1_000})))
    day = [(k, p) for k, p in day if not (k.endswith("agent/mg2/meter") and decode(p).hour == 11)]
    rec = read_recording(write(tmp_path / "five.mcap", run_id, day))
    assert restarts(rec).to_dict("records") == [{"sender": "mg2", "market_day": DAY, "hour": 10}]
    frames = tables(rec)
    assert (frames["hours"]["deviation_credit"] == 0).all()
    figure = figure_of(rec, frames, "five")
    assert "settled by paper:penalty=" in figure.get_suptitle()
    labels = [t.get_text() for legend in figure.legends for t in legend.get_texts()]
    assert "process restarted (the agent)" in labels
    assert "hour with no accepted meter report (missing-data rule)" in labels
    assert not any("credit" in label for label in labels)
    width, height = Image.open(save(figure, tmp_path / "five.png")).size
    assert width <= 1_400 and height <= 1_600, (width, height)


def test_tables_and_the_runs_summary_list_agents_in_natural_order(tmp_path):
    """mg2 before mg10, in every table with an agent column and in the summary ``dmosim run`` prints, not the text
    order mg1, mg10, mg11, mg2."""
    from dmosim.cli.run import summary_table  # noqa: PLC0415

    names = [f"mg{i}" for i in range(1, 12)]
    run_id = new_run_id()
    frames = open_recording(write(tmp_path / "day.mcap", run_id, synthetic_day(run_id, len(names), K)))
    for name, frame in frames.items():
        if "agent" in frame and not frame.empty:
            assert list(dict.fromkeys(frame["agent"])) == names, name
    money = dict.fromkeys(["award_mwh", "import_mwh", "deviation_mwh", "energy_charge", "deviation_penalty",
                           "total"], 0.0)
    result = {"days": [{"market_day": DAY, "islanded_hours": []}], "run_id": run_id, "run_dir": str(tmp_path),
              "settlement": {name: money for name in sorted(names)}, "settlement_rule": "paper",
              "rejected_messages": 0, "incidents": [], "verdict": {"ok": True, "problems": []}}
    listed = [line.split()[0] for line in summary_table(typed(result)).splitlines() if line.startswith("mg")]
    assert listed == names
