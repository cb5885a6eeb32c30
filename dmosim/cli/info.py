"""``dmosim info PATH``: what a recording holds: the run, its market day and agents, duration, channels and counts."""

from __future__ import annotations

import argparse
import datetime as dt
import json

from dmo.replay.resettle import accepted_meter_reports, day_messages, gaps, hour_ranges, rule_named
from messages.recording import BACKFILL_METADATA, Recording

from ..console import print_json
from ..experiment.spec import ExperimentError, parse_experiment, to_toml
from .flags import RECORDING_HELP, load_recording

HELP = "summary of a recording or a run directory: run, market days, agents, channels, counts, what it lacks"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", help=RECORDING_HELP)
    p.add_argument("--json", action="store_true", help="print one JSON object")


def describe(rec: Recording) -> dict:
    meta = rec.metadata
    times = [m.log_time for m in rec.messages]
    days, agents = set(), set()
    for m in rec.messages:
        parts = m.relative_key.split("/")
        if len(parts) >= 3 and parts[0] == "agent":
            agents.add(parts[1])
        elif len(parts) == 3 and parts[0] == "dmo":
            agents.add(parts[2])
        if m.kind == "clock" and m.invalid is None:
            try:
                days.add(json.loads(m.payload)["market_day"])
            except (ValueError, KeyError, TypeError):
                pass
    if meta.get("market_day"):
        days.add(meta["market_day"])
    if meta.get("agents"):
        agents.update(a for a in meta["agents"].split(",") if a)
    invalid = sum(1 for m in rec.messages if m.invalid)
    return {
        "path": rec.path, "bytes": rec.size, "complete": rec.complete, "cut": rec.cut_note,
        "library": rec.library, "run_id": rec.run_id or None, "key_prefix": rec.prefix or None,
        "schema_version": rec.schema_version, "market_days": sorted(days), "agents": sorted(agents),
        "seed": _int(meta.get("seed")), "config": _json(meta.get("config")), "versions": _json(meta.get("versions")),
        "recorder_started_at": meta.get("recorder_started_at"),
        "start": _iso(min(times)) if times else None, "end": _iso(max(times)) if times else None,
        "duration_s": round((max(times) - min(times)) / 1e9, 3) if times else 0.0,
        "messages": len(rec.messages), "invalid_messages": invalid,
        "backfilled_messages": _int(rec.other_metadata.get(BACKFILL_METADATA, {}).get("messages", 0)),
        "missing": gaps(rec), "missing_meter": missing_meter(rec), "settled_by": settled_by(rec),
        "strategies": strategies(rec), "feeder": feeder(rec),
        "chunks": rec.chunks, "compression": sorted(rec.compression),
        "attachments": [{"name": a.name, "media_type": a.media_type, "bytes": len(a.data)} for a in rec.attachments],
        "channels": [{"key": c.relative_key, "messages": c.messages, "schema": c.schema_name,
                      "schema_encoding": c.schema_encoding, "message_encoding": c.message_encoding}
                     for c in sorted(rec.channels.values(), key=lambda c: c.relative_key)],
    }


def missing_meter(rec: Recording) -> list[dict]:
    """The meter data the DMO did not have, per market day and agent: the ``hours`` with no accepted meter report
    and how many ``subperiods`` of each, as the agent's recorded statement settled them by the missing-data rule
    (its ``missing`` lines, with the ``penalty`` of those hours, $); without a recorded statement, the hours whose
    grid state is recorded and no accepted meter report is (every sub-period of each). ``settled`` says which."""
    statements, awards, operated = {}, {}, {}
    for _, st in day_messages(rec, None, "settlement_statement"):
        statements.setdefault((st.market_day, st.agent), st)
    for _, award in day_messages(rec, None, "award"):
        awards.setdefault((award.market_day, award.agent), award)
    for _, grid in day_messages(rec, None, "grid_state"):
        operated.setdefault(grid.market_day, set()).add(grid.hour)
    metered = {(m.market_day, m.sender, m.hour) for _, m in accepted_meter_reports(rec)[0]}
    out = []
    for day, agent in sorted(set(statements) | set(awards)):
        st = statements.get((day, agent))
        if st is not None:
            lines = [line for line in st.lines if line.missing]
            hours, subperiods = [ln.hour for ln in lines], [ln.missing_subperiods for ln in lines]
            penalty = round(sum(ln.deviation_penalty for ln in lines), 2)
        else:
            hours = [h for h in sorted(operated.get(day, ())) if (day, agent, h) not in metered]
            subperiods, penalty = [awards[day, agent].subperiods] * len(hours), None
        if hours:
            out.append({"market_day": day, "agent": agent, "hours": hours, "subperiods": subperiods,
                        "penalty": penalty, "settled": st is not None})
    return out


def strategies(rec: Recording) -> dict[str, str | None]:
    """Each registered agent's bidding strategy as its (latest) registration names it; None: it named none."""
    return {msg.sender: msg.strategy for _, msg in rec.decoded("registration")}


def feeder(rec: Recording) -> dict | None:
    """The feeder the market cleared on, as its first network_hour names it, and each agent's bus as its (first)
    award names it; None for a copper-plate market."""
    hours = day_messages(rec, None, "network_hour")
    first = next(iter(hours), None)
    if first is None:
        return None
    buses: dict[str, str] = {}
    for _, award in day_messages(rec, None, "award"):
        if award.bus is not None:
            buses.setdefault(award.agent, award.bus)
    return {"network": first[1].network, "buses": len(first[1].buses), "agents": dict(sorted(buses.items()))}


def settled_by(rec: Recording) -> dict[str, str]:
    """Market day -> the settlement rule its awards name (docs/settlement.md)."""
    out: dict[str, str] = {}
    for _, award in day_messages(rec, None, "award"):
        out.setdefault(award.market_day, rule_named(award))
    return dict(sorted(out.items()))


def _int(text):
    try:
        return int(text)
    except (TypeError, ValueError):
        return text


def _json(text):
    if text is None:
        return None
    try:
        return json.loads(text)
    except ValueError:
        return text


def _iso(ns: int) -> str:
    return dt.datetime.fromtimestamp(ns / 1e9, dt.timezone.utc).isoformat(timespec="milliseconds")


def render(info: dict) -> str:
    state = "complete" if info["complete"] else f"INCOMPLETE: {info['cut']}"
    strategies = ", ".join(f"{agent} {named or '?'}" for agent, named in sorted(info["strategies"].items()))
    rows = [f"file:        {info['path']} ({info['bytes']:,} bytes, {state})",
            f"run:         {info['run_id'] or '-'} (keys under {info['key_prefix'] or '-'}/)",
            f"market day{'s:' if len(info['market_days']) > 1 else ': '} {', '.join(info['market_days']) or '-'}",
            f"agents:      {', '.join(info['agents']) or '-'}",
            f"strategies:  {strategies or '-'}",
            "feeder:      " + (f"{info['feeder']['network']} ({info['feeder']['buses']} buses): "
                                + ", ".join(f"{a} at bus {b}" for a, b in info["feeder"]["agents"].items())
                                if info["feeder"] else "none (a copper plate)"),
            f"seed:        {info['seed'] if info['seed'] is not None else '-'}"]
    experiment = experiment_toml(info["config"])
    if experiment is None and info["config"] is not None:  # a configuration this version does not read
        rows.append(f"config:      {json.dumps(info['config'], sort_keys=True)}")
    versions = info["versions"] if isinstance(info["versions"], dict) else {}
    rows.append(f"versions:    message schemas v{info['schema_version'] or '?'}"
                + "".join(f", {k} {v}" for k, v in sorted(versions.items())))
    rows.append(f"written by:  {info['library'] or '-'}")
    rows.append(f"duration:    {info['duration_s']:.3f} s" + (f" ({info['start']} to {info['end']})" if info["start"] else ""))
    rows.append(f"messages:    {info['messages']} on {len(info['channels'])} channels"
                + (f", {info['invalid_messages']} invalid" if info["invalid_messages"] else "")
                + f"; {info['chunks']} chunks ({', '.join(info['compression']) or '-'})")
    rules = set(info["settled_by"].values())
    if len(rules) == 1:
        rows.append(f"settled by:  {rules.pop()}")
    elif rules:
        rows += [f"settled by:  {day}: {rule}" for day, rule in info["settled_by"].items()]
    if info["backfilled_messages"]:
        rows.append(f"backfilled:  {info['backfilled_messages']} messages from before the recorder joined, given by "
                    "the DMO's history")
    rows += [f"missing:     {gap}" for gap in info["missing"]]
    rows += [f"missing:     {_meter_gap(m)}" for m in info["missing_meter"]]
    if not info["missing"] and not info["missing_meter"]:
        rows.append("missing:     nothing: every registration, award, meter report, statement and the day summary")
    if info["attachments"]:
        rows.append("attachments: " + ", ".join(f"{a['name']} ({a['bytes']:,} bytes)" for a in info["attachments"]))
    width = max([len("channel")] + [len(c["key"]) for c in info["channels"]])
    rows.append(f"{'channel':<{width}}  {'messages':>8}  schema")
    for c in info["channels"]:
        rows.append(f"{c['key']:<{width}}  {c['messages']:>8}  {c['schema'] or '-'} ({c['schema_encoding'] or 'none'}, "
                    f"{c['message_encoding']})")
    if experiment is not None:  # last: the summary above stays on one screen
        rows.append("experiment (TOML, as the run directory's experiment.toml holds it; `dmosim run FILE` runs it):")
        rows += [f"  {line}" if line else "" for line in experiment.splitlines()[1:]]
    return "\n".join(rows)


def experiment_toml(config) -> str | None:
    """The recorded configuration as an experiment file (``dmosim.experiment.spec.to_toml``, the writer of the run
    directory's experiment.toml), or None if it is not an experiment this version reads."""
    if not isinstance(config, dict):
        return None
    try:
        return to_toml(parse_experiment(config, "config"))
    except ExperimentError:
        return None


def _meter_gap(m: dict) -> str:
    """One agent's day of missing meter data, as one line."""
    what = (f"{m['agent']} {m['market_day']}: no accepted meter report for hour(s) {hour_ranges(m['hours'])} "
            f"({sum(m['subperiods'])} sub-period(s))")
    if not m["settled"]:
        return what + "; no statement recorded"
    return what + f", settled by the missing-data rule (penalty in those hours: ${m['penalty']:,.2f})"


def run(args) -> int:
    info = describe(load_recording(args.path))
    if args.json:
        print_json(info)
    else:
        print(render(info))
    return 0
