"""``--check`` is the run's check (docs/network.md, "Limits"): a feeder file that loads as ``dmosim run --check``
loads it clears in the DMO, and every message the DMO builds of its day is valid on the wire; one that does not
load is refused in one line. Feeder files of a few buses, TOML and pandapower JSON, are drawn with names and numbers
at and past every limit, and what the DMO does with them is run in this process: its clearing
(``dmo.market.distflow`` through ``dmo.operator.markets.LiveMarket``), its awards, network_hour messages and their AC
checks, the operating envelope in the grid states, and the statements.
"""

from __future__ import annotations

import json
import math
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dmo.operator import feeder, outbox
from dmo.operator.markets import LiveMarket
from dmo.operator.state import DayState
from dmosim.cli.checks import check_inputs
from dmosim.experiment.spec import ExperimentError, parse_experiment
from dmosim.launch.roles import day_config, resolved
from messages import Bid, BidStep, MeterReport, Registration, decode, encode
from scenarios.horizon import HOURS
from scenarios.network import (KV_RANGE, MAX_BUS_MW, MAX_LINE_MVA, MAX_LINE_OHM, MAX_MULTIPLIER, MAX_NAME_LENGTH,
                               MIN_LINE_OHM, MIN_POWER_FACTOR, UNRATED_KA)
from scenarios.tomltext import toml_text

DAY = "2026-07-01"
# Each feeder is drawn plain (every name and number an ordinary one), at the edges (some at the limits, which load)
# or hostile (some past them, or not numbers at all).
MODES = ("plain", "edge", "hostile")
HOSTILE = st.sampled_from([-1.0, 1e-300, 1e12, 1e308, -1e308, math.inf, -math.inf, math.nan, True, "1"])
EDGE_NAMES = st.one_of(st.integers(0, 10**6), st.text("ab", min_size=MAX_NAME_LENGTH, max_size=MAX_NAME_LENGTH),
                       st.text(st.characters(codec="utf-8", categories=("L", "N", "P", "S", "Zs")), min_size=1,
                               max_size=8))
HOSTILE_NAMES = st.one_of(st.text(max_size=3), st.text("ab", min_size=MAX_NAME_LENGTH + 1, max_size=70),
                          st.just(""), st.booleans(), st.floats())
PLAIN_STEM, LONG_STEM = r"[a-z]{1,8}", "x" * (MAX_NAME_LENGTH + 5)


def name(mode: str):
    plain = st.from_regex(r"[a-z0-9]{1,6}", fullmatch=True)
    return {"plain": plain, "edge": st.one_of(plain, EDGE_NAMES),
            "hostile": st.one_of(plain, plain, EDGE_NAMES, HOSTILE_NAMES)}[mode]


def number(mode: str, lo: float, hi: float, *edges: float):
    """A number of [lo, hi]; at the edges, or one of ``edges`` (each within the limits); hostile, or anything."""
    plain = st.floats(lo, hi)
    return {"plain": plain, "edge": st.one_of(plain, st.sampled_from(edges or (lo,))),
            "hostile": st.one_of(plain, plain, plain, st.sampled_from(edges or (lo,)), HOSTILE)}[mode]


def maybe(strategy):
    return st.one_of(st.none(), strategy)


@st.composite
def toml_feeder(draw) -> tuple[str, str]:
    mode = draw(st.sampled_from(MODES))
    n = draw(st.integers(2, 5))
    names = draw(st.lists(name(mode), min_size=n, max_size=n, unique_by=str))
    mw = (-MAX_BUS_MW, MAX_BUS_MW, 0.0, 5e-324)
    buses = [{"name": names[0]}] + [
        {"name": b, "p_mw": draw(number(mode, -0.5, 2.0, *mw)), "q_mvar": draw(number(mode, -0.2, 1.0, *mw)),
         "v_min": draw(maybe(number(mode, 0.85, 0.95, 0.5))), "v_max": draw(maybe(number(mode, 1.05, 1.1, 1.5)))}
        for b in names[1:]]
    ohm = (0.0, MIN_LINE_OHM, MAX_LINE_OHM)
    lines = [{"from": names[draw(st.integers(0, k))], "to": names[k + 1], "r_ohm": draw(number(mode, 0.01, 2.0, *ohm)),
              "x_ohm": draw(number(mode, 0.01, 2.0, *ohm)),
              "s_max_mva": draw(maybe(number(mode, 0.5, 20.0, 1e-6, MAX_LINE_MVA)))} for k in range(n - 1)]
    data = {"name": draw(maybe(name(mode))), "base_kv": draw(number(mode, 4.0, 35.0, *KV_RANGE)),
            "substation": names[0], "power_factor": draw(maybe(number(mode, 0.8, 1.0, MIN_POWER_FACTOR))),
            "load_scale": draw(maybe(number(mode, 0.5, 2.0, 1e-6, MAX_MULTIPLIER))),
            "rating_margin": draw(maybe(number(mode, 1.0, 2.0, 1e-6, MAX_MULTIPLIER))),
            "load_profile": draw(maybe(st.lists(number(mode, 0.3, 1.0, 0.0, MAX_MULTIPLIER), min_size=HOURS,
                                                max_size=HOURS))),
            "buses": buses, "lines": lines}
    stem = draw(st.from_regex(PLAIN_STEM, fullmatch=True) if mode == "plain" else st.sampled_from(["f", LONG_STEM]))
    return f"{stem}.toml", toml_text(data)


def _table(columns: dict[str, list]) -> dict:
    rows = len(next(iter(columns.values())))
    split = {"columns": list(columns), "index": list(range(rows)),
             "data": [[columns[c][k] for c in columns] for k in range(rows)]}
    return {"_module": "pandas.core.frame", "_class": "DataFrame", "_object": json.dumps(split), "orient": "split"}


@st.composite
def pandapower_feeder(draw) -> tuple[str, str]:
    mode = draw(st.sampled_from(MODES))
    n = draw(st.integers(2, 5))
    kv = draw(number(mode, 4.0, 35.0, *KV_RANGE))
    lines = [(draw(st.integers(0, k)), k + 1) for k in range(n - 1)]
    net = {
        "bus": _table({"vn_kv": [kv] * n, "in_service": [True] * n,
                       "min_vm_pu": [draw(maybe(number(mode, 0.85, 0.95, 0.5))) for _ in range(n)],
                       "max_vm_pu": [draw(maybe(number(mode, 1.05, 1.1, 1.5))) for _ in range(n)]}),
        "ext_grid": _table({"bus": [0], "in_service": [True]}),
        "line": _table({"from_bus": [a for a, _ in lines], "to_bus": [b for _, b in lines],
                        "length_km": [draw(number(mode, 0.1, 3.0, 1e-3, 100.0)) for _ in lines],
                        "r_ohm_per_km": [draw(number(mode, 0.05, 1.0, 0.0, 100.0)) for _ in lines],
                        "x_ohm_per_km": [draw(number(mode, 0.05, 1.0, 0.0, 100.0)) for _ in lines],
                        "max_i_ka": [draw(number(mode, 0.05, 1.0, UNRATED_KA, 99_999.0, math.nan)) for _ in lines],
                        "parallel": [draw(number(mode, 1, 1, 2)) for _ in lines],
                        "in_service": [True] * len(lines)}),
        "load": _table({"bus": list(range(1, n)),
                        "p_mw": [draw(number(mode, 0.0, 2.0, MAX_BUS_MW, -MAX_BUS_MW)) for _ in range(1, n)],
                        "q_mvar": [draw(number(mode, 0.0, 1.0, MAX_BUS_MW)) for _ in range(1, n)],
                        "scaling": [draw(number(mode, 0.5, 1.0, 0.0, MAX_MULTIPLIER)) for _ in range(1, n)],
                        "in_service": [True] * (n - 1)}),
    }
    doc = {"_module": "pandapower.auxiliary", "_class": "pandapowerNet", "_object": net}
    stem = draw(st.from_regex(PLAIN_STEM, fullmatch=True) if mode == "plain" else st.sampled_from(["f", LONG_STEM]))
    return f"{stem}.json", json.dumps(doc)


def the_dmos_day(experiment, seed: int) -> list:
    """What the DMO builds of one day on the experiment's feeder, two agents at their buses bidding (but in hour
    ``seed``): every message, each through the wire's codec."""
    config = day_config(experiment)
    state = DayState(market_day=DAY)
    for k, (agent, bus) in enumerate(sorted(config.placement.items())):
        state.registered[agent] = Registration(sender=agent, market_day=DAY, case="paper", max_import_mw=5.0,
                                               max_export_mw=5.0, bus=bus)
        state.bids[agent] = Bid(sender=agent, market_day=DAY, hours=tuple(
            (BidStep(price_per_mwh=20.0 + 7.0 * ((h + seed + k) % 9), quantity_mw=(-1.0) ** (h + k) * (1 + k)),)
            if h != seed else () for h in range(HOURS)))  # an hour nobody bids in: the feeder's load alone
    clearing = LiveMarket(config).clear(state)
    at = feeder.sites(config, state)
    sent = [outbox.award(config, 1, clearing, agent, at[agent]) for agent in sorted(state.registered)]
    sent += feeder.planned(config, 1, clearing, at)
    room = feeder.envelope(config, clearing, at)
    sent += [outbox.grid_state(config, 1, hour, room) for hour in range(1, HOURS + 1)]
    k = config.subperiods
    # every agent meters its award: the realised network_hours would be the plan's again, by the same builder
    for agent, award in clearing.awards.items():
        state.meter[agent] = {h: (award[h],) * k for h in range(HOURS)}
        sent += [MeterReport(sender=agent, market_day=DAY, hour=h + 1, subperiods=k, p_m_mw=(award[h],) * k,
                             deviation_mw=(0.0,) * k) for h in range(HOURS)]
    statements, _ = LiveMarket(config).settle(state, clearing)
    sent += [outbox.statement_message(st, DAY, *config.rates, config.rule.label) for st in statements.values()]
    for message in sent:
        assert decode(encode(message)) == message
    return sent


@pytest.mark.slow  # a search over feeder files through a whole day of the DMO, seconds long; the cases below are fast
@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.one_of(toml_feeder(), pandapower_feeder()), st.sampled_from([0.0, 0.0, 0.01, 0.05]),
       st.sampled_from([1.0, 1.0, 0.5, 10.0]), st.integers(0, 8))
def test_a_feeder_that_passes_the_check_clears_and_every_message_of_its_day_is_valid(file, margin, scale, seed):
    name, text = file
    with tempfile.TemporaryDirectory() as tmp:  # a new path each time: the roles load a feeder once per path
        path = Path(tmp) / name
        path.write_text(text)
        try:
            experiment = resolved(parse_experiment({
                "market_day": DAY, "agents": {"count": 2}, "schedule": {"scenarios": 1},
                "network": {"feeder": str(path), "load_scale": scale, "voltage_margin": margin}}))
            check_inputs(experiment)  # what dmosim run --check does after the experiment: the feeder loads here
        except ExperimentError as exc:  # refused: one line, naming the feeder
            assert "\n" not in str(exc) and str(exc).startswith("network.feeder: "), str(exc)
            return
        sent = the_dmos_day(experiment, seed)
    assert sum(m.kind == "network_hour" for m in sent) == HOURS


FEEDER5 = (Path(__file__).resolve().parents[2] / "scenarios" / "data" / "feeder5.toml").read_text()
LONG_BUS = "b" * MAX_NAME_LENGTH


@pytest.mark.parametrize("stem, change, refused", [
    ("x" * MAX_NAME_LENGTH, {'name = "feeder5"\n': ""}, None),  # the file's name is the feeder's, at most 64
    ("x" * (MAX_NAME_LENGTH + 5), {'name = "feeder5"\n': ""}, "the network's name 'xxx"),
    ("f", {'"4"': f'"{LONG_BUS}"'}, None),
    ("f", {'"4"': f'"{LONG_BUS}b"'}, "bus 5's name 'bbb"),
    ("f", {"p_mw = 0.25": "p_mw = 1e308"}, r"bus 4 p_mw must be >= -10,000 and <= 10,000, got 1e\+308"),
])
def test_what_the_run_would_fail_on_the_check_refuses_and_what_it_passes_clears(tmp_path, stem, change, refused):
    """The feeders of the bug report: a file name or a bus name over 64 characters passed --check and then stopped the
    DMO (its messages cannot carry them), and so did a load of 1e308 MW (an OverflowError, naming no file)."""
    text = FEEDER5
    for old, new in change.items():
        assert old in text
        text = text.replace(old, new)
    path = tmp_path / f"{stem}.toml"
    path.write_text(text)
    settings = {"market_day": DAY, "agents": {"count": 2}, "network": {"feeder": str(path)}}
    if refused:
        with pytest.raises(ExperimentError, match=refused) as err:
            check_inputs(resolved(parse_experiment(settings)))
        assert "\n" not in str(err.value) and str(err.value).startswith("network.feeder: ")
        return
    experiment = resolved(parse_experiment(settings))
    check_inputs(experiment)
    sent = the_dmos_day(experiment, 0)
    names = {name for m in sent if m.kind == "network_hour" for name in (m.network, *m.buses)}
    assert max(map(len, names)) == MAX_NAME_LENGTH  # carried by every network_hour


def test_generation_the_export_limit_cannot_carry_passes_the_check_and_the_dmo_spills_it(tmp_path):
    """20 MW of fixed generation at bus 1 (times the load profile) against an export limit of 10 MW (5 per agent):
    the check once refused such a feeder (no load shed helps); now the DMO's day spills what the limit and the lines
    cannot carry, and never exports beyond the limit."""
    path = tmp_path / "f.toml"
    path.write_text(FEEDER5.replace("p_mw = 0.4\nq_mvar = 0.15", "p_mw = -20.0\nq_mvar = 0.0"))
    experiment = resolved(parse_experiment({"market_day": DAY, "agents": {"count": 2},
                                            "network": {"feeder": str(path)}}))
    check_inputs(experiment)
    hours = [m for m in the_dmos_day(experiment, 0) if m.kind == "network_hour" and m.stage == "plan"]
    spilling = [m for m in hours if max(m.spilled_mw) > 0]
    assert len(hours) == HOURS and spilling and not any(any(m.shed_mw) for m in hours)
    assert all(m.ac.substation_mw >= -10.0 - 1e-6 for m in hours)
