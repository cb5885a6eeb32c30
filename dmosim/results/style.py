"""The colours and formats that the panels of a run's figure share (figures.py, compact.py), so that the per-agent
and the compact layout read alike."""

from __future__ import annotations

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter

ENERGY, PENALTY, CREDIT, ISLANDED = "#8c9fc4", "#d62728", "#2ca02c", "0.85"
MISSING, RESTART = "#ff7f0e", "#9467bd"
DOLLARS = FuncFormatter(lambda y, _: f"{y:,.0f}".removeprefix("-") if abs(y) < 0.5 else f"{y:,.0f}")  # no "-0"


def figure(**kwargs) -> Figure:
    """A Figure drawn by Agg, for files: made without pyplot, so that neither pyplot's backend (a notebook user's
    choice) nor its list of open figures is touched, and nothing needs closing."""
    fig = Figure(**kwargs)
    FigureCanvasAgg(fig)
    return fig


def short_dates(market_days: list[str]) -> list[str]:
    """Dates as MM-DD when they share a year (the title says which), else as they are."""
    return [d[5:] for d in market_days] if len({d[:4] for d in market_days}) == 1 else list(market_days)
