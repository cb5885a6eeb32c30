"""Bad input, tried in volume (docs/faults.md, docs/protocol.md).

Messages: more than 10,000 hostile payloads are generated from the JSON Schema of every message kind and mutated
(wrong types, NaN and infinities, huge and negative numbers, missing and unknown fields, wrong kinds, versions,
days and senders, broken JSON, oversized payloads), plus replays of the day's own messages with their old sequence
numbers. They go to a running DMO and two running agents, over Zenoh, through every phase of the day. No process
may crash, the settlement must equal that of an undisturbed day with the same seeds, and every payload must be
counted where it arrived: by the DMO as a rejection with the code predicted here (and published with its reason),
by an agent as refused by its transport or ignored.

Files: mutated case files, fleet files and recordings go to the CLI in this process; it must answer with exit 0
or with one line and exit 2 (``settle`` may also list differences and exit 1), never a traceback.
"""

from __future__ import annotations

import collections
import contextlib
import io
import json
import math
import re
import signal
import threading
import time
import tomllib
from pathlib import Path

import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from test_market_day import DAY, DEADLINES, ENV, TINY, dmosim

from dmosim.cli import main as cli_main
from dmosim.launch.processes import Roles, free_port, wait_listening
from messages import (HOURS, KINDS, SCHEMA_VERSION, SCHEMAS, AgentTotals, Award, Bid, BidStep, CallForBids, Clock,
                      DaySummary, GridState, Incident, MessageError, MeterReport, Registration, Rejection, Schedule,
                      check_route, decode, encode, parse_key)
from messages.keys import new_run_id
from messages.recording import RecordingWriter
from messages.transport import Bus, BusConfig
from scenarios.case import DATA_DIR

AGENTS = ("mg1", "mg2")
# The run's token is drawn by the DMO as it starts; payloads are made before, with this in its place, and sent with
# the real one put in (the same length, hex), so that they get past the DMO's first check and reach the others.
TOKEN = "0123456789abcdef" * 2
WRONG_DAYS = ("2026-06-30", "2026-07-02", "1999-12-31")
BEFORE_THE_AGENTS = time.time_ns()  # an incarnation below it is a process of theirs older than the live one
DMO_TOPICS = {"registration": "register", "bid": "bid", "schedule": "schedule", "meter_report": "meter"}
AGENT_KEYS = {"call_for_bids": ("dmo/call_for_bids",), "grid_state": ("dmo/grid",), "day_summary": ("dmo/summary",),
              "rejection": ("dmo/rejected",), "award": ("dmo/award/mg1", "dmo/award/mg2"),
              "settlement_statement": ("dmo/statement/mg1", "dmo/statement/mg2")}
SUBSCRIBED = {a: {"dmo/call_for_bids", "dmo/grid", "dmo/summary", f"dmo/award/{a}", f"dmo/statement/{a}"}
              for a in AGENTS}


# --- strategies from the JSON Schemas ---------------------------------------------------------------------------

def from_schema(schema: dict, root: dict | None = None) -> st.SearchStrategy:
    """Instances of a JSON Schema, for the subset our message schemas use ($ref, anyOf, const, enum, objects with
    properties or patternProperties, arrays, strings with patterns, bounded numbers). Arrays are kept short
    except where the schema fixes their length (24 hours)."""
    root = root or schema
    if "$ref" in schema:
        return st.deferred(lambda: from_schema(root["$defs"][schema["$ref"].rsplit("/", 1)[1]], root))
    if "anyOf" in schema:
        return st.one_of([from_schema(s, root) for s in schema["anyOf"]])
    if "const" in schema:
        return st.just(schema["const"])
    if "enum" in schema:
        return st.sampled_from(schema["enum"])
    kind = schema.get("type")
    if kind == "object":
        if "properties" in schema:
            return st.fixed_dictionaries({k: from_schema(v, root) for k, v in schema["properties"].items()})
        (pattern, values), = schema.get("patternProperties", {".*": {}}).items()
        return st.dictionaries(st.from_regex(pattern, fullmatch=True), from_schema(values, root), max_size=2)
    if kind == "array":
        low = schema.get("minItems", 0)
        return st.lists(from_schema(schema.get("items", {}), root), min_size=low,
                        max_size=min(schema.get("maxItems", low + 3), max(low, 3)))
    if kind == "string":
        if "pattern" in schema:
            return st.from_regex(schema["pattern"], fullmatch=True).filter(
                lambda s: len(s) <= schema.get("maxLength", 10**6))
        return st.text(min_size=schema.get("minLength", 0), max_size=min(schema.get("maxLength", 20), 20))
    if kind == "integer":
        return st.integers(schema.get("minimum"), schema.get("maximum"))
    if kind == "number":
        return st.floats(schema.get("minimum", schema.get("exclusiveMinimum")), schema.get("maximum"),
                         exclude_min="exclusiveMinimum" in schema, allow_nan=False, allow_infinity=False)
    if kind == "boolean":
        return st.booleans()
    if kind == "null":
        return st.none()
    return st.none()


def templates() -> dict[str, list[dict]]:
    """Realistic messages of each kind (as on the wire), the closest a hostile sender gets to a valid one."""
    hourly = tuple(float(h) for h in range(HOURS))
    line = dict(hour=1, p_sch_mw=1.0, clearing_price_per_mwh=50.0, energy_charge=50.0, import_mwh=1.0,
                deviation_mwh=0.0, under_import_mwh=0.0, deviation_penalty=0.0, deviation_credit=0.0, total=50.0,
                missing=False, missing_subperiods=0)
    msgs = [
        Registration(sender="mg1", market_day=DAY, case="paper", max_import_mw=16.0, max_export_mw=16.0, seq=0),
        Bid(sender="mg2", market_day=DAY, hours=((BidStep(price_per_mwh=40.0, quantity_mw=2.0),),) * HOURS, seq=1),
        Schedule(sender="mg1", market_day=DAY, status="optimal", commitment={"G1": (1,) * HOURS}, expected_cost=1e4,
                 p_m_expected_mw=hourly, scenarios=1, mip_gap=0.01, seq=2),
        MeterReport(sender="mg2", market_day=DAY, hour=3, subperiods=1, p_m_mw=(2.5,), deviation_mw=(0.5,), seq=5),
        CallForBids(sender="dmo", market_day=DAY, iso_price_per_mwh=hourly, price_floor_per_mwh=-1000.0,
                    price_cap_per_mwh=1e4, import_limit_mw=16.0, export_limit_mw=10.0, penalty_per_mwh=150.0,
                    subperiods=1, deadline_s=120.0, seq=3),
        Award(sender="dmo", market_day=DAY, agent="mg1", p_sch_mw=hourly, clearing_price_per_mwh=hourly,
              penalty_per_mwh=150.0, subperiods=1, rules_version=1, rules="rules", seq=9),
        GridState(sender="dmo", market_day=DAY, hour=4, subperiods=1, connected=(True,), seq=20),
        Clock(sender="dmo", market_day=DAY, phase="realtime", hour=4, deadline_s=60.0, day=1, days=1, seq=19),
        DaySummary(sender="dmo", market_day=DAY, agents=AGENTS, clearing_price_per_mwh=hourly,
                   totals={"mg1": AgentTotals(energy_charge=1.0, deviation_penalty=0.0, deviation_credit=0.0,
                                              total=1.0)},
                   rejected_messages=0, incidents=(Incident(agent="mg1", phase="realtime", hour=2, reason="late"),),
                   seq=80),
        Rejection(sender="dmo", market_day=DAY, key="dmosim/x/agent/mg1/bid", code="late", reason="late",
                  offender="mg1", rejected_kind="bid", payload_size=10, payload_sha256="0" * 64, received_at=1, seq=7),
    ]
    out: dict[str, list[dict]] = collections.defaultdict(list)
    for m in msgs:
        out[m.kind].append(json.loads(encode(m.model_copy(update={"run": TOKEN}))))
    out["settlement_statement"].append(dict(
        kind="settlement_statement", schema_version=1, sender="dmo", market_day=DAY, seq=70, sent_at=1, agent="mg1",
        penalty_per_mwh=150.0, credit_per_mwh=0.0, rules_version=1,
        lines=[dict(line, hour=h) for h in range(1, HOURS + 1)], energy_charge=1200.0, deviation_penalty=0.0,
        deviation_credit=0.0, total=1200.0, missing_subperiods=0))
    return out


TEMPLATES = templates()
HOSTILE_VALUES = st.one_of(
    st.text(max_size=8), st.integers(-(2**70), 2**70), st.floats(), st.booleans(), st.none(),
    st.sampled_from([1e308, -1e308, 2**63, 2**64, -1, 0, -0.0, 10**400, "NaN", "1", "true", "", "\u0000"]),
    st.lists(st.integers(-3, 3), max_size=3), st.dictionaries(st.text(max_size=3), st.integers(), max_size=2))


def _paths(data, prefix=()):
    """Every place in a JSON value: (path, value) for each object member and array item, depth first."""
    if isinstance(data, dict):
        for k, v in data.items():
            yield prefix + (k,), v
            yield from _paths(v, prefix + (k,))
    elif isinstance(data, list):
        for i, v in enumerate(data):
            yield prefix + (i,), v
            yield from _paths(v, prefix + (i,))


def _set(data, path, value):
    for part in path[:-1]:
        data = data[part]
    data[path[-1]] = value


def _delete(data, path):
    for part in path[:-1]:
        data = data[part]
    del data[path[-1]]


_POOL: dict[str, list[dict]] = {}


def schema_instances(kind: str, n: int = 25) -> list[dict]:
    """n instances of the kind's JSON Schema, drawn once (drawing one costs milliseconds; mutating it, far less)."""
    if kind not in _POOL:
        out: list[dict] = []

        @settings(max_examples=n, database=None, deadline=None, derandomize=True, phases=[Phase.generate],
                  suppress_health_check=list(HealthCheck))
        @given(from_schema(SCHEMAS[kind]))
        def collect(instance):
            out.append(instance)

        collect()
        _POOL[kind] = out
    return _POOL[kind]


@st.composite
def mutated(draw, kind: str) -> dict | list | str | int | None:
    """A message of ``kind`` (a template or an instance of its JSON Schema) with up to three hostile changes."""
    base = draw(st.one_of(st.sampled_from(TEMPLATES[kind]), st.sampled_from(schema_instances(kind))))
    data = json.loads(json.dumps(base))
    for _ in range(draw(st.integers(0, 3))):
        how = draw(st.sampled_from(["replace", "replace", "replace", "numbers", "delete", "extra", "kind",
                                    "version", "day", "seq", "sender", "impostor", "shape"]))
        paths = list(_paths(data)) if isinstance(data, (dict, list)) else []
        if how == "replace" and paths:
            _set(data, draw(st.sampled_from(paths))[0], draw(HOSTILE_VALUES))
        elif how == "numbers" and paths:  # huge, negative, non-finite quantities where numbers belong
            numeric = [p for p, v in paths if isinstance(v, (int, float)) and not isinstance(v, bool)]
            for path in draw(st.lists(st.sampled_from(numeric), max_size=4)) if numeric else ():
                _set(data, path, draw(st.sampled_from([1e308, -1e308, -1.0, -(2**62), 2**63 - 1, math.inf,
                                                       -math.inf, math.nan, 1e-320])))
        elif how == "delete" and paths:
            _delete(data, draw(st.sampled_from(paths))[0])
        elif isinstance(data, dict):
            if how == "extra":
                data[draw(st.text(min_size=1, max_size=10))] = draw(HOSTILE_VALUES)
            elif how == "kind":
                data["kind"] = draw(st.one_of(st.sampled_from(KINDS), st.text(max_size=12), HOSTILE_VALUES))
            elif how == "version":
                data["schema_version"] = draw(st.sampled_from([0, SCHEMA_VERSION + 1, 7, 10**6, -1, "1", 1.0, True]))
            elif how == "day":
                data["market_day"] = draw(st.sampled_from([*WRONG_DAYS, "2026-02-30", "26-07-01", "", "today"]))
            elif how == "seq":
                data["seq"] = draw(st.sampled_from([-1, 2**63, 2**64, 1.5, "7", None]))
            elif how == "sender":
                data["sender"] = draw(st.sampled_from([*AGENTS, "dmo", "DMO", "recorder", "evil", "mg3", "", "mg 1",
                                                       "x" * 40]))
            elif how == "impostor":  # a well-formed message from someone who is not in the day
                data["sender"] = draw(st.sampled_from(["mg3", "evil", "MG1", "mg1x"]))
            elif how == "shape":
                data = draw(st.sampled_from([[data], "a string", 42, None, {"message": data}]))
    return data


@st.composite
def hostile(draw, target: str) -> tuple[str, bytes]:
    """One hostile payload and the key (relative to the run prefix) it is sent on; ``target`` is "dmo" (keys the
    DMO listens to) or "agents" (keys the agents listen to)."""
    if target == "dmo":
        kind = draw(st.sampled_from(sorted(DMO_TOPICS) + ["award", "grid_state", "call_for_bids"]))
        data = draw(mutated(kind))
        sender = data.get("sender") if isinstance(data, dict) else None
        owner = sender if isinstance(sender, str) and sender and draw(st.integers(0, 3)) else draw(
            st.sampled_from([*AGENTS, "evil", "dmo", "Mg1", "a/b"]))
        topic = DMO_TOPICS.get(kind, "meter") if draw(st.integers(0, 5)) else draw(
            st.sampled_from(["register", "bid", "schedule", "meter", "award", "status", "meter/x"]))
        key = f"agent/{owner}/{topic}"
    else:
        kind = draw(st.sampled_from(sorted(AGENT_KEYS)))
        data = draw(mutated(kind))
        key = draw(st.sampled_from(AGENT_KEYS[kind]))
    how = draw(st.sampled_from(["json"] * 6 + ["truncate", "garbage", "binary", "utf8", "deep", "nan"]))
    text = json.dumps(data, allow_nan=True).encode()
    if how == "truncate":
        text = text[:draw(st.integers(0, max(0, len(text) - 1)))]
    elif how == "garbage":
        at = draw(st.integers(0, len(text)))
        text = text[:at] + draw(st.binary(min_size=1, max_size=8)) + text[at:]
    elif how == "binary":
        text = draw(st.binary(max_size=64))
    elif how == "utf8":
        text = text.replace(b'"', b'"\xc3\x28', 1)
    elif how == "deep":
        depth = draw(st.integers(100, 5000))
        text = b"[" * depth + b"]" * depth
    elif how == "nan":
        text = re.sub(rb"(?<=[:\[,])-?[0-9][0-9.eE+-]*", draw(st.sampled_from([b"NaN", b"Infinity", b"-Infinity",
                                                                             b"1e999", b"0x10"])), text, count=1)
    return key, text


def verdict(key: str, payload: bytes, run_id: str, registered: bool) -> str | None:
    """What the receiver makes of a hostile payload, by the same checks the Bus, the DMO and the agents apply: a
    rejection code, "wrong_run", "wrong_day", "unregistered" or "stale" (their first checks), or None when only the
    phase (or the sender's process) could refuse it. ``registered``: whether the agents have registered by the time
    it arrives (a registration of theirs is then a rejoin, which belongs to the run, not to a day)."""
    try:
        msg = decode(payload, expected_kind=parse_key(key).kind)
        check_route(key, msg, run_id)
    except MessageError as err:
        return err.code
    if msg.run != TOKEN:
        return "wrong_run"
    if registered and msg.kind == "registration" and msg.sender in AGENTS:
        return "stale" if msg.incarnation < BEFORE_THE_AGENTS else None
    if msg.market_day != DAY:
        return "wrong_day"
    if key.split("/")[2] == "agent" and msg.kind != "registration" and msg.sender not in AGENTS:
        return "unregistered"
    return None


BATCH = 50


def generate(target: str, n: int, run_id: str, registered: bool = True) -> list[tuple[str, bytes, str]]:
    """n hostile payloads (relative key, payload, expected code), each certainly refused: a payload only the phase
    would refuse is sent on the wrong market day (and as from an agent's earlier process) instead, so that none can
    take part in the day. ``registered``: whether they are sent after the agents registered."""
    out: list[tuple[str, bytes, str]] = []
    prefix = f"dmosim/{run_id}/"

    @settings(max_examples=n // BATCH, database=None, deadline=None, derandomize=True, phases=[Phase.generate],
              suppress_health_check=list(HealthCheck))
    @given(st.lists(hostile(target), min_size=BATCH, max_size=BATCH))
    def collect(batch):
        for key, payload in batch:
            code = verdict(prefix + key, payload, run_id, registered)
            if code in (None, "stale"):  # a stale one too: the test's watch takes what is of the day for real
                data = json.loads(payload)
                data["market_day"] = WRONG_DAYS[len(out) % len(WRONG_DAYS)]
                if data["kind"] == "registration":
                    data["incarnation"] = len(out) % 1000  # an agent's earlier process
                payload = json.dumps(data).encode()
                code = verdict(prefix + key, payload, run_id, registered)
            assert code is not None
            out.append((key, payload, code))

    collect()
    return out


def oversized(n: int) -> list[tuple[str, bytes, str]]:
    return [(f"agent/{AGENTS[i % 2]}/meter", b'{"kind":"meter_report","pad":"' + b"x" * (1 << 20) + b'"}', "oversize")
            for i in range(n)]


# --- the day under fire ------------------------------------------------------------------------------------------

class Watch:
    """The test's own view of the day: the DMO's clock (and the run's token), its rejections, and every payload the
    agents and the DMO published (for replays). Only messages of the day (right run, right market day) count;
    hostile ones are of another run or day, or impostors."""

    def __init__(self, bus: Bus):
        self.lock = threading.Lock()
        self.phase, self.hour, self.token = None, 0, None
        self.changed = threading.Condition(self.lock)
        self.rejections: list[Rejection] = []
        self.summary: DaySummary | None = None
        self.statements: dict[str, object] = {}
        self.sent: list[tuple[str, bytes, object]] = []  # (relative key, payload, message) of the real processes
        self.seen: set[bytes] = set()
        self.prefix = bus.keys.prefix + "/"
        self.run_id = bus.keys.run_id
        bus.subscribe_raw(bus.keys.everything(), self.on_payload)  # raw: no warning per hostile payload

    def on_payload(self, key, payload, at):
        try:
            msg = decode(payload, expected_kind=parse_key(key).kind)
            check_route(key, msg, self.run_id)
        except MessageError:
            return
        if msg.market_day != DAY or msg.sender not in (*AGENTS, "dmo") or msg.run in ("", TOKEN):  # hostile ones
            return
        with self.lock:
            if msg.kind == "clock":
                self.phase, self.hour, self.token = msg.phase, msg.hour or 0, msg.run
            elif msg.kind == "rejection":
                self.rejections.append(msg)
            elif msg.kind == "day_summary":
                self.summary = msg
            elif msg.kind == "settlement_statement":
                self.statements[msg.agent] = msg
            elif msg.kind == "receipt":
                pass
            elif payload not in self.seen:  # replays come back here: keep the original only
                self.seen.add(payload)
                self.sent.append((key[len(self.prefix):], payload, msg))
            self.changed.notify_all()

    def wait(self, what, timeout=300.0):
        with self.lock:
            assert self.changed.wait_for(lambda: what(self), timeout), f"timed out at {self.phase} {self.hour}"


def start_day(roles: Roles, tmp: Path, run_id: str, recorded: bool = False):
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    common = ["--run-id", run_id, "--market-day", DAY]
    # each hour's grid state half a second late: the day is still in real time when the flood and the replays of
    # hours 3 and 6 come (its hours otherwise take milliseconds)
    roles.start("dmo", dmosim("dmo", *common, "--listen", endpoint, "--agents", str(len(AGENTS)), "--subperiods", "1",
                              "--fault", "delay:dmo/grid:0.5",
                              "--result", str(tmp / "result.json"), *DEADLINES, "--insecure",  # hostile peers join
                              # on the honest agents' keys (no credentials here), more than their budgets allow: what
                              # is tested is that each is refused and counted; the budget, in test_faults.py
                              "--budget", "1000000,1000000000",
                              *(["--await-recorder", "60"] if recorded else [])), log=tmp / "dmo.log", env=ENV)
    wait_listening(port, 60, lambda: roles.roles["dmo"].process.poll() is None)
    return endpoint


def start_recorder(roles: Roles, tmp: Path, run_id: str, endpoint: str, record: Path):
    """The DMO started with a recording waits for the recorder before its first message (its registration clock)."""
    roles.start("recorder", dmosim("record", "--out", str(record), "--run-id", run_id, "--connect", endpoint,
                                   "--meta", f"market_day={DAY}"), log=tmp / "recorder.log", env=ENV)


def start_agents(roles: Roles, tmp: Path, run_id: str, endpoint: str):
    for agent in AGENTS:
        roles.start(agent, dmosim("agent", "--run-id", run_id, "--market-day", DAY, "--id", agent, "--connect",
                                  endpoint, "--agents", str(len(AGENTS)), "--lease", "1", *TINY), log=tmp / f"{agent}.log",
                                  env=ENV)


def finish(roles: Roles, tmp: Path) -> dict:
    for name in ("dmo", *AGENTS):
        code = roles.roles[name].process.wait(timeout=120)
        assert code == 0, f"{name} exited {code}: " + (tmp / f"{name}.log").read_text()[-3000:]
    if "recorder" in roles.roles:
        roles.roles["recorder"].process.send_signal(signal.SIGTERM)
        assert roles.roles["recorder"].process.wait(timeout=60) == 0
    return json.loads((tmp / "result.json").read_text())


def agent_counts(result: dict, agent: str) -> dict:
    """The agent's message counts as its realised day (agent_day, in the DMO's result) reports them."""
    days = result["realised"].get(agent)
    assert days, f"{agent} did not report its realised day"
    return days[-1]["messages"]


def bill(result: dict) -> dict:
    return {a: (s["energy_charge"], s["deviation_penalty"], s["total"], s["missing_subperiods"])
            for a, s in result["settlement"].items()}


def replays(watch: Watch, hour: int, copies: int) -> tuple[list, list]:
    """Copies of the day's own messages, sent again: to the DMO, each agent message of an earlier phase or of an
    hour already closed, half byte for byte (each taken as that message again: receipted, nothing more) and half
    changed but with its old seq (refused as a duplicate); to the agents, the call for bids, their awards and grid
    states of closed hours, byte for byte. Every one must be refused or ignored."""
    with watch.lock:
        sent = list(watch.sent)
    to_dmo, to_agents = [], []
    for key, payload, msg in sent:
        if msg.kind in ("meter_report", "grid_state") and msg.hour >= hour - 1:
            continue  # its hour may still be open: not yet a replay
        if key.startswith("agent/"):
            k = getattr(msg, "subperiods", 0)
            changed = {"registration": {"max_import_mw": 0.0}, "bid": {"hours": ((),) * HOURS},
                       "schedule": {"expected_cost": -1.0},
                       "meter_report": {"p_m_mw": (-16.0,) * k, "deviation_mw": (0.0,) * k}}
            forged = encode(msg.model_copy(update=changed[msg.kind]))
            with watch.lock:
                watch.seen.add(forged)  # the test's own forgery: never to be taken for what the agents said
            to_dmo += [(key, payload, "again") if i % 2 == 0 else (key, forged, "duplicate") for i in range(copies)]
        elif msg.kind in ("call_for_bids", "award", "grid_state"):
            to_agents += [(key, payload, msg.kind)] * copies
    return to_dmo, to_agents


def test_ten_thousand_hostile_messages_crash_nothing_change_no_settlement_and_are_all_counted(tmp_path):
    run_id = new_run_id()
    (tmp_path / "undisturbed").mkdir()
    with Roles() as reference:  # the same day undisturbed, run meanwhile on its own prefix and port
        start_agents(reference, tmp_path / "undisturbed", run_id + "r",
                     start_day(reference, tmp_path / "undisturbed", run_id + "r"))
        to_dmo = generate("dmo", 5000, run_id, registered=False) + generate("dmo", 2000, run_id) + oversized(10)
        to_agents = generate("agents", 3000, run_id)
        undisturbed = finish(reference, tmp_path / "undisturbed")
    assert undisturbed["rejected_messages"] == 0
    record = tmp_path / "day.mcap"
    replayed_to_dmo, replayed_to_agents = [], []
    with Roles() as roles:
        endpoint = start_day(roles, tmp_path, run_id, recorded=True)
        with Bus(run_id, "hostile", BusConfig(mode="client", connect=(endpoint,)), announce=False) as bus:
            watch = Watch(bus)
            start_recorder(roles, tmp_path, run_id, endpoint, record)

            def put(items):
                for key, payload, _ in items:
                    bus.publish_raw(f"{bus.keys.prefix}/{key}", payload.replace(TOKEN.encode(), watch.token.encode()))

            # 1. before any agent: the DMO is in registration. Its port listens before it subscribes to the agents'
            # keys; its registration clock comes after (and after the recorder joined, which the watch precedes)
            watch.wait(lambda w: w.phase == "registration", 120)
            assert watch.token not in ("", TOKEN)
            put(to_dmo[:5000])
            watch.wait(lambda w: len(w.rejections) >= 5000, 120)
            start_agents(roles, tmp_path, run_id, endpoint)
            # 2. while the agents schedule, and at hours 3 and 6 with replays of the day so far
            watch.wait(lambda w: w.phase in ("scheduling", "realtime"))
            put(to_dmo[5000:])
            put(to_agents)
            for hour, copies in ((3, 40), (6, 40)):
                watch.wait(lambda w, h=hour: w.phase == "realtime" and w.hour >= h)
                dmo_items, agent_items = replays(watch, watch.hour, copies)
                put(dmo_items)
                put(agent_items)
                replayed_to_dmo += dmo_items
                replayed_to_agents += agent_items
            watch.wait(lambda w: w.summary is not None)
            result = finish(roles, tmp_path)
            refused = [item for item in to_dmo + replayed_to_dmo if item[2] != "again"]
            watch.wait(lambda w: len(w.rejections) >= len(refused), 60)  # the last ones

    # the day itself is untouched: same awards, same settlement, nothing accepted twice, nothing lost
    assert bill(result) == bill(undisturbed)
    assert result["awards"] == undisturbed["awards"]
    assert result["accepted_messages"] == undisturbed["accepted_messages"]
    assert result["transport"]["handler_errors"] == 0 and result["locked_out"] == []

    # every exact copy of an accepted message was taken as that message again (as were the agents' own resends)
    copies = sum(1 for _, _, code in replayed_to_dmo if code == "again")
    resent = sum(agent_counts(result, a)["sent_again"] for a in AGENTS)
    assert copies > 0 and copies <= result["received_again"] <= copies + resent

    # every other hostile payload to the DMO was rejected once, with the code predicted here and a reason
    everything = refused
    expected = collections.Counter(code for _, _, code in everything)
    assert result["rejected_messages"] == len(everything) >= 7000
    assert result["rejected_by_code"] == dict(expected)
    assert len(watch.rejections) == len(everything) and all(r.reason for r in watch.rejections)
    assert len({c for _, _, c in everything}) >= 8  # the hostile payloads reached most rejection codes
    summary_rejections = [i for i in result["incidents"] if "rejected in all" in i["reason"]]
    assert summary_rejections and str(len(everything)) in summary_rejections[0]["reason"]

    # and every one to an agent was refused by its transport or ignored, and counted
    for agent in AGENTS:
        counts = agent_counts(result, agent)
        mine = [(k, c) for k, _, c in to_agents if k in SUBSCRIBED[agent]]
        assert sum(counts["rejected"].values()) == sum(1 for _, c in mine if c not in ("wrong_day", "wrong_run"))
        assert counts["handler_errors"] == 0
        ignored = counts["ignored"]
        assert ignored.get("wrong_day", 0) == sum(1 for _, c in mine if c == "wrong_day")
        assert ignored.get("wrong_run", 0) == sum(1 for _, c in mine if c == "wrong_run")
        again = collections.Counter(kind for key, _, kind in replayed_to_agents if key in SUBSCRIBED[agent])
        asked = counts["asked"]  # what it asked the DMO for may cross what the DMO sent it anyway
        for kind, reason in (("call_for_bids", "call_for_bids_again"), ("award", "award_again"),
                             ("grid_state", "grid_state_of_an_operated_hour")):
            assert again[kind] <= ignored.get(reason, 0) <= again[kind] + asked, (kind, ignored, asked)
    tried = len(to_dmo) + len(replayed_to_dmo) + len(to_agents) + len(replayed_to_agents)
    assert tried >= 10_000

    # the recording keeps them all, and re-settles to the recorded statements
    assert cli_main(["settle", str(record)]) == 0
    print(f"\nhostile messages tried {tried}: to the DMO {len(to_dmo) + len(replayed_to_dmo)} (rejected "
          f"{result['rejected_messages']}, taken again {copies}: "
          f"{dict(sorted(expected.items()))}), to the agents {len(to_agents) + len(replayed_to_agents)}; "
          f"settlements changed 0; accepted messages lost 0")


# --- the CLI's file inputs ----------------------------------------------------------------------------------------

def toml_dumps(data: dict) -> str:
    """A small TOML writer for what the case and fleet files hold (tables, arrays of tables, scalars, arrays)."""

    def string(v: str) -> str:
        return json.dumps(v, ensure_ascii=False).replace("\x7f", "\\u007f")

    def value(v) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, float):
            return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
        if isinstance(v, int):
            return str(v)
        if isinstance(v, str):
            return string(v)
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        if isinstance(v, dict):
            return "{" + ", ".join(f"{string(k)} = {value(x)}" for k, x in v.items()) + "}"
        return string(str(v))

    def table(d: dict, name: str) -> list[str]:
        lines, nested = [], []
        for k, v in d.items():
            if isinstance(v, dict) and v and all(isinstance(x, dict) for x in v.values()):
                nested.append((k, v, False))
            elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
                nested.append((k, v, True))
            else:
                lines.append(f"{string(k)} = {value(v)}")
        for k, v, many in nested:
            sub = f"{name}.{string(k)}" if name else string(k)
            for item in (v if many else [v]):
                lines += ["", f"[[{sub}]]" if many else f"[{sub}]", *table(item, sub)]
        return lines

    return "\n".join(table(data, "")) + "\n"


@st.composite
def mutated_file(draw, text: str) -> bytes:
    """A file's text with hostile changes to its values and structure, or damaged bytes."""
    if draw(st.integers(0, 3)) == 0:  # damaged bytes
        data = bytearray(text.encode())
        for _ in range(draw(st.integers(1, 4))):
            at = draw(st.integers(0, max(0, len(data) - 1)))
            how = draw(st.sampled_from(["flip", "cut", "insert"]))
            if how == "flip" and data:
                data[at] ^= 1 << draw(st.integers(0, 7))
            elif how == "cut":
                del data[at:]
            else:
                data[at:at] = draw(st.binary(min_size=1, max_size=6))
        return bytes(data)
    data = tomllib.loads(text)
    for _ in range(draw(st.integers(1, 3))):
        paths = list(_paths(data))
        how = draw(st.sampled_from(["replace", "replace", "numbers", "delete", "extra"]))
        if how == "replace" and paths:
            _set(data, draw(st.sampled_from(paths))[0], draw(FILE_VALUES))
        elif how == "numbers" and paths:
            numeric = [p for p, v in paths if isinstance(v, (int, float)) and not isinstance(v, bool)]
            if numeric:
                _set(data, draw(st.sampled_from(numeric)), draw(st.sampled_from(
                    [-1, 0, -1.0, 1e308, -1e308, math.inf, -math.inf, math.nan, 2**62, -(2**62), 0.5])))
        elif how == "delete" and paths:
            _delete(data, draw(st.sampled_from(paths))[0])
        elif how == "extra":
            containers = [p for p, v in paths if isinstance(v, dict)] or [()]
            path = draw(st.sampled_from(containers))
            target = data
            for part in path:
                target = target[part]
            target[draw(st.text(min_size=1, max_size=8))] = draw(FILE_VALUES)
    return toml_dumps(data).encode()


FILE_VALUES = st.one_of(st.text(max_size=10), st.integers(-(2**63), 2**63 - 1), st.floats(), st.booleans(),
                        st.lists(st.integers(-5, 30), max_size=30), st.lists(st.floats(), min_size=24, max_size=24),
                        st.dictionaries(st.text(max_size=4), st.integers(), max_size=2))


def run_cli(argv: list[str], allowed=(0, 2)) -> int:
    """The CLI in this process: an allowed exit, one line on stderr with exit 2, and never a traceback."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli_main(argv)
    text = err.getvalue()
    assert code in allowed, f"exit {code}: {text}"
    assert "Traceback" not in text + out.getvalue() and not text.startswith("failed:"), text
    if code == 2:
        assert text.count("\n") == 1 and text.startswith("error: "), text
    return code


FILE_FUZZ = settings(max_examples=120, deadline=None, database=None, derandomize=True,
                     suppress_health_check=list(HealthCheck))
CASE_TEXT = (DATA_DIR / "paper.toml").read_text()
FLEET_TEXT = "".join(f'[[agents]]\nid = "mg{i}"\ncase = "paper"\nscale = {0.5 * i}\nshift_hours = {i}\nseed = {i}\n\n'
                     for i in (1, 2))


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fuzzed-files")


@FILE_FUZZ
@given(case=mutated_file(CASE_TEXT))
def test_mutated_case_files_get_exit_0_or_one_line_and_exit_2(files, case):
    path = files / "case.toml"
    path.write_bytes(case)
    run_cli(["run", "--check", "--case", str(path)])


@settings(FILE_FUZZ, max_examples=80)
@given(fleet=mutated_file(FLEET_TEXT), case=mutated_file(CASE_TEXT))
def test_mutated_fleet_files_and_their_cases_get_exit_0_or_one_line_and_exit_2(files, fleet, case):
    (files / "member.toml").write_bytes(case)
    path = files / "fleet.toml"
    path.write_bytes(fleet.replace(b'"paper"', json.dumps(str(files / "member.toml")).encode(), 1))
    run_cli(["run", "--check", "--fleet", str(path)])


def small_recording(path: Path) -> None:
    """A recorded day of one agent over two hours' worth of messages, settled by the DMO's own rules."""
    from dmo.market.settlement import RULES, RULES_VERSION, settle  # noqa: PLC0415
    from dmo.operator.outbox import statement_message  # noqa: PLC0415

    run_id = "fuzzed-day"
    prefix = f"dmosim/{run_id}"
    t = [1_700_000_000_000_000_000]

    def write(writer, key, msg):
        t[0] += 1_000_000
        writer.write(f"{prefix}/{key}", encode(msg.model_copy(update={"sent_at": t[0]})), t[0])

    awards = {"mg1": tuple([1.0] * HOURS)}
    prices = tuple([50.0] * HOURS)
    meter = {"mg1": {h: (1.5,) for h in range(HOURS) if h % 5}}
    statements, _ = settle(awards, prices, meter, subperiods=1, penalty=150.0, credit=0.0, p_m_max={"mg1": 16.0})
    with RecordingWriter(path, run_id) as writer:
        writer.start({"market_day": DAY, "agents": "mg1"})
        write(writer, "agent/mg1/register", Registration(sender="mg1", market_day=DAY, case="paper",
                                                          max_import_mw=16.0, max_export_mw=16.0))
        write(writer, "dmo/award/mg1", Award(sender="dmo", market_day=DAY, agent="mg1", p_sch_mw=awards["mg1"],
                                             clearing_price_per_mwh=prices, penalty_per_mwh=150.0, subperiods=1,
                                             rules_version=RULES_VERSION, rules=RULES))
        for h, p_m in meter["mg1"].items():
            write(writer, "agent/mg1/meter", MeterReport(sender="mg1", market_day=DAY, hour=h + 1, subperiods=1,
                                                         p_m_mw=p_m, deviation_mw=(0.5,), seq=h + 1))
        write(writer, "dmo/statement/mg1", statement_message(statements["mg1"], DAY, 150.0, 0.0))


@pytest.fixture(scope="module")
def recording(files) -> bytes:
    path = files / "small.mcap"
    small_recording(path)
    assert run_cli(["settle", str(path)]) == 0
    return path.read_bytes()


@pytest.fixture(scope="module")
def recorded(files, recording) -> list:
    from messages.recording import read_recording  # noqa: PLC0415

    return read_recording(files / "small.mcap").in_log_order()


@settings(max_examples=120, deadline=None, database=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_mutated_recordings_get_an_answer_never_a_traceback(files, recording, data):
    damaged = bytearray(recording)
    how = data.draw(st.sampled_from(["flip", "flip", "cut", "insert", "zero", "swap"]))
    at = data.draw(st.integers(0, len(damaged) - 1))
    if how == "flip":
        for _ in range(data.draw(st.integers(1, 8))):
            damaged[data.draw(st.integers(0, len(damaged) - 1))] ^= 1 << data.draw(st.integers(0, 7))
    elif how == "cut":
        del damaged[at:]
    elif how == "insert":
        damaged[at:at] = data.draw(st.binary(min_size=1, max_size=16))
    elif how == "zero":
        damaged[at:at + data.draw(st.integers(1, 64))] = bytes(min(64, len(damaged) - at))
    else:
        n = data.draw(st.integers(1, 32))
        damaged[at:at + n] = data.draw(st.binary(min_size=n, max_size=n))
    path = files / "damaged.mcap"
    path.write_bytes(bytes(damaged))
    run_cli(["info", str(path)])
    run_cli(["info", "--json", str(path)])
    run_cli(["settle", str(path)], allowed=(0, 1, 2))


@settings(max_examples=100, deadline=None, database=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(kind=st.sampled_from(["meter_report", "registration", "award", "settlement_statement"]), data=st.data())
def test_recordings_with_hostile_messages_inside_get_an_answer_never_a_traceback(files, recorded, kind, data):
    """A well-formed file whose messages are hostile: written as a recorder would (invalid payloads go to the
    invalid channel) and, bypassing it, straight onto the channels, as a hand-made file could."""
    from mcap.writer import Writer  # noqa: PLC0415

    payload = json.dumps(data.draw(mutated(kind)), allow_nan=True).encode()
    key = {"meter_report": "agent/mg1/meter", "registration": "agent/mg1/register", "award": "dmo/award/mg1",
           "settlement_statement": "dmo/statement/mg1"}[kind]
    path = files / "hostile.mcap"
    if data.draw(st.booleans()):
        with RecordingWriter(path, "fuzzed-day") as writer:
            writer.start({"market_day": DAY})
            at = data.draw(st.integers(0, len(recorded)))
            for m in recorded[:at]:
                writer.write(m.key, m.payload, m.log_time)
            writer.write(f"dmosim/fuzzed-day/{key}", payload, 1_700_000_000_000_000_000 + at)
            for m in recorded[at:]:
                writer.write(m.key, m.payload, m.log_time)
    else:
        with open(path, "wb") as f:
            w = Writer(f)
            w.start()
            schema = w.register_schema(name=kind, encoding="jsonschema", data=json.dumps(SCHEMAS[kind]).encode())
            channel = w.register_channel(topic=f"dmosim/fuzzed-day/{key}", message_encoding="json", schema_id=schema)
            w.add_message(channel, log_time=1, data=payload, publish_time=1)
            w.finish()
    run_cli(["info", str(path)])
    run_cli(["settle", str(path)], allowed=(0, 1, 2))
