"""A settlement rule as a user names it: a built-in by name, or a function of the user's own, with parameters;
checked as a name without loading anything (``rule_name``), loaded and checked on a synthetic day before it settles
anything (``choose``), and, when a file names it rather than the user, loaded only if trusted (``Trust``;
docs/settlement.md, "Choosing a rule" and "Rules named by recordings").

``NAME[:key=value,...]`` names a built-in rule (``paper``, ``symmetric``, ``deadband``, ``price-linked``);
``path/to/rules.py:function[:key=value,...]`` or ``module:function[:key=value,...]`` a rule of one's own.
"""

from __future__ import annotations

import inspect
import numbers
from collections.abc import Mapping
from dataclasses import dataclass, field

from microgrid_agent.usercode import CodeKind, check_target, code_of, load, params_text, split_spec
from scenarios.horizon import HOURS

from .rules import BUILT_IN, DeviationRule, GridHour, Rule
from .settlement import RULES, DayTotals, RuleError, Statement, settle_day, settlement_day

RULE = CodeKind("settlement rule", "function", "path/to/rules.py", "dmosim_rule_")


@dataclass(frozen=True)
class ChosenRule:
    """A rule and its parameters. ``name`` is the rule as named (``deadband``, ``rules.py:capped``), ``params`` the
    parameters given (a built-in's defaults fill in the rest)."""

    name: str
    rule: Rule = field(compare=False)
    params: Mapping[str, float] = field(default_factory=dict)

    @property
    def built_in(self) -> DeviationRule | None:
        return self.rule if isinstance(self.rule, DeviationRule) else None

    @property
    def parameters(self) -> dict[str, float]:
        """Every parameter the rule settles with: a built-in's defaults, or the numbers a rule of one's own defaults
        its keyword parameters to, with those given over them."""
        if self.built_in:
            return self.built_in.parameters(self.params)
        return {**_defaults(self.rule), **self.params}

    @property
    def label(self) -> str:
        """The rule as one would name it again: ``deadband:band_mw=0.5,rate=150``."""
        params = params_text(self.parameters)
        return f"{self.name}:{params}" if params else self.name

    @property
    def words(self) -> str:
        """The rule in words, as the award states it."""
        if self.name == "paper":
            return RULES
        if self.built_in:
            return (f"{self.label}: f(d) = {self.built_in.formula} ($/h, d = P_M - P_sch), charged f(d) x dt per "
                    "sub-period; energy charge = clearing price x award per hour; a missing sub-period is charged the "
                    "worst reading within the registered limits, with no credit (docs/settlement.md)")
        doc = (getattr(self.rule, "__doc__", None) or "a rule of the user's own").strip().split("\n\n")[0]
        return f"{self.label}: {' '.join(doc.split())}"[:4000]

    def deviation_cost(self, award, prices) -> list[list[tuple[float, float]]] | None:
        """The pieces an award carries for the agent's model (docs/settlement.md, "What agents schedule against"):
        a built-in's, where convex; None for a rule of one's own, which the model cannot carry."""
        return self.built_in.deviation_cost(self.params, award, prices) if self.built_in else None

    def settle(self, day) -> tuple[dict[str, Statement], DayTotals]:
        """Settle a ``SettlementDay``; RuleError, one line, when the rule fails."""
        return settle_day(day, self.rule, self.name, **self.params)


def _defaults(rule: Rule) -> dict[str, float]:
    """The numeric defaults of a function's parameters after its first (the day), in the signature's order."""
    try:
        params = list(inspect.signature(rule).parameters.values())[1:]
    except (TypeError, ValueError):  # a callable whose signature Python cannot read: no defaults to show
        return {}
    return {p.name: p.default for p in params
            if isinstance(p.default, numbers.Real) and not isinstance(p.default, bool)}


def paper_rule(penalty: float, credit: float = 0.0) -> ChosenRule:
    """The paper's rule at these rates."""
    return ChosenRule("paper", BUILT_IN["paper"], {"penalty": penalty, "credit": credit})


@dataclass(frozen=True)
class RuleName:
    """A rule as named, checked without loading anything: ``target`` a built-in's name or ``where:function`` (a
    file, path/to/rules.py, or a module), ``params`` the parameters given."""

    target: str
    params: Mapping[str, float] = field(default_factory=dict)

    @property
    def built_in(self) -> bool:
        return self.target in BUILT_IN

    @property
    def code(self) -> str | None:
        """The code a rule of one's own would run, as loading it would find it (a file resolved against the current
        directory, a module by name); None for a built-in. Two names with the same code run the same function."""
        return None if self.built_in else code_of(self.target)


def rule_name(spec: str) -> RuleName:
    """``spec`` checked as a name, importing and running nothing: its syntax, and a built-in's parameter names and
    values. ValueError, one line, when it is not a rule's name. This is all that reading a file that names a rule
    (an experiment, a recording) does with it; only ``choose`` loads a rule."""
    target, params = split_spec(spec, RULE)
    if target in BUILT_IN:
        try:
            BUILT_IN[target].parameters(params)
        except ValueError as err:
            raise ValueError(f"settlement rule {err}") from None
    elif ":" in target:
        check_target(target, RULE)
    else:
        raise ValueError(f"unknown settlement rule {target!r}: the built-in rules are {', '.join(BUILT_IN)}; a rule "
                         "of your own is path/to/rules.py:function or module:function")
    return RuleName(target, params)


def choose(spec: str) -> ChosenRule:
    """The rule ``spec`` names, loaded and checked (``check``); ValueError, one line, when it cannot be used. A rule
    of one's own is imported and run here: only for a rule the user named (on the command line, or in the
    experiment file they run), or one a file names that ``Trust`` allows."""
    name = rule_name(spec)
    chosen = ChosenRule(name.target, BUILT_IN[name.target] if name.built_in else load(name.target, RULE), name.params)
    check(chosen)
    return chosen


class UntrustedRule(ValueError):
    """A file (a recording, a run directory's experiment) names a rule of its own that the user did not: ``spec``
    is the rule as named."""

    def __init__(self, spec: str):
        super().__init__(f"settlement rule {spec} is code that a file names, not the user")
        self.spec = spec


@dataclass(frozen=True)
class Trust:
    """Which code of one's own that a file names may be loaded (docs/settlement.md, "Rules named by recordings";
    docs/strategies.md, "Trust"): code the user named on the command line (``named``, each a
    ``microgrid_agent.usercode.code_of``), or all of it (``everything``: the user trusts the file). A built-in is
    always allowed: it runs no code of the file's. The rules' and the bidding strategies' one trust."""

    everything: bool = False
    named: frozenset[str] = frozenset()

    @classmethod
    def of(cls, everything: bool, specs=()) -> Trust:
        """Trust in the rules ``specs`` name (the user's own, already loaded), or in everything."""
        return cls(everything, frozenset(code for code in (rule_name(s).code for s in specs) if code))

    def allows_code(self, code: str | None) -> bool:
        """Whether code a file names (``code_of``; None for a built-in) may be loaded."""
        return code is None or self.everything or code in self.named

    def allows(self, spec: str) -> bool:
        """Whether the rule a file names as ``spec`` may be loaded; ValueError if it is no rule's name."""
        return self.allows_code(rule_name(spec).code)

    def choose(self, spec: str) -> ChosenRule:
        """``choose(spec)`` for a rule a file names: UntrustedRule, before anything is imported, if not allowed."""
        if not self.allows(spec):
            raise UntrustedRule(spec)
        return choose(spec)


# The trial day's grid: islanded in hour index 17, and in the second sub-period of hour index 18.
TRIAL_ISLANDED = {17: (False, False), 18: (True, False)}


def trial_day():
    """A small day that exercises what a rule must handle: an importer and an exporter, two sub-periods, readings
    above and below the award, a negative price, a missing sub-period, a missing hour, an agent with no meter data
    at all, and the grid's states: an islanded hour and an hour islanded in one sub-period (P_M = 0 there)."""
    prices = [20.0 + 2.5 * h for h in range(HOURS)]
    prices[3] = -5.0
    awards = {"mg1": [3.0] * HOURS, "mg2": [-2.0] * HOURS, "mg3": [1.5] * HOURS}
    meter = {"mg1": {h: [3.0 + (h % 5 - 2) * 0.75, 3.0 - (h % 3) * 0.5] for h in range(HOURS) if h != 7},
             "mg2": {h: [-2.0 + (h % 4 - 1) * 0.5, None if h == 11 else -2.5] for h in range(HOURS)}}
    grid = [GridHour(TRIAL_ISLANDED.get(h, (True, True))) for h in range(HOURS)]
    for readings in meter.values():
        for h, connected in TRIAL_ISLANDED.items():
            readings[h] = [p if up else 0.0 for p, up in zip(readings[h], connected)]
    return settlement_day(awards, prices, meter, subperiods=2, p_m_max={"mg1": 6.0, "mg2": 4.0, "mg3": 3.0},
                          p_m_min={"mg1": 6.0, "mg2": 4.0, "mg3": 3.0}, grid=grid)


def check(chosen: ChosenRule) -> None:
    """Settle the synthetic day under ``chosen``: a rule that raises, returns money that is not finite, or lines
    that do not add up is refused with one line naming it and the problem (ValueError)."""
    try:
        chosen.settle(trial_day())
    except RuleError as err:
        raise ValueError(f"{err} (on a synthetic day, before settling anything)") from None
