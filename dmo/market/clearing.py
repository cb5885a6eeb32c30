"""Day-ahead clearing of the DMO's hourly step bids against the ISO price and the feeder's import/export limits.

Pure and deterministic: typed immutable bids in, a ``ClearingResult`` out. The rules (which price is chosen,
how ties at the margin are shared, what "congested" means) are stated in docs/market.md; the functions below
follow them one step each so each can be tested on its own.

Order independence is exact, not approximate: every sum over steps is ``math.fsum`` (the correctly rounded sum
of the multiset, whatever its order), and the only prices ever chosen are the ISO price or a bid's own price,
so permuting microgrids or steps gives a bit-identical result.
"""

from __future__ import annotations

import math
from bisect import bisect_left
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from scenarios.horizon import HOURS, finite, hourly

# How a feeder clears (``distflow.clear_network``'s ``method``): on LinDistFlow alone, or on the AC flow linearised at
# its own plan (docs/market.md, "AC-faithful clearing"). Here, so that naming one loads no LP.
CLEARING_METHODS = ("lindistflow", "ac")


def _agent_id(agent: object) -> str:
    if not isinstance(agent, str) or not agent.strip():
        raise ValueError(f"agent id must be a non-empty string, got {agent!r}")
    return agent


@dataclass(frozen=True)
class Step:
    """One price-quantity step: ``quantity`` > 0 buys up to that many MW at prices <= ``price`` ($/MWh);
    ``quantity`` < 0 sells up to |quantity| MW at prices >= ``price``. A zero step trades nothing."""

    price: float
    quantity: float

    def __post_init__(self) -> None:
        # + 0.0 makes a price of -0.0 the 0.0 it equals, so the price chosen among equal ones has one sign
        object.__setattr__(self, "price", finite(self.price, "step price") + 0.0)
        object.__setattr__(self, "quantity", finite(self.quantity, "step quantity"))


@dataclass(frozen=True)
class BidCurve:
    """A microgrid's day-ahead bid: for each of the 24 hours (index 0..23) a tuple of steps (possibly empty)."""

    agent: str
    hours: tuple[tuple[Step, ...], ...]

    def __post_init__(self) -> None:
        _agent_id(self.agent)
        if isinstance(self.hours, (str, bytes)) or not isinstance(self.hours, Sequence):
            raise ValueError(f"bid of {self.agent} must give {HOURS} hours of steps")
        if len(self.hours) != HOURS:
            raise ValueError(f"bid of {self.agent} must have {HOURS} hours, got {len(self.hours)}")
        hours = []
        for h, steps in enumerate(self.hours):
            if isinstance(steps, Step) or not isinstance(steps, Sequence):
                raise ValueError(f"bid of {self.agent}, hour index {h}: expected a sequence of steps")
            if not all(isinstance(s, Step) for s in steps):
                raise ValueError(f"bid of {self.agent}, hour index {h}: every step must be a Step")
            hours.append(tuple(steps))
        object.__setattr__(self, "hours", tuple(hours))


@dataclass(frozen=True)
class ClearingResult:
    """Uniform price per hour ($/MWh), the award per microgrid per hour (MW, + import / - export, 24 values),
    and per hour whether a feeder limit bound ("none", "import", "export": ``messages.schemas.Congestion``, the one
    definition of congestion, which each award carries and every table and figure reads). ``awards`` is keyed in sorted
    agent order and must be treated as read-only."""

    price: tuple[float, ...]
    awards: dict[str, tuple[float, ...]]
    congested: tuple[str, ...]

    def net_import(self, hour: int) -> float:
        """The DMO's net position with the ISO in one hour: the sum of the awards (MW)."""
        return math.fsum(a[hour] for a in self.awards.values())

    @property
    def agent_price(self) -> dict[str, tuple[float, ...]]:
        """The price each microgrid's award is settled at, per hour: the uniform price, the same for every agent
        (a ``distflow.NetworkClearing`` gives each agent its bus's price under the same name)."""
        return {a: self.price for a in self.awards}


# --- one hour's order book ----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Book:
    """One hour's steps as arrays: owner index into ``agents``, price, signed quantity (zero steps dropped)."""

    owner: np.ndarray
    price: np.ndarray
    quantity: np.ndarray


def hour_book(bids: Sequence[BidCurve], agents: Sequence[str], hour: int) -> Book:
    index = {a: i for i, a in enumerate(agents)}
    rows = [(index[b.agent], s.price, s.quantity) for b in bids for s in b.hours[hour] if s.quantity != 0.0]
    owner, price, quantity = (np.array(c) for c in zip(*rows)) if rows else (np.zeros(0, int), np.zeros(0), np.zeros(0))
    return Book(owner.astype(int), price.astype(float), quantity.astype(float))


def _net(book: Book, buy: np.ndarray, sell: np.ndarray) -> float:
    """Net import (MW) when the purchases selected by ``buy`` and the sales selected by ``sell`` are accepted."""
    q = book.quantity
    return math.fsum(np.concatenate([q[(q > 0) & buy], q[(q < 0) & sell]]))


def net_import_low(book: Book, p: float) -> float:
    """Least net import consistent with price p: purchases priced > p, sales priced <= p (non-increasing in p)."""
    return _net(book, book.price > p, book.price <= p)


def net_import_high(book: Book, p: float) -> float:
    """Greatest net import consistent with price p: purchases priced >= p, sales priced < p (non-increasing)."""
    return _net(book, book.price >= p, book.price < p)


def net_import_at_iso(book: Book, iso: float) -> float:
    """Net import the ISO price alone calls for: every purchase priced >= ISO and every sale priced <= ISO."""
    return _net(book, book.price >= iso, book.price <= iso)


# --- price ------------------------------------------------------------------------------------------------------

def clearing_price(book: Book, iso: float, import_limit: float, export_limit: float) -> tuple[float, str]:
    """The hour's uniform price and congestion state (docs/market.md, "Price").

    Uncongested: the ISO price. Import congestion: the lowest price p >= ISO at which the least net import
    consistent with p, ``net_import_low(p)``, is within the import limit. Export congestion: the highest
    p <= ISO with ``net_import_high(p)`` >= -export limit. Both are the ISO price or a bid step's price.
    """
    wanted = net_import_at_iso(book, iso)
    if wanted > import_limit:
        candidates = sorted({iso, *book.price[book.price > iso].tolist()})
        # net_import_low is non-increasing, so "within the limit" is False...False, True...True over candidates;
        # the last candidate always qualifies (no purchase lies above it), so the index is in range.
        i = bisect_left(candidates, True, key=lambda p: net_import_low(book, p) <= import_limit)
        return candidates[i], "import"
    if wanted < -export_limit:
        candidates = sorted({iso, *book.price[book.price < iso].tolist()})
        # net_import_high >= -limit holds on a prefix (always for the lowest candidate: no sale lies below it).
        i = bisect_left(candidates, True, key=lambda p: net_import_high(book, p) < -export_limit)
        return candidates[i - 1], "export"
    return iso, "none"


# --- the ISO's curve -------------------------------------------------------------------------------------------

MAX_BLOCKS = 50  # blocks of one side of an ISO curve: a wholesale offer curve's length, far more than a study needs


@dataclass(frozen=True)
class IsoCurve:
    """The ISO's terms at the substation (docs/market.md, "The ISO's curve"): ``import_curve`` are (MW, premium
    $/MWh) the ISO sells the DMO at its hourly price plus the premium, ``export_curve`` (MW, discount $/MWh) what it
    buys from the DMO at its price less the discount; each side's blocks in order, premiums and discounts strictly
    increasing. A side with no blocks is one block as wide as the substation's limit at the ISO price: the flat
    curve, a price taker's market, is ``IsoCurve()``. The substation's limits cut each side's blocks."""

    import_curve: tuple[tuple[float, float], ...] = ()
    export_curve: tuple[tuple[float, float], ...] = ()

    def __post_init__(self) -> None:
        for side in ("import_curve", "export_curve"):
            blocks = tuple((finite(mw, f"{side} MW"), finite(extra, f"{side} price")) for mw, extra in
                           getattr(self, side))
            if len(blocks) > MAX_BLOCKS:
                raise ValueError(f"{side}: at most {MAX_BLOCKS} blocks, got {len(blocks)}")
            if any(mw <= 0 for mw, _ in blocks):
                raise ValueError(f"{side}: every block must have MW > 0")
            extras = [extra for _, extra in blocks]
            if any(extra < 0 for extra in extras) or any(b <= a for a, b in zip(extras, extras[1:])):
                raise ValueError(f"{side}: the {'premiums' if side == 'import_curve' else 'discounts'} must be "
                                 f">= 0 and strictly increasing, got {extras}")
            object.__setattr__(self, side, blocks)

    def check_prices(self, iso_price: Sequence[float], floor: float, cap: float) -> None:
        """ValueError (one line) if the curve prices the substation outside [floor, cap] at the ISO's hourly prices
        ``iso_price``: a price no message could carry."""
        low = min(iso_price) - max((extra for _, extra in self.export_curve), default=0.0)
        high = max(iso_price) + max((extra for _, extra in self.import_curve), default=0.0)
        if low < floor or high > cap:
            raise ValueError(f"the ISO's curve prices the substation from {low:g} to {high:g} $/MWh, beyond the "
                             f"prices messages carry ({floor:g} to {cap:g} $/MWh)")


FLAT = IsoCurve()


@dataclass(frozen=True)
class Segments:
    """The price of the DMO's position P0 at the substation (MW, + import) in one hour: ``price[s]`` ($/MWh,
    strictly ascending) over P0 in [``low[s]``, ``high[s]``], the segments in order and touching."""

    price: np.ndarray
    low: np.ndarray
    high: np.ndarray

    @property
    def top(self) -> float:
        """The most the DMO can import."""
        return float(self.high[-1])

    @property
    def bottom(self) -> float:
        """Minus the most it can export."""
        return float(self.low[0])

    def cost(self, p0: float) -> float:
        """What the position ``p0`` costs at the ISO's curve ($ per hour; < 0: a revenue): each MW between 0 and
        p0 at its segment's price (a position past an end by rounding, at the end's price)."""
        a, b = min(p0, 0.0), max(p0, 0.0)
        mw = np.clip(self.high, a, b) - np.clip(self.low, a, b)  # exact for the flat curve: p0 - 0
        mw[-1 if p0 > 0 else 0] += max(p0 - self.top, self.bottom - p0, 0.0)
        return math.copysign(1.0, p0) * math.fsum(self.price * mw)


def segments(curve: IsoCurve, iso: float, import_limit: float, export_limit: float) -> Segments:
    """One hour's segments of ``curve`` at the ISO price ``iso``, each side cut at the substation's limit; equal
    prices either side of 0 are one segment (a flat curve is a single one, [-export_limit, import_limit] at iso)."""
    def side(blocks, limit, sign):
        mw, extra = np.array(blocks or ((limit, 0.0),), dtype=float).reshape(-1, 2).T
        end = np.minimum(np.cumsum(mw), limit)
        start = np.concatenate([[0.0], end[:-1]])
        keep = end > start
        return iso + sign * extra[keep], sign * start[keep], sign * end[keep]

    up, down = side(curve.import_curve, import_limit, 1.0), side(curve.export_curve, export_limit, -1.0)
    price = np.concatenate([down[0][::-1], up[0]]) + 0.0
    low = np.concatenate([down[2][::-1], up[1]])
    high = np.concatenate([down[1][::-1], up[2]])
    if price.size == 0:  # both limits 0: the DMO trades nothing, at the ISO's price
        return Segments(np.array([iso + 0.0]), np.zeros(1), np.zeros(1))
    same = np.flatnonzero(price[1:] == price[:-1])  # only the two sides' first blocks can share a price
    if same.size:
        price, low, high = np.delete(price, same + 1), np.delete(low, same + 1), np.delete(high, same)
    return Segments(price, low, high)


# --- quantities -------------------------------------------------------------------------------------------------

def marginal_shares(fixed: float, marginal_buy: float, marginal_sell: float, target: float) -> tuple[float, float]:
    """Fractions (alpha, beta) of the purchases and of the sales priced exactly at the clearing price to accept
    so that fixed + alpha * marginal_buy - beta * marginal_sell = target (docs/market.md, "Ties").

    Volume is maximised: the side that is short after the net ``target - fixed`` is met is accepted in full.
    Each fraction is shared pro rata by every step at the margin, and clipped to [0, 1] against rounding.
    """
    r = target - fixed
    a = min(marginal_buy, marginal_sell + r)
    b = min(marginal_sell, marginal_buy - r)
    alpha = a / marginal_buy if marginal_buy > 0 else 1.0
    beta = b / marginal_sell if marginal_sell > 0 else 1.0
    return min(max(alpha, 0.0), 1.0), min(max(beta, 0.0), 1.0)


def accepted_fractions(book: Book, price: float, target: float | None) -> np.ndarray:
    """Per step, the accepted fraction of its quantity at ``price``: 1 in the money, 0 out of it, and at the
    margin the pro-rata share that brings the net import to ``target`` (None: all marginal steps accepted)."""
    q, pr = book.quantity, book.price
    buy, sell = q > 0, q < 0
    at = pr == price
    frac = np.where((buy & (pr > price)) | (sell & (pr < price)), 1.0, 0.0)
    if target is None:
        alpha = beta = 1.0
    else:
        fixed = math.fsum(q * frac)
        alpha, beta = marginal_shares(fixed, math.fsum(q[buy & at]), -math.fsum(q[sell & at]), target)
    frac[buy & at] = alpha
    frac[sell & at] = beta
    return frac


def clear_hour(book: Book, iso: float, import_limit: float, export_limit: float) -> tuple[float, str, np.ndarray]:
    """Price, congestion state and per-step awards (MW, signed) of one hour."""
    price, congested = clearing_price(book, iso, import_limit, export_limit)
    target = {"none": None, "import": import_limit, "export": -export_limit}[congested]
    return price, congested, book.quantity * accepted_fractions(book, price, target)


def clear_on_curve(book: Book, curve: Segments, base: float = 0.0) -> tuple[float, str, np.ndarray]:
    """Price, congestion state and per-step awards of one hour on the ISO's curve (docs/market.md, "The ISO's
    curve"), the DMO's position being ``base`` (MW, e.g. fixed load) plus the book's net import.

    The hour clears on the first segment s whose high end holds what the bids want at the next segment's price, all
    ties accepted (the last segment otherwise), as ``clear_hour`` clears at one ISO price between two limits: at the segment's
    price, or at a bid's price up to the next segment's when its high end binds. Only the curve's ends are
    congestion ("import", "export"): a position held at the boundary of two segments is "none". A flat curve is
    ``clear_hour`` between the limits exactly. ``base`` must lie within the curve's ends.
    """
    last = len(curve.price) - 1
    s = next((s for s in range(last) if net_import_at_iso(book, curve.price[s + 1]) <= curve.high[s] - base), last)
    price, congested, step_mw = clear_hour(book, float(curve.price[s]), curve.high[s] - base, base - curve.low[s])
    return price, "none" if congested == "import" and s < last else congested, step_mw


def per_agent(book: Book, step_awards: np.ndarray, n_agents: int) -> list[float]:
    # + 0.0 turns a -0.0 (a rejected sale) into 0.0 so equal results print equal.
    return [math.fsum(step_awards[book.owner == i]) + 0.0 for i in range(n_agents)]


def market_inputs(bids: Iterable[BidCurve], iso_price: float | Sequence[float], import_limit: float | Sequence[float],
                  export_limit: float | Sequence[float], agents: Iterable[str] = ()) -> tuple[
                      list[BidCurve], list[str], tuple[float, ...], tuple[float, ...], tuple[float, ...]]:
    """A market day's inputs, checked (ValueError with a one-line reason): the bids, the sorted names of the
    bidders and of ``agents``, and the 24 hourly ISO prices, import limits and export limits."""
    bids = list(bids)
    if not all(isinstance(b, BidCurve) for b in bids):
        raise ValueError("every bid must be a BidCurve")
    bidders = [b.agent for b in bids]
    if len(set(bidders)) != len(bidders):
        dup = sorted(a for a in set(bidders) if bidders.count(a) > 1)[0]
        raise ValueError(f"more than one bid from agent {dup}")
    names = sorted(set(bidders) | {_agent_id(a) for a in agents})
    iso = tuple(p + 0.0 for p in hourly(iso_price, "iso_price"))  # no -0.0 price, as in Step
    imp = hourly(import_limit, "import_limit", non_negative=True)
    exp = hourly(export_limit, "export_limit", non_negative=True)
    return bids, names, iso, imp, exp


def clear(bids: Iterable[BidCurve], iso_price: float | Sequence[float], import_limit: float | Sequence[float],
          export_limit: float | Sequence[float], agents: Iterable[str] = (), curve: IsoCurve = FLAT) -> ClearingResult:
    """Clear one market day: a uniform price and an award per microgrid for each of the 24 hours.

    ``iso_price`` ($/MWh) and the feeder limits (MW, >= 0) are a scalar or 24 hourly values. ``agents`` names
    microgrids that may have sent no bid; they, like bidders with no accepted step, get award 0. ``curve``: the
    ISO's blocks around its price (the flat curve: a price taker's market). Raises ValueError with a one-line reason
    for invalid input, including two bids from one agent.
    """
    bids, names, iso, imp, exp = market_inputs(bids, iso_price, import_limit, export_limit, agents)
    prices, congested, columns = [], [], []
    for h in range(HOURS):
        book = hour_book(bids, names, h)
        p, c, step_awards = clear_on_curve(book, segments(curve, iso[h], imp[h], exp[h]))
        prices.append(p)
        congested.append(c)
        columns.append(per_agent(book, step_awards, len(names)))
    awards = {a: tuple(columns[h][i] for h in range(HOURS)) for i, a in enumerate(names)}
    return ClearingResult(tuple(prices), awards, tuple(congested))


def fixed_awards(awards: Mapping[str, Sequence[float]], iso_price: float | Sequence[float]) -> ClearingResult:
    """Publish given awards (e.g. the paper's Table I) at the ISO price, with no congestion: "fixed" mode."""
    if not isinstance(awards, Mapping):
        raise ValueError("awards must map agent id to 24 hourly MW values")
    out = {_agent_id(a): hourly(v, f"award of {a}") for a, v in sorted(awards.items(), key=lambda kv: str(kv[0]))}
    return ClearingResult(hourly(iso_price, "iso_price"), out, ("none",) * HOURS)
