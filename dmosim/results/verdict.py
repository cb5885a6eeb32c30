"""Whether a finished run can be trusted: the problems, one line each, that make ``dmosim run`` and
``dmosim sweep`` exit 1 (docs/experiments.md, "The result"), read from the run's result alone."""

from __future__ import annotations

from collections.abc import Iterable

from dmo.operator.report import DmoReport

from .report import Recorded, Reproduced, Verdict

SHOWN_PROBLEMS = 3  # the one line on stderr names this many; result.json's verdict has them all


def problems(result: DmoReport, *, agents: Iterable[str], days: int, recorded: set[tuple[str, str]] | None = None,
             recording: Recorded | None = None, reproduced: Reproduced | None = None) -> list[str]:
    """Every reason not to trust the run, one line each; empty when there is none.

    ``result`` is the DMO's result of the run; ``agents`` the run's fleet, ``days`` the days its experiment asked
    for; ``recorded`` the (market day, agent) of every statement a complete recording holds (None when the recording
    is incomplete or there is none: then nothing is asked of it); ``recording`` what the run's result says of its
    recording (None: not recorded), ``reproduced`` of the run it repeats (None: not a ``--from`` run). The problems,
    in this order: an agent locked out on a day (the day's ``locked_out``: its process talked to the DMO while the
    DMO was not taking its messages); a day the DMO did not settle; an agent of the run with no statement on a
    settled day; a statement the DMO settled that the complete recording lacks; the recorder's failure or an
    unreadable or cut recording; a complete recording whose days do not re-settle, from it alone, to the statements
    the DMO published (``recorded.resettled``); a ``--from`` run that did not settle as its recording.
    """
    out = []
    settled = result.days
    for day in settled:
        for agent in day.locked_out:
            out.append(f"{agent} was locked out on {day.market_day}: its process talked to the DMO while the DMO "
                       "was not taking its messages")
    numbers = {day.day for day in settled}
    out += [f"day {n} of {days} was not settled" for n in range(1, days + 1) if n not in numbers]
    everyone = sorted(set(agents) | set(result.agents))
    for day in settled:
        lacking = [a for a in everyone if a not in day.settlement]
        out += [f"{agent} has no statement for {day.market_day}" for agent in lacking]
    if recorded is not None:
        out += [f"the recording lacks {agent}'s statement for {day.market_day}" for day in settled
                for agent in sorted(day.settlement) if (day.market_day, agent) not in recorded]
    out += _recording_problems(recording)
    out += _reproduction_problems(reproduced)
    return out


def verdict(found: list[str]) -> Verdict:
    """The ``verdict`` of the result: ``ok`` and the ``problems``."""
    return Verdict(ok=not found, problems=list(found))


def one_line(found: list[str]) -> str:
    """The problems as the one line ``dmosim run`` prints on stderr: the first few, and how many more."""
    more = len(found) - SHOWN_PROBLEMS
    return (f"the run is not to be trusted: {'; '.join(found[:SHOWN_PROBLEMS])}"
            + (f"; and {more} more (result.json, \"verdict\")" if more > 0 else ""))


def _recording_problems(recorded: Recorded | None) -> list[str]:
    if recorded is None:  # --no-record
        return []
    if recorded.recorder:
        return [f"the recorder failed: {recorded.recorder}; the recording is incomplete"]
    if recorded.error:
        return [f"the recording cannot be read: {recorded.error}"]
    if not recorded.complete:
        return ["the recording is incomplete"]
    again = recorded.resettled
    if again is None or again.identical:
        return []
    if again.error:
        return [f"the recording cannot be re-settled: {again.error}"]
    diffs = again.differences or []
    return [f"the recording does not re-settle as the DMO settled: {len(diffs)} difference(s)"
            + (f", first {diffs[0]}" if diffs else "")]


def _reproduction_problems(reproduced: Reproduced | None) -> list[str]:
    if reproduced is None:  # not a --from run
        return []
    if reproduced.error:
        return [f"--from {reproduced.source}: cannot compare: {reproduced.error}"]
    diffs = reproduced.differences
    if reproduced.identical and not diffs:
        return []
    return [f"--from {reproduced.source}: {len(diffs)} statement line(s) differ from the recording"
            + (f", first {diffs[0]}" if diffs else "")]
