"""The DMO's feeder, hour by hour: where each agent sits, the network_hour messages of a day as planned (after
clearing) and as realised (after real time), each with the AC power-flow check of that hour, and the day's operating
envelope, which the hours' grid states carry (docs/network.md)."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from messages import DMO
from messages.schemas import ACCheck, NetworkHour
from scenarios.horizon import HOURS
from scenarios.network import Network

from ..market.acflow import check_hours
from ..market.distflow import NetworkClearing
from ..market.envelope import Rooms, operating_envelope
from .config import DayConfig
from .state import DayState


def sites(config: DayConfig, state: DayState) -> dict[str, str]:
    """Agent -> its bus on the feeder (empty on the copper plate): the run's placement, or, for an agent the run does
    not place, the bus its registration names (``acceptance.check_bus`` admitted only agents that have one)."""
    if config.network is None:
        return {}
    return {a: config.placement.get(a) or reg.bus for a, reg in state.registered.items()}


def per_bus(network: Network, at: Mapping[str, str], mw: Mapping[str, object]) -> np.ndarray:
    """(24 x buses) the agents' MW (agent -> 24 values) summed at their buses (``at``: agent -> bus)."""
    out = np.zeros((HOURS, network.n_buses))
    for agent, values in mw.items():
        out[:, network.index[at[agent]]] += values
    return out


def _hours(config: DayConfig, day: int, stage: str, injection: np.ndarray, shed: np.ndarray | None = None,
           clearing: str | None = None, **fields) -> list[NetworkHour]:
    """The 24 network_hour messages of one stage: LinDistFlow's voltages and loadings of the fixed loads and
    generation (less what was ``shed`` of either, MW per bus, its Q in proportion) plus the microgrids' ``injection``
    (24 x buses, MW imported, Q = tan(phi) P),
    and the AC check of each hour; ``clearing``, the method the plan was cleared by. ``fields`` name per-hour (24)
    arrays of numbers, or per-hour arrays of values per bus or line (24 x buses or lines)."""
    net = config.network
    kept = 1.0 if shed is None else 1.0 - np.divide(shed, np.abs(net.fixed_p), out=np.zeros_like(shed),
                                                    where=net.fixed_p != 0)
    p, q = net.fixed_p * kept + injection, net.fixed_q * kept + injection * net.tan_phi
    flow_p, flow_q, v = net.lindistflow(p, q)
    loading = np.hypot(flow_p, flow_q) / net.s_max_mva
    checks = [{k: x for k, x in c.as_dict().items() if k != "hour"}  # the message's hour says which
              for c in check_hours(net, p - net.fixed_p, q_mvar=q - net.fixed_q, margin=config.voltage_margin)]
    return [NetworkHour(sender=DMO, market_day=config.market_day_of(day), hour=h + 1, stage=stage,
                        network=net.name, buses=net.buses, substation=net.substation, lines=net.line_names,
                        substation_mw=float(p[h].sum()),
                        injection_mw=tuple(injection[h].tolist()), voltage_pu=tuple(v[h].tolist()),
                        line_loading=tuple(loading[h].tolist()), ac=ACCheck(**checks[h]), clearing=clearing,
                        **{k: float(a[h]) if np.ndim(a) == 1 else tuple(a[h].tolist()) for k, a in fields.items()})
            for h in range(HOURS)]


def planned(config: DayConfig, day: int, clearing: NetworkClearing, at: Mapping[str, str]) -> list[NetworkHour]:
    """The day as cleared: each hour's awards at their buses, how they were cleared, the bus prices and their
    components, shed load and spilled generation, and what binds."""
    injection = per_bus(config.network, at, clearing.awards)
    facet = np.where(clearing.binding_facet >= 0, clearing.binding_facet, None)
    side = np.array([None, "v_max", "v_min"], dtype=object)[clearing.binding_voltage]  # 0: none, +1: upper, -1: lower
    return _hours(config, day, "plan", injection, np.asarray(clearing.shed_mw) + np.asarray(clearing.spill_mw),
                  clearing.method,
                  energy_price_per_mwh=np.asarray(clearing.price), bus_price_per_mwh=np.asarray(clearing.bus_price),
                  loss_price_per_mwh=np.asarray(clearing.loss), congestion_price_per_mwh=np.asarray(clearing.congestion),
                  voltage_price_per_mwh=np.asarray(clearing.voltage), shed_mw=np.asarray(clearing.shed_mw),
                  spilled_mw=np.asarray(clearing.spill_mw), limit_loading=np.asarray(clearing.limit_loading),
                  binding_facet=facet, line_shadow_price_per_mwh=np.asarray(clearing.line_shadow_price),
                  binding_voltage=side, voltage_shadow_price_per_pu=np.asarray(clearing.voltage_shadow_price))


def realised(config: DayConfig, day: int, state: DayState, at: Mapping[str, str]) -> list[NetworkHour]:
    """The day as metered: each hour's mean metered transfer of every agent at its bus (a missing reading, or
    hour, counts as 0: this is the grid's load, not the settlement's)."""
    mean = {a: np.array([np.mean([r or 0.0 for r in state.meter.get(a, {}).get(h, (0.0,))]) for h in range(HOURS)])
            for a in state.registered}
    return _hours(config, day, "realised", per_bus(config.network, at, mean))


def envelope(config: DayConfig, clearing: NetworkClearing, at: Mapping[str, str]) -> Rooms:
    """The day's operating envelope as cleared: the rooms each microgrid at a bus has above and below its award,
    within the run's voltage margin and substation limits (docs/network.md, "Operating envelopes")."""
    return operating_envelope(clearing, config.network, at, config.import_limit, config.export_limit,
                              config.voltage_margin)
