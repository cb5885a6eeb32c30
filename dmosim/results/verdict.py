"""Whether a finished run can be trusted: the problems, one line each, that make ``dmosim run`` and
``dmosim sweep`` exit 1 (docs/experiments.md, "The result"), read from the run's result alone."""

from __future__ import annotations

from collections.abc import Iterable

SHOWN_PROBLEMS = 3  # the one line on stderr names this many; result.json's verdict has them all


def problems(result: dict, *, agents: Iterable[str], days: int,
             recorded: set[tuple[str, str]] | None = None) -> list[str]:
    """Every reason not to trust the run, one line each; empty when there is none.

    ``result`` is the run's result (``dmosim run --json``); ``agents`` the run's fleet, ``days`` the days its
    experiment asked for; ``recorded`` the (market day, agent) of every statement a complete recording holds (None
    when the recording is incomplete or there is none: then nothing is asked of it). The problems, in this order:
    an agent locked out on a day (the day's ``locked_out``: its process talked to the DMO while the DMO was not
    taking its messages); a day the DMO did not settle; an agent of the run with no statement on a settled day; a
    statement the DMO settled that the complete recording lacks; the recorder's failure or an unreadable or cut
    recording (``recorded``); a complete recording whose days do not re-settle, from it alone, to the statements the
    DMO published (``recorded.resettled``); a ``--from`` run that did not settle as its recording (``reproduced``).
    """
    out = []
    settled = result.get("days", [])
    for day in settled:
        for entry in day.get("locked_out", []):
            agent = entry if isinstance(entry, str) else entry.get("agent")
            out.append(f"{agent} was locked out on {day['market_day']}: its process talked to the DMO while the DMO "
                       "was not taking its messages")
    numbers = {day["day"] for day in settled}
    out += [f"day {n} of {days} was not settled" for n in range(1, days + 1) if n not in numbers]
    everyone = sorted(set(agents) | set(result.get("agents", [])))
    for day in settled:
        lacking = [a for a in everyone if a not in day.get("settlement", {})]
        out += [f"{agent} has no statement for {day['market_day']}" for agent in lacking]
    if recorded is not None:
        out += [f"the recording lacks {agent}'s statement for {day['market_day']}" for day in settled
                for agent in sorted(day.get("settlement", {})) if (day["market_day"], agent) not in recorded]
    out += _recording_problems(result.get("recorded"))
    out += _reproduction_problems(result.get("reproduced"))
    return out


def verdict(found: list[str]) -> dict:
    """The ``verdict`` object of the result: ``ok`` and the ``problems``."""
    return {"ok": not found, "problems": list(found)}


def one_line(found: list[str]) -> str:
    """The problems as the one line ``dmosim run`` prints on stderr: the first few, and how many more."""
    more = len(found) - SHOWN_PROBLEMS
    return (f"the run is not to be trusted: {'; '.join(found[:SHOWN_PROBLEMS])}"
            + (f"; and {more} more (result.json, \"verdict\")" if more > 0 else ""))


def _recording_problems(recorded: dict | None) -> list[str]:
    if recorded is None:  # --no-record
        return []
    if recorded.get("recorder"):
        return [f"the recorder failed: {recorded['recorder']}; the recording is incomplete"]
    if recorded.get("error"):
        return [f"the recording cannot be read: {recorded['error']}"]
    if not recorded.get("complete", False):
        return ["the recording is incomplete"]
    again = recorded.get("resettled")
    if again is None or again.get("identical", False):
        return []
    if again.get("error"):
        return [f"the recording cannot be re-settled: {again['error']}"]
    diffs = again.get("differences", [])
    return [f"the recording does not re-settle as the DMO settled: {len(diffs)} difference(s)"
            + (f", first {diffs[0]}" if diffs else "")]


def _reproduction_problems(reproduced: dict | None) -> list[str]:
    if reproduced is None:  # not a --from run
        return []
    if reproduced.get("error"):
        return [f"--from {reproduced['source']}: cannot compare: {reproduced['error']}"]
    diffs = reproduced.get("differences", [])
    if reproduced.get("identical", False) and not diffs:
        return []
    return [f"--from {reproduced['source']}: {len(diffs)} statement line(s) differ from the recording"
            + (f", first {diffs[0]}" if diffs else "")]
