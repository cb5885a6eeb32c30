"""A recording as tidy pandas tables: one row per observation, columns named as the wire names them (units in the
names: ``_mw``, ``_mwh``, ``_per_mwh``; money in $), every table with a ``market_day`` column.

``tables(rec)`` is pure: it reads only the ``messages.recording.Recording`` it is given; ``open_recording(path)``
reads the file first. Messages are read as the receivers read them (valid, from the key's owner), and grouped by
the ``market_day`` each one carries, so a recording of several days gives rows of each. Of the DMO's own
messages the first of each (day, agent) or (day, hour) counts, as in ``dmo.replay.resettle``; of the agents' bids,
meter reports and realised days, those the DMO accepted (``dmo.replay.resettle.accepted_meter_reports``). The
columns of each table, with their types, are ``TABLE_COLUMNS``; an empty table still has them.

An hour's congestion is the clearing's, as the award carries it (docs/market.md); an award older than version 5
of the protocol carries none, and the hour's congestion is then unknown (``<NA>``), never inferred from the awards.
"""

from __future__ import annotations

import os
from pathlib import Path

import pandas as pd

from dmo.replay.resettle import accepted_messages, accepted_meter_reports, day_messages
from messages import relative_key
from messages.recording import Recording, read_recording
from scenarios.horizon import HOURS

from .order import by_agent

_KEY_TYPES = {"market_day": "string", "agent": "string", "hour": "int64", "subperiod": "int64"}
_MONEY = {"energy_charge": "float64", "deviation_penalty": "float64", "deviation_credit": "float64",
          "total": "float64"}
_WHEN = {"market_day": "string", "timestamp": "datetime64[ns]"}  # the day, and the start of the row's hour
TABLE_COLUMNS: dict[str, dict[str, str]] = {
    "hours": {**_WHEN, "agent": "string", "hour": "int64", "clearing_price_per_mwh": "float64",
              "p_sch_mw": "float64", "import_mwh": "float64", "deviation_mwh": "float64",
              "under_import_mwh": "float64", **_MONEY, "missing_subperiods": "int64", "islanded": "bool",
              "congestion": "string", "bus": "string", "energy_price_per_mwh": "Float64",
              "loss_price_per_mwh": "Float64", "congestion_price_per_mwh": "Float64",
              "voltage_price_per_mwh": "Float64"},
    "days": {**_WHEN, "agent": "string", **_MONEY, "missing_subperiods": "int64",
             "import_mwh": "float64", "deviation_mwh": "float64", "under_import_mwh": "float64",
             "award_mwh": "float64"},
    "meter": {**_WHEN, "agent": "string", "hour": "int64", "subperiod": "int64", "p_m_mw": "float64",
              "deviation_mw": "float64", "p_sch_mw": "float64", "connected": "boolean"},
    "bids": {**_WHEN, "agent": "string", "hour": "int64", "step": "int64",
             "price_per_mwh": "float64", "quantity_mw": "float64"},
    "incidents": {**_WHEN, "agent": "string", "phase": "string", "hour": "Int64", "reason": "string"},
    "rejections": {**_WHEN, "key": "string", "code": "string", "reason": "string",
                   "offender": "string", "rejected_kind": "string", "payload_size": "int64", "received_at": "int64"},
    "agent_days": {**_WHEN, "agent": "string", "generation": "float64", "startup": "float64",
                   "curtailment": "float64", "penalty": "float64", "total": "float64", "curtailment_mwh": "float64",
                   "deviation_mwh": "float64", "stored_mwh": "Float64", "wall_s": "float64", "cpu_s": "float64",
                   "sent_again": "int64", "asked": "int64"},
    "schedules": {**_WHEN, "agent": "string", "status": "string", "stopped_short": "bool", "mip_gap": "Float64",
                  "scenarios": "int64", "expected_cost": "float64"},
    "network": {**_WHEN, "hour": "int64", "stage": "string", "network": "string", "clearing": "string",
                "substation_mw": "float64",
                "energy_price_per_mwh": "Float64", "shed_mw": "Float64", "spilled_mw": "Float64", "v_min_pu": "float64",
                "max_loading": "float64", "ac_converged": "bool", "ac_v_min_pu": "float64", "ac_v_min_bus": "string",
                "ac_v_max_pu": "float64", "ac_v_max_bus": "string", "ac_max_loading": "float64",
                "ac_max_loading_line": "string", "ac_voltage_error_pu": "float64", "ac_flow_error_mw": "float64",
                "ac_losses_mw": "float64", "ac_substation_mw": "float64", "ac_violations": "string",
                "ac_margin": "float64"},
    "buses": {**_WHEN, "hour": "int64", "stage": "string", "bus": "string", "injection_mw": "float64",
              "voltage_pu": "float64", "bus_price_per_mwh": "Float64", "loss_price_per_mwh": "Float64",
              "congestion_price_per_mwh": "Float64", "voltage_price_per_mwh": "Float64", "shed_mw": "Float64",
              "spilled_mw": "Float64", "binding_voltage": "string", "voltage_shadow_price_per_pu": "Float64"},
    "lines": {**_WHEN, "hour": "int64", "stage": "string", "line": "string", "loading": "float64",
              "limit_loading": "Float64", "binding_facet": "Int64", "line_shadow_price_per_mwh": "Float64"},
}
_PER_BUS = ("injection_mw", "voltage_pu", "bus_price_per_mwh", "loss_price_per_mwh", "congestion_price_per_mwh",
            "voltage_price_per_mwh", "shed_mw", "spilled_mw", "binding_voltage", "voltage_shadow_price_per_pu")
_PER_LINE = {"line_loading": "loading", "limit_loading": "limit_loading", "binding_facet": "binding_facet",
             "line_shadow_price_per_mwh": "line_shadow_price_per_mwh"}  # the message's field: the table's column


def open_recording(path: str | os.PathLike) -> dict[str, pd.DataFrame]:
    """The tables of the recording at ``path`` (``read_recording``: a cut file gives what precedes the cut; a file
    that is not a recording raises ``messages.recording.RecordingError``)."""
    return tables(read_recording(path))


def tables(rec: Recording) -> dict[str, pd.DataFrame]:
    """Every table of the recording, by name, in the order of ``TABLE_COLUMNS``."""
    grid, statements = _grid(rec), _statements(rec)
    hours = _hours(statements, grid, _congestion(rec))
    network = _network_hours(rec)
    return {"hours": hours, "days": _days(statements, hours), "meter": _meter(rec, grid), "bids": _bids(rec),
            "incidents": _incidents(rec), "rejections": _rejections(rec), "agent_days": _agent_days(rec),
            "schedules": _schedules(rec),
            "network": _network(network), "buses": _buses(network), "lines": _lines(network)}


def write_tables(frames: dict[str, pd.DataFrame], directory: Path, fmt: str = "csv") -> dict[Path, int]:
    """Each table as ``directory/<name>.<fmt>`` (csv, or parquet with pyarrow), without an index column; the rows
    of each file written. ``directory`` must exist."""
    written = {}
    for name, frame in frames.items():
        path = directory / f"{name}.{fmt}"
        if fmt == "csv":
            frame.to_csv(path, index=False)
        else:
            frame.to_parquet(path, index=False)
        written[path] = len(frame)
    return written


def _typed(name: str, frame: pd.DataFrame | None) -> pd.DataFrame:
    """The table's columns, in order and with their types; an empty table keeps them."""
    columns = TABLE_COLUMNS[name]
    if frame is None or frame.empty:
        return pd.DataFrame({c: pd.Series(dtype=t) for c, t in columns.items()})
    return frame.assign(timestamp=timestamps(frame))[list(columns)].astype(columns).reset_index(drop=True)


def timestamps(frame: pd.DataFrame) -> pd.Series:
    """When each row's period starts, as a timezone-naive datetime (market days have no time zone on the wire):
    its market day's midnight, plus ``hour - 1`` hours (hour 1 is 00:00-01:00), plus, per sub-period, its share
    of the hour (sub-period k of K starts (k - 1) / K h in). A row with no hour (an incident of the whole day, a
    rejection, a day's totals) is at the day's midnight."""
    when = pd.to_datetime(frame["market_day"].astype(str), format="%Y-%m-%d")
    if "hour" in frame:
        when = when + pd.to_timedelta(frame["hour"].astype("Float64").fillna(1).to_numpy(dtype=float) - 1, unit="h")
    if "subperiod" in frame:
        per_hour = frame.groupby(["market_day", "agent", "hour"])["subperiod"].transform("max")
        share = (frame["subperiod"] - 1) / per_hour
        when = when + pd.to_timedelta(share.to_numpy(dtype=float) * 3600, unit="s").round("ms")
    return when.astype("datetime64[ns]")


def _dumps(rec: Recording, kind: str) -> list[dict]:
    """The valid messages of one kind, of every day, from their key's owner, as JSON-like dicts, in log order."""
    return [msg.model_dump(mode="json") for _, msg in day_messages(rec, None, kind)]


def _frame(records: list[dict], columns: list[str]) -> pd.DataFrame:
    """These columns of the records, the keys typed alike in every frame so that frames merge on them. The
    ``agent`` of an agent's message is its sender; the DMO's messages name theirs."""
    frame = pd.DataFrame(records)
    if "agent" not in frame:
        frame = frame.rename(columns={"sender": "agent"})
    frame = frame.reindex(columns=columns)
    return frame.astype({c: t for c, t in _KEY_TYPES.items() if c in frame})


def _numbered(frame: pd.DataFrame, by: list[str], column: str) -> pd.DataFrame:
    """Number the rows of each group 1, 2, ... in ``column``: the hour, sub-period or step of an exploded list."""
    frame[column] = (frame.groupby(by, sort=False).cumcount() + 1).astype("int64")
    return frame


def _grid(rec: Recording) -> pd.DataFrame:
    """(market_day, hour, subperiod, connected) of the first grid state recorded for each day and hour."""
    states = _frame(_dumps(rec, "grid_state"), ["market_day", "hour", "connected"])
    states = states.drop_duplicates(["market_day", "hour"]).explode("connected", ignore_index=True)
    return _numbered(states, ["market_day", "hour"], "subperiod").astype({"connected": "bool"})


def _statements(rec: Recording) -> list[dict]:
    """The first statement recorded for each market day and agent."""
    first: dict[tuple[str, str], dict] = {}
    for st in _dumps(rec, "settlement_statement"):
        first.setdefault((st["market_day"], st["agent"]), st)
    return list(first.values())


_COMPONENTS = ["energy_price_per_mwh", "loss_price_per_mwh", "congestion_price_per_mwh", "voltage_price_per_mwh"]


def _congestion(rec: Recording) -> pd.DataFrame:
    """(market_day, agent, hour, congestion, bus and price components) from the first award recorded for each day
    and agent: the clearing's own decision. An award that states no congestion (older than version 5) gives no
    rows; one of the copper plate no bus and no components (<NA>)."""
    awards = _frame(_dumps(rec, "award"), ["market_day", "agent", "congestion", "bus", *_COMPONENTS])
    awards = awards.drop_duplicates(["market_day", "agent"])
    awards = awards[awards["congestion"].notna()]
    for column in _COMPONENTS:  # the copper plate's null: 24 missing values, so every column explodes alike
        awards[column] = awards[column].map(lambda v: [None] * HOURS if v is None or v is pd.NA else v)
    return _numbered(awards.explode(["congestion", *_COMPONENTS], ignore_index=True), ["market_day", "agent"], "hour")


def _hours(statements: list[dict], grid: pd.DataFrame, congestion: pd.DataFrame) -> pd.DataFrame:
    if not statements:
        return _typed("hours", None)
    lines = pd.json_normalize(statements, record_path="lines", meta=["market_day", "agent"])
    lines = lines.astype({c: t for c, t in _KEY_TYPES.items() if c in lines})
    islanded = (~grid.groupby(["market_day", "hour"])["connected"].all()).rename("islanded").reset_index()
    hours = lines.merge(islanded, on=["market_day", "hour"], how="left")
    hours["islanded"] = hours["islanded"].astype("boolean").fillna(False)  # no grid state recorded: not islanded
    hours = hours.merge(congestion, on=["market_day", "agent", "hour"], how="left")  # no congestion stated: <NA>
    return _typed("hours", hours.sort_values(["market_day", "agent", "hour"], key=by_agent))


def _days(statements: list[dict], hours: pd.DataFrame) -> pd.DataFrame:
    if not statements:
        return _typed("days", None)
    totals = _frame(statements, ["market_day", "agent", *_MONEY, "missing_subperiods"])
    energy = (hours.groupby(["market_day", "agent"], as_index=False)
              [["import_mwh", "deviation_mwh", "under_import_mwh", "p_sch_mw"]].sum()
              .rename(columns={"p_sch_mw": "award_mwh"}))  # an award of P_sch MW for 1 h is P_sch MWh
    return _typed("days", totals.merge(energy, on=["market_day", "agent"]).sort_values(["market_day", "agent"], key=by_agent))


def _meter(rec: Recording, grid: pd.DataFrame) -> pd.DataFrame:
    reports, _ = accepted_meter_reports(rec)
    if not reports:
        return _typed("meter", None)
    meter = _frame([msg.model_dump(mode="json") for _, msg in reports],
                   ["market_day", "agent", "hour", "p_m_mw", "deviation_mw"])
    meter = _numbered(meter.explode(["p_m_mw", "deviation_mw"], ignore_index=True), ["market_day", "agent", "hour"],
                      "subperiod")
    awards = _frame(_dumps(rec, "award"), ["market_day", "agent", "p_sch_mw"]).drop_duplicates(["market_day", "agent"])
    awards = _numbered(awards.explode("p_sch_mw", ignore_index=True), ["market_day", "agent"], "hour")
    meter = meter.merge(awards, on=["market_day", "agent", "hour"], how="left")
    meter = meter.merge(grid, on=["market_day", "hour", "subperiod"], how="left")  # no grid state: connected NA
    return _typed("meter", meter.sort_values(["market_day", "agent", "hour", "subperiod"], key=by_agent))


def _bids(rec: Recording) -> pd.DataFrame:
    kept, _ = accepted_messages(rec, "bid")
    bids = _frame([msg.model_dump(mode="json") for _, msg in kept], ["market_day", "agent", "hours"])
    bids = bids.drop_duplicates(["market_day", "agent"])  # the DMO takes one bid per agent and day
    hours = _numbered(bids.explode("hours", ignore_index=True), ["market_day", "agent"], "hour")
    steps = hours.explode("hours", ignore_index=True).dropna(subset="hours")  # an empty hour: no offer, no row
    if steps.empty:
        return _typed("bids", None)
    steps = _numbered(steps, ["market_day", "agent", "hour"], "step")
    prices = pd.DataFrame(steps["hours"].tolist(), index=steps.index)
    return _typed("bids", steps.join(prices).sort_values(["market_day", "agent", "hour", "step"], key=by_agent))


def _incidents(rec: Recording) -> pd.DataFrame:
    last = {summary["market_day"]: summary for summary in _dumps(rec, "day_summary")}  # the latest of each day
    if not any(summary["incidents"] for summary in last.values()):
        return _typed("incidents", None)
    return _typed("incidents", pd.json_normalize(list(last.values()), record_path="incidents", meta=["market_day"]))


def _rejections(rec: Recording) -> pd.DataFrame:
    rejections = _frame(_dumps(rec, "rejection"), list(TABLE_COLUMNS["rejections"]))
    prefix = rec.prefix
    rejections["key"] = rejections["key"].map(lambda key: relative_key(key, prefix))
    return _typed("rejections", rejections)


def _schedules(rec: Recording) -> pd.DataFrame:
    """The last day-ahead schedule the DMO accepted of each agent and day (a rejoined agent sends its schedule
    again): how its solve ended (``status``, ``stopped_short``: ``messages.Schedule.stopped_short``), its
    certified gap, scenarios and expected cost."""
    kept, _ = accepted_messages(rec, "schedule")
    last = {(msg.market_day, msg.sender): msg for _, msg in kept}
    if not last:
        return _typed("schedules", None)
    rows = [{"market_day": m.market_day, "agent": m.sender, "status": m.status, "stopped_short": m.stopped_short,
             "mip_gap": m.mip_gap, "scenarios": m.scenarios, "expected_cost": m.expected_cost} for m in last.values()]
    return _typed("schedules", pd.DataFrame(rows).sort_values(["market_day", "agent"], key=by_agent))


def _agent_days(rec: Recording) -> pd.DataFrame:
    """The first realised day (``agent_day``) the DMO accepted of each agent and day: its own cost by term, what it
    curtailed and deviated, its storage at midnight, the computation of the messages it handled (summed) and how
    many payloads it sent again and asked for. An agent that sent none has no row."""
    kept, _ = accepted_messages(rec, "agent_day")
    days = {}
    for _, msg in kept:
        days.setdefault((msg.market_day, msg.sender), msg)
    if not days:
        return _typed("agent_days", None)
    rows = [{**msg.model_dump(exclude={"compute", "messages", "units"}), "agent": msg.sender,
             "wall_s": sum(e.wall_s for e in msg.compute), "cpu_s": sum(e.cpu_s for e in msg.compute),
             "sent_again": msg.messages.sent_again, "asked": msg.messages.asked} for msg in days.values()]
    return _typed("agent_days", pd.DataFrame(rows).sort_values(["market_day", "agent"], key=by_agent))


def _network_hours(rec: Recording) -> list[dict]:
    """The first network_hour recorded of each day, hour and stage (a feeder's day; none on the copper plate)."""
    first: dict[tuple[str, int, str], dict] = {}
    for msg in _dumps(rec, "network_hour"):
        first.setdefault((msg["market_day"], msg["hour"], msg["stage"]), msg)
    return sorted(first.values(), key=lambda m: (m["market_day"], m["stage"] != "plan", m["hour"]))


def _network(hours: list[dict]) -> pd.DataFrame:
    """One row per day, hour and stage: how the plan was cleared, the DMO's position, LinDistFlow's lowest voltage
    and highest loading, shed load, and the AC check (its violations joined by "; ")."""
    if not hours:
        return _typed("network", None)
    rows = [{"market_day": m["market_day"], "hour": m["hour"], "stage": m["stage"], "network": m["network"],
             "clearing": m["clearing"], "substation_mw": m["substation_mw"], "energy_price_per_mwh": m["energy_price_per_mwh"],
             "shed_mw": None if m["shed_mw"] is None else sum(m["shed_mw"]),
             "spilled_mw": None if m["spilled_mw"] is None else sum(m["spilled_mw"]),
             "v_min_pu": min(v for b, v in zip(m["buses"], m["voltage_pu"]) if b != m["substation"]),
             "max_loading": max(m["line_loading"]),
             **{f"ac_{k}": ("; ".join(v) if k == "violations" else v) for k, v in m["ac"].items()}}
            for m in hours]
    return _typed("network", pd.DataFrame(rows))


def _buses(hours: list[dict]) -> pd.DataFrame:
    """One row per day, hour, stage and bus: the microgrids' injection, the voltage and, in the plan, the prices."""
    if not hours:
        return _typed("buses", None)
    frame = pd.DataFrame([{"market_day": m["market_day"], "hour": m["hour"], "stage": m["stage"], "bus": m["buses"],
                           **{k: m[k] if m[k] is not None else [None] * len(m["buses"]) for k in _PER_BUS}}
                          for m in hours])
    return _typed("buses", frame.explode(["bus", *_PER_BUS], ignore_index=True))


def _lines(hours: list[dict]) -> pd.DataFrame:
    """One row per day, hour, stage and line: its loading by LinDistFlow (apparent power over its limit) and, in
    the plan, what binds."""
    if not hours:
        return _typed("lines", None)
    frame = pd.DataFrame([{"market_day": m["market_day"], "hour": m["hour"], "stage": m["stage"], "line": m["lines"],
                           **{column: m[k] if m[k] is not None else [None] * len(m["lines"])
                              for k, column in _PER_LINE.items()}} for m in hours])
    return _typed("lines", frame.explode(["line", *_PER_LINE.values()], ignore_index=True))
