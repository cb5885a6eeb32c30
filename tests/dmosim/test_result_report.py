"""The run's result is typed (``dmosim.results.report.RunReport``): its JSON Schema in docs is the one the model
generates, docs/experiments.md's table names every key, a result reads back to the same JSON with the keys that do
not apply left out, and a file that is not a result is refused in one line."""

from __future__ import annotations

import json
import re
from pathlib import Path

import jsonschema
import pytest

from dmo.operator.finished import ENVELOPE
from dmo.operator.report import DayReport, DmoReport, ReportedDay
from dmo.operator.results import RunResult
from dmosim.cli.main import main
from dmosim.console import UsageError
from dmosim.results.report import RESULT_SCHEMA, RunReport, parse_result, read_result, result_schema, result_text
from messages.schemas import AgentDay
from scenarios.horizon import HOURS

ROOT = Path(__file__).resolve().parents[2]
LAUNCHED = {"wall_s": 2.5, "experiment": "run", "run_dir": "/runs/r", "logs": "/runs/r/logs", "recording": None,
            "faults": [], "restarts": {}, "verdict": {"ok": True, "problems": []}}


def day(n: int) -> DayReport:
    money = {"energy_charge": 10.0 * n, "deviation_penalty": 1.25, "credit": 0.0, "total": 10.0 * n + 1.25,
             "award_mwh": 3.0, "import_mwh": 3.5, "deviation_mwh": 0.5, "missing_subperiods": 0}
    return DayReport.model_validate({
        "day": n, "market_day": f"2026-07-0{n}", "islanded_hours": [n + 3], "clearing_prices": [40.0] * HOURS,
        "congestion": ["none"] * HOURS, "awards": {"mg1": [0.5] * HOURS}, "settlement": {"mg1": money},
        "day_summary": {"agents": ["mg1"], "energy_charge": 10.0 * n, "deviation_penalty": 1.25, "credit": 0.0,
                        "total": 10.0 * n + 1.25, "deviation_mwh": 0.5, "missing_subperiods": 0,
                        "agents_without_meter": []},
        "expected_cost": {"mg1": 99.5}, "schedules_stopped_short": [
            {"agent": "mg1", "status": "time_limit", "mip_gap": None}],
        "rejected_messages": 1, "rejected_by_code": {"stale": 1}, "accepted_messages": {"bid": 1},
        "received_again": 0, "dropped_messages": {}, "locked_out": [],
        "incidents": [{"agent": "mg1", "phase": "realtime", "hour": 5, "reason": "late"}],
        "phase_s": {"bidding": 0.5}})


def run_report(days: int) -> RunReport:
    dmo = RunResult([day(n) for n in range(1, days + 1)], "paper:penalty=150,credit=0", ["mg1"]).report(
        "20260701T000000-abcdef", {"published": 3, "in_process": True})
    return RunReport.model_validate({**dict(dmo), **LAUNCHED})


def test_docs_hold_the_json_schema_the_result_generates_and_dmosim_schemas_writes_it(tmp_path):
    held = json.loads((ROOT / "docs" / "result.schema.json").read_text())
    assert held == result_schema(), ("docs/result.schema.json differs from the result's model: write it again with "
                                     f"`dmosim schemas --out DIR` and copy DIR/{RESULT_SCHEMA}")
    jsonschema.Draft202012Validator.check_schema(held)
    assert main(["schemas", "--out", str(tmp_path)]) == 0
    assert json.loads((tmp_path / RESULT_SCHEMA).read_text()) == held


def test_the_result_table_of_experiments_md_names_every_key_of_the_result():
    text = (ROOT / "docs" / "experiments.md").read_text()
    section = text[text.index("## The result"):]
    section = section[:section.index("\n## ", 1)]
    named = {name for row in re.findall(r"^\| ([^|]+) \|", section, re.M) for name in re.findall(r"`(\w+)`", row)}
    assert named == set(RunReport.model_fields)


def test_experiments_md_names_the_keys_dmosim_run_adds_to_the_dmo_s_result():
    text = " ".join((ROOT / "docs" / "experiments.md").read_text().split())
    said = text[text.index("(`DmoReport`: every key"):]
    said = said[:said.index(")")]
    assert set(re.findall(r"`(\w+)`", said)) - {"DmoReport"} == set(RunReport.model_fields) - set(DmoReport.model_fields)


def test_a_realised_day_has_the_fields_of_an_agent_day_without_its_envelope_and_with_the_run_s_day():
    assert set(ReportedDay.model_fields) == set(AgentDay.model_fields) - ENVELOPE | {"day", "market_day"}


@pytest.mark.parametrize("days", [1, 2])
def test_a_result_reads_back_to_the_same_json_with_the_keys_that_do_not_apply_left_out(days):
    report = run_report(days)
    text = result_text(report)
    data = json.loads(text)
    jsonschema.validate(data, result_schema())
    assert parse_result(text, "result.json") == report and result_text(parse_result(text, "r")) == text
    assert data["recording"] is None and "recorded" not in data and "reproduced" not in data
    assert data["schedules_stopped_short"][0]["mip_gap"] is None  # a null that is a value, not an absent key
    one_day = {"day", "day_summary", "expected_cost", "phase_s"}
    if days == 1:
        assert one_day <= set(data) and "market_days" not in data and "market_day" not in data["incidents"][0]
    else:
        assert not one_day & set(data) and data["market_days"] == ["2026-07-01", "2026-07-02"]
        assert [i["market_day"] for i in data["incidents"]] == data["market_days"]
        assert data["settlement"]["mg1"]["total"] == 32.5 and data["islanded_hours"] == [[4], [5]]


@pytest.mark.parametrize("text, wrong", [
    ("{", "the top: Invalid JSON"),
    ("[]", "the top: Input should be an object"),
    ("{}", "run_id: Field required"),
])
def test_text_that_is_not_a_result_is_one_line_naming_what_is_wrong(text, wrong):
    with pytest.raises(UsageError) as caught:
        parse_result(text, "runs/r/result.json")
    line = str(caught.value)
    assert "\n" not in line and line.startswith("runs/r/result.json: not a dmosim result: ") and wrong in line


def test_a_result_file_with_a_wrong_value_or_none_at_all_is_one_line(tmp_path):
    data = json.loads(result_text(run_report(1)))
    data["days"][0]["settlement"]["mg1"]["total"] = "a lot"
    (tmp_path / "result.json").write_text(json.dumps(data))
    with pytest.raises(UsageError, match=r"result.json: not a dmosim result: days\.0\.settlement\.mg1\.total: "):
        read_result(tmp_path / "result.json")
    with pytest.raises(UsageError, match="cannot read the result"):
        read_result(tmp_path / "none.json")
