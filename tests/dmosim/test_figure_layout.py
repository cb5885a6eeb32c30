"""The run's figure keeps its size with many agents (``dmosim.results.figures``, ``dmosim.results.compact``): past
``COMPACT_AGENTS`` agents share heat maps and ranked bills instead of a row of panels each; up to it the per-agent
layout stays as it was.

The recordings are ``synthetic_day`` (no solving), written and read back as a run's would be; nothing runs a market.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from dmosim.bench.recording import synthetic_day
from dmosim.results.compact import COMPACT_AGENTS, HOURLY_DAYS, RANKED
from dmosim.results.figures import DPI, ROW_IN, WIDTH_IN, recording_figure, restarts
from dmosim.results.tables import tables
from dmosim.studies.figures import save
from messages import decode, encode
from messages.keys import new_run_id
from messages.recording import RecordingWriter, read_recording

ROOT = Path(__file__).resolve().parents[2]
DAY = "2026-07-01"
COMPACT_AXES = 6  # the price, the bills, the two heat maps and their colour bars
MAX_HEIGHT_IN = 14.0


def record(path: Path, messages: list[tuple[str, bytes]]):
    run_id = messages[0][0].split("/")[1]
    with RecordingWriter(path, run_id) as writer:
        writer.start({})
        for i, (key, payload) in enumerate(messages):
            writer.write(key, payload, 1_800_000_000_000_000_000 + i * 1_000_000)
    return read_recording(path)


def day_of(agents: int, market_day: str = DAY, run_id: str | None = None) -> list[tuple[str, bytes]]:
    return synthetic_day(run_id or new_run_id(), agents, 2, market_day=market_day)


def with_faults(day: list[tuple[str, bytes]]) -> list[tuple[str, bytes]]:
    """mg3's meter reports of hours 5 to 7 lost; mg12's process restarted before its hour-10 report."""
    out = []
    for key, payload in day:
        msg = decode(payload)
        if key.endswith("agent/mg3/meter") and 5 <= msg.hour <= 7:
            continue
        if "/agent/mg12/" in key:
            later = key.endswith("/meter") and msg.hour >= 10
            payload = encode(msg.model_copy(update={"incarnation": 2_000 if later else 1_000}))
        out.append((key, payload))
    return out


@pytest.fixture(scope="module")
def twenty(tmp_path_factory):
    rec = record(tmp_path_factory.mktemp("layout") / "twenty.mcap", with_faults(day_of(20)))
    return tables(rec), restarts(rec)


@pytest.fixture(scope="module")
def hundred_fifty(tmp_path_factory):
    return tables(record(tmp_path_factory.mktemp("layout") / "many.mcap", day_of(150)))


def axes_titled(fig, start: str):
    return next(ax for ax in fig.axes if ax.get_title(loc="left").startswith(start))


def test_past_the_threshold_the_figure_has_the_same_panels_and_a_bounded_size_whatever_the_agents(
        twenty, hundred_fifty, tmp_path):
    frames, restarted = twenty
    sizes, panels = {}, {}
    for n, (f, r) in {20: (frames, restarted), 150: (hundred_fifty, None)}.items():
        fig = recording_figure(f, "", r)
        panels[n] = [re.sub(r"\d+", "N", ax.get_title(loc="left")) for ax in fig.axes]
        assert len(fig.axes) == COMPACT_AXES, (n, panels[n])
        assert fig.get_figwidth() == WIDTH_IN and fig.get_figheight() <= MAX_HEIGHT_IN, (n, fig.get_size_inches())
        sizes[n] = Image.open(save(fig, tmp_path / f"{n}.png")).size
    assert panels[20] == panels[150]
    assert all(w <= WIDTH_IN * DPI + 40 and h <= MAX_HEIGHT_IN * DPI for w, h in sizes.values()), sizes


def test_up_to_the_threshold_each_agent_keeps_its_row_of_panels(tmp_path):
    frames = tables(record(tmp_path / "few.mcap", day_of(COMPACT_AGENTS)))
    fig = recording_figure(frames)
    titles = [ax.get_title(loc="left") for ax in fig.axes]
    assert len(fig.axes) == 2 * (1 + COMPACT_AGENTS)
    assert f"mg{COMPACT_AGENTS}: award and metered import (negative: export)" in titles
    assert f"mg{COMPACT_AGENTS}: deviation penalty per hour" in titles
    assert fig.get_figheight() == pytest.approx(ROW_IN * (1 + COMPACT_AGENTS) + 1.2)
    assert not any("heat" in t or "deviation per hour" in t for t in titles)


def test_the_deviation_map_is_metered_less_awarded_blank_and_hatched_where_no_report_came(twenty):
    frames, restarted = twenty
    fig = recording_figure(frames, "", restarted)
    ax = axes_titled(fig, "deviation per hour")
    image = ax.get_images()[0]
    agents = [f"mg{i}" for i in range(1, 21)]  # natural order: mg2 before mg10
    hours = frames["hours"]
    expected = (hours.assign(d=hours["import_mwh"] - hours["p_sch_mw"])
                .pivot(index="agent", columns="hour", values="d").reindex(agents).to_numpy())
    shown = image.get_array()
    row = agents.index("mg3")
    assert shown.shape == (20, 24)
    assert shown.mask[row, 4:7].all() and shown.mask.sum() == 3  # hours 5-7 of mg3, nothing else
    np.testing.assert_allclose(shown.filled(np.nan)[~shown.mask], expected[~shown.mask])
    top = np.abs(expected[~shown.mask]).max()
    assert (image.norm.vmin, image.norm.vmax) == pytest.approx((-top, top))  # symmetric, about 0
    assert [t.get_text() for t in ax.get_yticklabels()] == agents

    hatched = [c for c in ax.collections if c.get_label() == "hour with no accepted meter report (missing-data rule)"]
    assert len(hatched) == 1 and hatched[0].get_hatch()
    corners = sorted((round(p.vertices[:, 0].min()), round(p.vertices[:, 1].mean())) for p in hatched[0].get_paths())
    assert corners == [(4, row), (5, row), (6, row)]
    restart = next(line for line in ax.get_lines() if line.get_label() == "process restarted (the agent)")
    assert list(restart.get_xdata()) == [9] and list(restart.get_ydata()) == [agents.index("mg12")]
    legend = [t.get_text() for legend in fig.legends for t in legend.get_texts()]
    assert "process restarted (the agent)" in legend and "islanded hour (grid state; framed on the maps)" in legend


def test_the_penalty_map_has_each_hours_penalty_on_the_same_rows(twenty):
    frames, _ = twenty
    fig = recording_figure(frames)
    image = axes_titled(fig, "deviation penalty per hour").get_images()[0]
    expected = frames["hours"].pivot(index="agent", columns="hour", values="deviation_penalty").reindex(
        [f"mg{i}" for i in range(1, 21)]).to_numpy()
    np.testing.assert_allclose(image.get_array().filled(np.nan), expected)
    assert image.norm.vmin == 0


@pytest.mark.parametrize("n", [20, 150])
def test_agent_names_on_a_map_never_overlap(n, twenty, hundred_fifty):
    frames = twenty[0] if n == 20 else hundred_fifty
    fig = recording_figure(frames)
    fig.canvas.draw()
    ax = axes_titled(fig, "deviation per hour")
    labels = [t for t in ax.get_yticklabels() if t.get_visible() and t.get_text()]
    boxes = sorted((t.get_window_extent() for t in labels), key=lambda b: b.y0)
    assert all(low.y1 <= high.y0 for low, high in zip(boxes, boxes[1:]))
    assert len(labels) == n if n == 20 else 10 < len(labels) < n


def test_the_bills_rank_the_highest_and_lowest_and_show_the_others_mean(hundred_fifty):
    fig = recording_figure(hundred_fifty)
    ax = axes_titled(fig, "the day's bill")
    totals = hundred_fifty["days"].set_index("agent")["total"].sort_values(ascending=False, kind="stable")
    names = [t.get_text() for t in ax.get_yticklabels()]
    others = f"{len(totals) - 2 * RANKED} others (mean)"
    assert names == [*totals.index[:RANKED], others, *totals.index[-RANKED:]]
    written = [t.get_text() for t in ax.texts]
    mean = totals.iloc[RANKED:-RANKED].mean()
    assert written[RANKED] == f"{'-' if mean < 0 else ''}${abs(mean):,.2f}"
    assert written[0] == f"${totals.iloc[0]:,.2f}"


def test_beyond_a_week_the_penalty_map_sums_each_day(tmp_path):
    run_id, days = new_run_id(), [f"2026-07-{d:02d}" for d in range(1, HOURLY_DAYS + 3)]
    messages = [m for day in days for m in day_of(COMPACT_AGENTS + 1, day, run_id)]
    frames = tables(record(tmp_path / "days.mcap", messages))
    fig = recording_figure(frames)
    image = axes_titled(fig, "deviation penalty per day").get_images()[0]
    expected = frames["hours"].pivot_table(index="agent", columns="market_day", values="deviation_penalty",
                                           aggfunc="sum").reindex([f"mg{i}" for i in range(1, COMPACT_AGENTS + 2)])
    np.testing.assert_allclose(image.get_array().filled(np.nan), expected[days].to_numpy())
    assert len(fig.axes) == COMPACT_AXES and fig.get_figheight() <= MAX_HEIGHT_IN


def test_the_docs_state_the_threshold():
    doc = (ROOT / "docs" / "recording.md").read_text()
    assert f"more than {COMPACT_AGENTS} agents" in doc
