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


def sweep_figure(table: pd.DataFrame, keys: list[str], title: str = "") -> Figure:
    """Each agent's total bill against the first swept setting, one panel per combination of the others; a
    numeric setting on a line, any other as grouped bars. A sweep of ``seed`` shows, per setting of the other
    keys, the mean over the seeds with its 95% interval as a bar (``seed_summary``); of the seed alone, one bar
    per agent."""
    ok = table[table["status"] == "ok"]
    if ok.empty:
        raise ValueError("no run of the sweep finished: nothing to plot")
    seeds = SEED in keys
    if seeds:
        ok = seed_summary(table, keys).assign(setting=f"mean of {ok[SEED].nunique()} seeds").rename(
            columns={"total_mean": "total"})
        keys = [k for k in keys if k != SEED] or ["setting"]
    x_key, others = keys[0], keys[1:]
    groups = list(ok.groupby(others, sort=False)) if others else [((), ok)]
    fig = figure(figsize=(max(6.0, 4.5 * len(groups)), 4.2), layout="constrained")
    axes = fig.subplots(1, len(groups), squeeze=False, sharey=True)
    numeric = pd.api.types.is_numeric_dtype(ok[x_key]) and not pd.api.types.is_bool_dtype(ok[x_key])
    agents = sorted(ok["agent"].unique(), key=natural)
    for ax, (key, frame) in zip(axes[0], groups):
        values = list(dict.fromkeys(frame[x_key]))
        for i, agent in enumerate(agents):
            own = frame[frame["agent"] == agent].set_index(x_key).reindex(values)
            y = own["total"].to_numpy(dtype=float)
            spread = np.abs([y - own["total_low"].to_numpy(dtype=float),
                             own["total_high"].to_numpy(dtype=float) - y]) if seeds else None
            if numeric:
                ax.errorbar(values, y, yerr=spread, fmt="o-", capsize=4, label=agent)
            else:
                width = 0.8 / len(agents)
                ax.bar(np.arange(len(values)) + (i - (len(agents) - 1) / 2) * width, y, width=width, yerr=spread,
                       capsize=4, label=agent)
        if not numeric:
            ax.set_xticks(np.arange(len(values)), [str(v) for v in values])
        ax.axhline(0, color="0.5", lw=0.6)
        ax.set_xlabel(x_key)
        ax.grid(alpha=0.3)
        key = key if isinstance(key, tuple) else (key,)
        ax.set_title(", ".join(f"{k}={v}" for k, v in zip(others, key)) or "", loc="left", fontsize=10)
        ax.yaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda y, _: f"{y:,.0f}"))
    axes[0][0].set_ylabel("total bill over the run, $" + (" (mean, 95% interval)" if seeds else ""))
    axes[0][-1].legend(fontsize=8, frameon=False)
    fig.suptitle(title or f"each agent's bill against {x_key}", fontsize=12)
    return fig
