"""A sweep's results (``dmosim sweep``): one tidy table, a row per run and agent, and its figure.

The table has the swept settings as columns (named by their dotted keys), then the run's ``label``, ``status``
(``ok``, ``untrusted`` or ``failed``), ``run_dir``, ``wall_s``, ``agent``, the agent's settlement summed over the
run's days (``SETTLED``), and what only the agent knows, from its realised days: its own operating cost and the
load it curtailed (``REALISED``).
A failed run keeps one row with its error and empty money, so a sweep that lost a run still says which; an
untrusted one (its verdict is not ok) keeps its rows, with what its DMO settled and its problems as the error.
"""

from __future__ import annotations

import matplotlib
import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from dmo.operator.report import ReportedDay

from .order import natural
from .report import RunReport
from .style import figure

SEED = "seed"  # the swept key whose runs are replications of one setting
CONFIDENCE = 0.95  # of the interval of a figure across seeds
SETTLED = ("energy_charge", "deviation_penalty", "credit", "total", "award_mwh", "import_mwh", "deviation_mwh",
           "missing_subperiods")
REALISED = {"operating_cost": "total", "curtailment_mwh": "curtailment_mwh"}  # column -> field of a realised day


def sweep_rows(settings: dict[str, object], label: str, run_dir: str, wall_s: float, result: RunReport | None,
               error: str | None = None) -> list[dict]:
    """The rows of one run: one per agent of its result (``dmosim run --json``), or one saying why it failed
    (``error``, used only when there is no result). A result whose verdict is not ok is ``untrusted``, its problems
    the error of each of its rows."""
    found = result.verdict.problems if result is not None else []
    status = "failed" if result is None else "untrusted" if found else "ok"
    head = {**{key: _cell(value) for key, value in settings.items()}, "label": label, "status": status,
            "run_dir": run_dir, "wall_s": round(wall_s, 1)}
    if result is None:
        return [{**head, "agent": None, **dict.fromkeys([*SETTLED, *REALISED]), "error": error}]
    return [{**head, "agent": agent, **{k: getattr(s, k) for k in SETTLED},
             **{column: _realised_sum(result.realised.get(agent), field) for column, field in REALISED.items()},
             "error": "; ".join(found) or None}
            for agent, s in sorted(result.settlement.items(), key=lambda item: natural(item[0]))]


def seed_summary(table: pd.DataFrame, keys: list[str]) -> pd.DataFrame:
    """Per setting (every swept key but ``seed``) and agent, over the runs that ended ok: ``runs`` (seeds counted),
    and of each figure its ``_mean`` and the ``_low`` and ``_high`` ends of its 95% interval (Student's t over the
    seeds; equal to the mean with one seed)."""
    from scipy import stats  # noqa: PLC0415  (only for sweeps of seeds)

    settings = [k for k in keys if k != SEED]
    ok = table[table["status"] == "ok"]
    figures = [c for c in (*SETTLED, *REALISED) if c in ok]
    rows = []
    for key, runs in ok.groupby([*settings, "agent"], sort=False, dropna=False):
        key = key if isinstance(key, tuple) else (key,)
        row = {**dict(zip([*settings, "agent"], key)), "runs": len(runs)}
        for column in figures:
            values = runs[column].dropna().astype(float)
            mean = values.mean() if len(values) else np.nan
            half = (float(stats.t.ppf((1 + CONFIDENCE) / 2, len(values) - 1)) * values.std(ddof=1)
                    / np.sqrt(len(values))) if len(values) > 1 else 0.0
            row.update({f"{column}_mean": mean, f"{column}_low": mean - half, f"{column}_high": mean + half})
        rows.append(row)
    return pd.DataFrame(rows)


def _realised_sum(days: list[ReportedDay] | None, field: str) -> float | None:
    """A realised quantity summed over the agent's days; None if it logged none (it did not finish a day)."""
    return round(sum(getattr(d, field) for d in days), 6) if days else None


def _cell(value):
    """A swept value as one table cell: lists (a load pattern) as text."""
    return ",".join(map(str, value)) if isinstance(value, list) else value


# The unit of each setting a sweep may vary, for its figure's x-axis (docs/experiments.md gives every setting's).
UNITS = {"market.penalty": "$/MWh", "market.credit": "$/MWh", "market.import_limit": "MW", "market.export_limit": "MW",
         "market.island_hours": "islanded hours a day", "market.subperiods": "sub-periods an hour",
         "schedule.scenarios": "scenarios", "schedule.gap": "relative MIP gap", "schedule.time_limit": "s",
         "schedule.workers": "threads", "profiles.load_scale": "x the case's load",
         "profiles.renewable_scale": "x the case's renewables", "agents.count": "agents", "days": "days",
         "network.load_scale": "x the feeder's load", "network.voltage_margin": "p.u.",
         "network.spill_price": "$/MWh", "deadlines.registration": "s", "deadlines.bid": "s",
         "deadlines.schedule": "s", "deadlines.hour": "s"}
PANELS = (("total", "bill over the run, $"), ("deviation_penalty", "deviation penalty over the run, $"))
MAX_AGENTS_DRAWN = 8  # past this, the agents' mean is drawn: a line or bar per agent would not be told apart


def axis_label(key: str) -> str:
    """A swept setting with its unit, as its axis names it."""
    return f"{key} ({UNITS[key]})" if key in UNITS else key


def _agents_mean(table: pd.DataFrame) -> pd.DataFrame:
    """Each run's rows that ended ok as one row, the mean over its agents, named ``mean of N agents``."""
    ok = table[table["status"] == "ok"]
    figures = [c for c in (*SETTLED, *REALISED) if c in ok]
    heads = [c for c in ok.columns if c not in (*figures, "agent", "error")]
    out = ok.groupby("label", sort=False).agg({**{c: "first" for c in heads}, **dict.fromkeys(figures, "mean")})
    return out.reset_index(drop=True).assign(agent=f"mean of {ok['agent'].nunique()} agents", error=None)


def sweep_figure(table: pd.DataFrame, keys: list[str], title: str = "") -> Figure:
    """What a sweep varies against what it gives: each agent's bill (top) and deviation penalty (bottom) over the run
    against the first swept setting (its unit on the axis), one column of panels per combination of the others; a
    numeric setting on a line, the agents' points set apart so that their intervals do not overlap, any other as
    grouped bars. A sweep of ``seed`` shows, per setting of the other keys, the mean over the seeds with its 95%
    interval (``seed_summary``). Past 8 agents, their mean."""
    ok = table[table["status"] == "ok"]
    if ok.empty:
        raise ValueError("no run of the sweep finished: nothing to plot")
    if ok["agent"].nunique() > MAX_AGENTS_DRAWN:
        table = ok = _agents_mean(table)
    seeds = SEED in keys
    if seeds:
        n_seeds = ok[SEED].nunique()
        ok = seed_summary(table, keys).assign(setting=f"mean of {n_seeds} seeds").rename(
            columns={f"{c}_mean": c for c, _ in PANELS})
        keys = [k for k in keys if k != SEED] or ["setting"]
    x_key, others = keys[0], keys[1:]
    groups = list(ok.groupby(others, sort=False)) if others else [((), ok)]
    fig = figure(figsize=(max(6.0, 4.5 * len(groups)), 7.0), layout="constrained")
    axes = fig.subplots(len(PANELS), len(groups), squeeze=False, sharex="col", sharey="row")
    numeric = pd.api.types.is_numeric_dtype(ok[x_key]) and not pd.api.types.is_bool_dtype(ok[x_key])
    agents = sorted(ok["agent"].unique(), key=natural)
    for col, (key, frame) in enumerate(groups):
        values = list(dict.fromkeys(frame[x_key]))
        if numeric:
            values.sort()
            gaps = np.diff(np.asarray(values, dtype=float))
            step = 0.3 * (gaps.min() if len(gaps) else max(abs(float(values[0])), 1.0)) / len(agents)
        for row, (column, label) in enumerate(PANELS):
            ax = axes[row][col]
            for i, agent in enumerate(agents):
                own = frame[frame["agent"] == agent].set_index(x_key).reindex(values)
                y = own[column].to_numpy(dtype=float)
                spread = np.abs([y - own[f"{column}_low"].to_numpy(dtype=float),
                                 own[f"{column}_high"].to_numpy(dtype=float) - y]) if seeds else None
                offset = i - (len(agents) - 1) / 2
                if numeric:
                    ax.errorbar(np.asarray(values, dtype=float) + offset * step, y, yerr=spread, fmt="o-",
                                capsize=3, label=agent)
                else:
                    width = 0.8 / len(agents)
                    ax.bar(np.arange(len(values)) + offset * width, y, width=width, yerr=spread, capsize=3,
                           label=agent)
            if not numeric:
                ax.set_xticks(np.arange(len(values)), [str(v) for v in values])
            elif len(values) <= 12:  # the settings swept, not round numbers between them
                ax.set_xticks(np.asarray(values, dtype=float), [f"{v:g}" for v in values])
            ax.axhline(0, color="0.5", lw=0.6)
            ax.grid(alpha=0.3)
            ax.yaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:,.0f}"))
            if col == 0:
                ax.set_ylabel(label + (f"\n(mean of {n_seeds} seeds, 95% interval)" if seeds else ""))
        axes[-1][col].set_xlabel(axis_label(x_key))
        key = key if isinstance(key, tuple) else (key,)
        axes[0][col].set_title(", ".join(f"{k}={v}" for k, v in zip(others, key)) or "", loc="left", fontsize=10)
    fig.legend(*axes[0][0].get_legend_handles_labels(), loc="outside right upper", fontsize=8, frameon=False)
    fig.suptitle(title or f"each agent's bill and penalty against {axis_label(x_key)}", fontsize=12)
    return fig
