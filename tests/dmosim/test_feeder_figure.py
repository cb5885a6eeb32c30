"""The feeder's panels of a run's figure (``dmosim.results.feeder``): the feeder cut into branches for its voltage
profile, the hour its voltage and loading panels show, and the panels drawn from a feeder's tables, checked on their
artists (no image comparison). The tables are built here with the columns of the real ones; nothing runs a market.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from matplotlib.collections import LineCollection

from dmosim.bench.recording import synthetic_day
from dmosim.results.feeder import branches, depths, parents, shown_hour
from dmosim.results.figures import recording_figure
from dmosim.results.tables import TABLE_COLUMNS, tables
from messages.keys import new_run_id
from messages.recording import RecordingWriter, read_recording

DAY = "2026-07-01"
# ieee33's lines as the tables name them: a trunk 0..17 and laterals off 1 (18-21), 2 (22-24) and 5 (25-32)
IEEE33 = ["0-1", "1-2", "2-3", "3-4", "4-5", "5-6", "6-7", "7-8", "8-9", "9-10", "10-11", "11-12", "12-13", "13-14",
          "14-15", "15-16", "16-17", "1-18", "18-19", "19-20", "20-21", "2-22", "22-23", "23-24", "5-25", "25-26",
          "26-27", "27-28", "28-29", "29-30", "30-31", "31-32"]
# seven buses: a trunk 0-1-2-3, a lateral 1-4-5, and a spur 2-6
BUSES, LINES = ["0", "1", "2", "3", "4", "5", "6"], ["0-1", "1-2", "2-3", "1-4", "4-5", "2-6"]


def drawn_lines(paths: list[list[str]]) -> list[str]:
    return [f"{a}-{b}" for path in paths for a, b in zip(path, path[1:])]


def test_each_line_is_in_one_branch_and_a_branch_runs_away_from_the_substation_only():
    buses = [str(b) for b in range(33)]
    paths = branches(buses, IEEE33)
    assert sorted(drawn_lines(paths)) == sorted(IEEE33)  # every line exactly once
    depth = depths(buses, IEEE33)
    for path in paths:  # each step one line further out: a branch never turns back to join another lateral
        assert [depth[b] for b in path] == list(range(depth[path[0]], depth[path[0]] + len(path)))
    assert paths[0] == [str(b) for b in range(18)]  # the longest first, from the substation
    assert paths[1:] == [["1", "18", "19", "20", "21"], ["2", "22", "23", "24"],
                         ["5", "25", "26", "27", "28", "29", "30", "31", "32"]]  # each from its junction
    assert depth["17"] == 17 and depth["21"] == 5 and depth["32"] == 13


def test_a_bus_name_with_a_dash_is_read_where_the_line_names_two_buses():
    buses = ["sub", "a-1", "a", "1-b"]
    lines = ["sub-a-1", "a-1-a", "sub-1-b"]
    assert parents(buses, lines) == {"a-1": "sub", "a": "a-1", "1-b": "sub"}
    assert branches(buses, lines) == [["sub", "a-1", "a"], ["sub", "1-b"]]
    with pytest.raises(ValueError, match="x-y"):
        parents(buses, ["x-y"])


def feeder_tables(congested: bool = True, shed: bool = True) -> dict[str, pd.DataFrame]:
    """A day on the seven-bus feeder, plan and realised. Hour 19 imports most. Hour 7 (``congested``): line 1-2 at
    its limit (limit_loading 1, its |S| 0.94) with a shadow price, bus 3 held at v_min, bus 3's price 40 above the
    substation's. Hour 9 (``shed``): 0.1 MW shed at bus 5 and 0.2 MW spilled at bus 6, no component (the
    substation's own limit)."""
    network, buses, lines = [], [], []
    for hour in range(1, 25):
        bind, cut = congested and hour == 7, shed and hour == 9
        for stage in ("plan", "realised"):
            plan = stage == "plan"
            network.append({"market_day": DAY, "hour": hour, "stage": stage, "network": "f7",
                            "clearing": "ac" if plan else None, "substation_mw": 2.0 + (hour == 19),
                            "energy_price_per_mwh": 50.0 if plan else None,
                            "shed_mw": (0.1 if cut else 0.0) if plan else None,
                            "spilled_mw": (0.2 if cut else 0.0) if plan else None,
                            "v_min_pu": 0.95, "max_loading": 0.94, "ac_converged": True, "ac_v_min_pu": 0.949,
                            "ac_v_min_bus": "3", "ac_v_max_pu": 1.0, "ac_v_max_bus": "0", "ac_max_loading": 0.94,
                            "ac_max_loading_line": "1-2", "ac_voltage_error_pu": 0.001, "ac_flow_error_mw": 0.001,
                            "ac_losses_mw": 0.01, "ac_substation_mw": 2.0, "ac_violations": "", "ac_margin": 0.0})
            for i, bus in enumerate(BUSES):
                local = 40.0 if bind and bus == "3" else 0.0
                buses.append({"market_day": DAY, "hour": hour, "stage": stage, "bus": bus, "injection_mw": 0.1,
                              "voltage_pu": 1.0 - 0.01 * i, "bus_price_per_mwh": 50.0 + local if plan else None,
                              "loss_price_per_mwh": 0.0 if plan else None,
                              "congestion_price_per_mwh": local if plan else None,
                              "voltage_price_per_mwh": 0.0 if plan else None,
                              "shed_mw": (0.1 if cut and bus == "5" else 0.0) if plan else None,
                              "spilled_mw": (0.2 if cut and bus == "6" else 0.0) if plan else None,
                              "binding_voltage": "v_min" if plan and bind and bus == "3" else None,
                              "voltage_shadow_price_per_pu": (500.0 if bind and bus == "3" else 0.0) if plan else None})
            for line in LINES:
                at = bind and line == "1-2"
                lines.append({"market_day": DAY, "hour": hour, "stage": stage, "line": line,
                              "loading": 0.94 if at else 0.5, "limit_loading": (1.0 if at else 0.52) if plan else None,
                              "binding_facet": 2 if plan and at else None,
                              "line_shadow_price_per_mwh": (5.0 if at else 0.0) if plan else None})
    frames = {"network": network, "buses": buses, "lines": lines}
    return {name: pd.DataFrame(rows).assign(timestamp=pd.Timestamp(DAY))[list(TABLE_COLUMNS[name])].astype(
        TABLE_COLUMNS[name]) for name, rows in frames.items()}


@pytest.mark.parametrize(("congested", "shed", "hour", "why"), [
    (True, True, 7, "most congested"),  # a limit's price beats MW shed at the substation's limit
    (False, True, 9, "most shed and spilled"),
    (False, False, 19, "peak import"),
])
def test_the_hour_shown_is_where_limits_cost_most_else_where_most_is_curtailed_else_the_peak(
        congested, shed, hour, why):
    frames = feeder_tables(congested, shed)
    assert shown_hour(frames["network"], frames["buses"]) == (DAY, hour, why)


def test_older_tables_without_what_binds_fall_back_to_the_peak_hour():
    frames = feeder_tables()
    for name, columns in (("buses", ["congestion_price_per_mwh", "voltage_price_per_mwh"]),
                          ("network", ["shed_mw", "spilled_mw"])):
        frames[name][columns] = pd.NA
    assert shown_hour(frames["network"], frames["buses"]) == (DAY, 19, "peak import")


@pytest.fixture(scope="module")
def market(tmp_path_factory) -> dict[str, pd.DataFrame]:
    run_id = new_run_id()
    path = tmp_path_factory.mktemp("feeder") / "day.mcap"
    with RecordingWriter(path, run_id) as writer:
        writer.start({})
        for i, (key, payload) in enumerate(synthetic_day(run_id, 2, 2, market_day=DAY)):
            writer.write(key, payload, 1_800_000_000_000_000_000 + i * 1_000_000)
    return tables(read_recording(Path(path)))


def axes_titled(fig, start: str):
    return next(ax for ax in fig.axes if ax.get_title(loc="left").startswith(start))


def test_the_feeder_panels_show_what_binds_on_the_runs_time_axis_branch_by_branch(market):
    fig = recording_figure({**market, **feeder_tables()}, "", None, (0.95, 1.05))
    fig.canvas.draw()
    price, heat = axes_titled(fig, "the substation's price"), axes_titled(fig, "bus price above")
    # one time axis: the same hours, ticks and pixels as the price above, a column of the map under each hour
    assert heat.get_xlim() == price.get_xlim() == (0, 24)
    assert list(heat.get_xticks()) == list(price.get_xticks())
    assert heat.get_window_extent().x0 == pytest.approx(price.get_window_extent().x0, abs=0.5)
    assert heat.get_window_extent().x1 == pytest.approx(price.get_window_extent().x1, abs=0.5)
    marks = {line.get_label(): line for line in heat.get_lines()}
    assert list(marks["load shed (bus, hour)"].get_xdata()) == [8.5]  # hour 9, bus 5 (the sixth row)
    assert list(marks["load shed (bus, hour)"].get_ydata()) == [5]
    assert list(marks["generation spilled (bus, hour)"].get_ydata()) == [6]
    shown = next(p for p in heat.patches if p.get_label() == "the hour the feeder's panels show")
    assert shown.get_x() == 6  # hour 7

    volt = axes_titled(fig, "voltage along each branch")
    assert f"{DAY} hour 7 (most congested)" in volt.get_title(loc="left")
    plan = next(c for c in volt.collections if isinstance(c, LineCollection) and c.get_label().startswith("plan"))
    assert [[x for x, _ in s] for s in plan.get_segments()] == [[0, 1, 2, 3], [1, 2, 3], [2, 3]]  # by distance
    held = next(line for line in volt.get_lines() if line.get_label() == "held at v_min (plan)")
    assert list(held.get_xdata()) == [3] and list(held.get_ydata()) == [pytest.approx(0.97)]
    assert sorted(line.get_ydata()[0] for line in volt.get_lines() if line.get_linestyle() == "--") == [0.95, 1.05]

    load = axes_titled(fig, "line loading as the clearing limits it")
    assert f"{DAY} hour 7 (most congested)" in load.get_title(loc="left")
    binding = next(c for c in load.containers if c.get_label().startswith("plan: binding"))
    assert [bar.get_height() for bar in binding] == [1.0]  # up to the limit, where |S| / rating shows 0.94
    assert [t.get_text() for t in load.texts] == ["$5.00/h per MW"]
    realised = next(line for line in load.get_lines() if line.get_label().startswith("realised"))
    np.testing.assert_allclose(realised.get_ydata(), [0.5, 0.94, 0.5, 0.5, 0.5, 0.5])


def test_a_day_with_nothing_binding_or_curtailed_marks_nothing(market):
    fig = recording_figure({**market, **feeder_tables(congested=False, shed=False)})
    heat, load = axes_titled(fig, "bus price above"), axes_titled(fig, "line loading")
    assert not [line for line in heat.get_lines() if "shed" in line.get_label() or "spilled" in line.get_label()]
    assert "hour 19 (peak import)" in load.get_title(loc="left")
    assert not load.texts and not any(c.get_label().startswith("plan: binding") for c in load.containers)
    volt = axes_titled(fig, "voltage along each branch")
    assert not any(line.get_linestyle() == "--" for line in volt.get_lines())  # limits unknown: not drawn
