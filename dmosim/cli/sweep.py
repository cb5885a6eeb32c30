"""``dmosim sweep EXPERIMENT --set KEY=V1,V2 ...``: the experiment run once per combination of the swept values
(dmosim/experiment/sweep.py), each run a ``dmosim run`` of its own into its own run directory, ``--parallel`` at a
time; then one table of every run and agent (``sweep.csv``) and its figure (``sweep.png``, dmosim/results/sweeps.py).

Every variant is validated before the first run starts. A run that fails, or ends with a verdict that is not ok
(docs/experiments.md, "The result"), is reported and keeps a row saying so (``status`` ``failed`` or
``untrusted``); the others go on, and the sweep exits 1 at the end. A run's output goes to files, read once it has
ended (``Command``). Ctrl-C or SIGTERM stops every run under way (each stops its roles; what is left of one after
``COMMAND_STOP_S`` is killed with all it started). With ``--cluster`` each run is a task on the workers of a Dask
cluster instead of a process here (dmosim/launch/cluster.py, docs/cluster.md), into the same directories, which the
workers must share.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
from pathlib import Path

from ..arguments import integer
from ..console import Progress, UsageError, print_json, stop_on_terminate
from ..experiment.rundir import RUNS, RunDirError, claim_directory
from ..experiment.spec import Experiment, ExperimentError, load_experiment, to_toml
from ..experiment.sweep import MAX_VARIANTS, Variant, parse_setting, variants
from ..launch.cluster import Commands
from ..launch.processes import COMMAND_STOP_S, Command, dmosim_command, interrupts_held, stop_processes
from ..launch.roles import resolved, strategy_of
from ..results.report import RunReport, parse_result
from .checks import Checked, check_inputs, strategy_source
from .flags import check_out
from .placement import add_cluster_flag, check_cluster, check_shared, connected

HELP = "run an experiment once per combination of swept settings, into one table and figure"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("experiment", metavar="EXPERIMENT", help="the experiment file (TOML, docs/experiments.md)")
    p.add_argument("--set", dest="settings", action="append", required=True, metavar="KEY=V1,V2,...",
                   help="a setting to sweep and its values, e.g. market.penalty=100,150,300 (repeatable: every "
                        "combination runs; values are TOML: numbers, true/false, strings, arrays like [1,0.8])")
    p.add_argument("--parallel", type=integer(1, MAX_VARIANTS), metavar="N",
                   help="runs at a time (default: what the machine's cores fit: cores / agents of a run, at least "
                        "1; each run is a DMO and its agents, each agent solving on a core; with --cluster, the "
                        "workers' threads in all)")
    add_cluster_flag(p, "each variant's dmosim run")
    p.add_argument("--out", metavar="DIR",
                   help="the sweep's directory: one run directory per variant, sweep.csv (sweep-seeds.csv), sweep.png "
                        "(default: runs/sweep-<experiment name>-<time>)")
    p.add_argument("--overwrite", action="store_true", help="use --out DIR even if it is not empty")
    p.add_argument("--check", action="store_true", help="validate every variant, list them and exit")
    p.add_argument("--json", action="store_true", help="print one JSON object at the end")
    p.add_argument("--quiet", action="store_true", help="no progress bar or lines on stderr")


def run(args) -> int:
    try:
        experiment = resolved(load_experiment(args.experiment))  # one market day for every variant
        runs = variants(_portable(experiment), [parse_setting(s) for s in args.settings])
    except ExperimentError as exc:
        raise UsageError(str(exc)) from None
    checked, agents = Checked(), 1  # each variant as `dmosim run --check` checks it, each file read once
    for v in runs:
        try:
            fleet = check_inputs(v.experiment, checked)
            agents = max(agents, len(fleet))
            checked.rule(v.experiment.market.settlement)
            for member in fleet:  # the experiment and the --set values are the user's: their strategies load
                checked.strategy(strategy_of(v.experiment, member), member, strategy_source(v.experiment, member))
        except ExperimentError as exc:
            raise UsageError(f"{v.label}: {exc}") from None
    keys = list(runs[0].settings)
    check_cluster(args)
    if args.check:
        check_out(args)
        print(f"dmosim sweep: {len(runs)} valid run(s) of {args.experiment}, sweeping {', '.join(keys)}:")
        for v in runs:
            print(f"  {v.label}")
        return 0
    stamp = time.strftime("%Y%m%dT%H%M%S")
    stop_on_terminate()  # a terminated sweep stops its runs, as Ctrl-C does
    # The cluster is reached before the sweep's directory is claimed: one that does not answer leaves nothing behind.
    with connected(args) if args.cluster else contextlib.nullcontext() as cluster:
        try:
            root = claim_directory(Path(args.out) if args.out else RUNS / f"sweep-{experiment.name}-{stamp}",
                                   args.overwrite)
        except RunDirError as exc:
            raise UsageError(str(exc)) from None
        if cluster:
            check_shared(cluster, root)
            commands, parallel = Commands(cluster), args.parallel or cluster.threads()
            where = f" on the cluster at {args.cluster} ({len(cluster.workers())} workers, {cluster.threads()} threads)"
        else:
            commands, parallel, where = LocalCommands(), args.parallel or max(1, (os.cpu_count() or 1) // agents), ""
        bar = None if args.quiet else Progress("runs")
        say, tick = (bar.say, bar.update) if bar else (lambda text: None, lambda done, total, text: None)
        say(f"sweep of {args.experiment}: {len(runs)} run(s), {parallel} at a time{where}, into {root}")
        try:
            rows, failed = _run_all(runs, root.resolve(), parallel, commands, say, tick)
        finally:
            if bar:
                bar.close()

    import pandas as pd  # noqa: PLC0415  (pandas, matplotlib: once the runs are done)

    from dmosim.studies.figures import save  # noqa: PLC0415

    from ..results.sweeps import SEED, seed_summary, sweep_figure  # noqa: PLC0415

    table = pd.DataFrame(rows)
    table.to_csv(root / "sweep.csv", index=False)
    seeds = root / "sweep-seeds.csv" if SEED in keys else None
    if seeds:
        seed_summary(table, keys).to_csv(seeds, index=False)
    figure = None
    if (table["status"] == "ok").any():
        figure = save(sweep_figure(table, keys, f"{experiment.name}: each agent's bill and penalty over the run"),
                      root / "sweep.png")
    status = table.drop_duplicates("label").set_index("label")["status"]
    summary = {"sweep": str(root.resolve()), "table": str((root / "sweep.csv").resolve()),
               "figure": str(figure.resolve()) if figure else None, "keys": keys, "runs": len(runs),
               "seeds_table": str(seeds.resolve()) if seeds else None,
               **{name: [label for label in failed if status[label] == name] for name in ("failed", "untrusted")}}
    if args.json:
        print_json(summary)
    else:
        print(_render(table, keys))
        print(f"table: {summary['table']}" + (f"; over the seeds: {summary['seeds_table']}" if seeds else "")
              + (f"; figure: {summary['figure']}" if figure else ""))
        for label in failed:
            print(f"{status[label].upper()}: {label} (its logs: {root / label / 'logs'})")
    if failed:  # one line, also with --quiet and --json, as dmosim run gives it
        print(f"failed: {len(failed)} of {len(runs)} run(s) did not end ok: "
              + ", ".join(f"{label} ({status[label]})" for label in failed), file=sys.stderr)
    return 1 if failed else 0


def _portable(experiment: Experiment) -> Experiment:
    """The experiment with its fleet file as an absolute path, so each variant's file may live elsewhere."""
    fleet = experiment.agents.fleet
    if fleet is None:
        return experiment
    return experiment.model_copy(update={"agents": experiment.agents.model_copy(
        update={"fleet": str(Path(fleet).resolve())})})


class LocalCommands:
    """``dmosim`` commands as processes of this machine, each watched by ``poll``, all stopped by ``stop``: what
    ``dmosim.launch.cluster.Commands`` does on a cluster's workers. Each leads a process group of its own (the
    terminal's Ctrl-C reaches the sweep, which stops them) and writes its output to files (``Command``)."""

    def __init__(self):
        self.commands: list[Command] = []

    def start(self, args: list[str], name: str):
        """Start ``dmosim ARGS``; a function that returns None while it runs, then its exit code, stdout and stderr."""
        with interrupts_held():  # recorded before a Ctrl-C can leave it unseen
            command = Command(dmosim_command(*args))
            self.commands.append(command)

        def poll() -> tuple[int, str, str] | None:
            code = command.poll()
            return None if code is None else (code, *command.output())

        return poll

    def stop(self) -> None:
        """Stop every command still running and wait for it: ``dmosim run`` stops its roles on SIGTERM, and what is
        left of it after ``COMMAND_STOP_S`` is killed."""
        stop_processes([c.process for c in self.commands], COMMAND_STOP_S)


def _run_all(runs: list[Variant], root: Path, parallel: int, commands: LocalCommands | Commands, say,
             tick) -> tuple[list[dict], list[str]]:
    """Every variant as ``dmosim run`` started by ``commands``, at most ``parallel`` at once; the table's rows and
    the failed labels. ``tick(runs done, runs in all, what is under way)`` follows them
    (``dmosim.console.Progress.update``); ``say`` reports a run that did not end ok."""
    from ..results.sweeps import sweep_rows  # noqa: PLC0415

    (root / "experiments").mkdir(exist_ok=True)
    pending, running, rows, failed, done = list(runs), {}, {}, [], 0
    try:
        while pending or running:
            while pending and len(running) < parallel:
                v = pending.pop(0)
                file = root / "experiments" / f"{v.label}.toml"
                file.write_text(to_toml(v.experiment))
                poll = commands.start(["run", str(file), "--out", str(root / v.label), "--json", "--quiet"],
                                      f"dmosim-sweep-{v.label}")
                running[v.label] = (v, poll, time.monotonic())
                tick(done, len(runs), f"started {v.label}")
            for label, (v, poll, started) in list(running.items()):
                ended = poll()
                if ended is None:
                    continue
                code, out, err = ended
                del running[label]
                done += 1
                seconds = time.monotonic() - started
                result = _result(out)
                if code and (result is None or result.verdict.ok):
                    result = None  # it went wrong otherwise than by its verdict: nothing of it to table
                rows[label] = sweep_rows(v.settings, label, str((root / label).resolve()), seconds, result,
                                         (err.strip().splitlines() or [f"exit {code}"])[-1])
                status = rows[label][0]["status"]
                if status == "ok":
                    tick(done, len(runs), f"{label} done in {seconds:.0f} s")
                else:
                    tick(done, len(runs), f"{label} {status}")
                    failed.append(label)
                    say(f"{done}/{len(runs)} {status.upper()}: {label} after {seconds:.0f} s: "
                        f"{rows[label][0]['error']}")
            time.sleep(0.2)
    finally:  # Ctrl-C, or any failure here: nothing of the sweep goes on (once all are over, a no-op)
        commands.stop()
    return [row for v in runs for row in rows[v.label]], failed


def _result(out: str) -> RunReport | None:
    """The result a run printed (``dmosim run --json``), also when its verdict made it exit 1; None if it printed
    none (it failed before its result was written)."""
    try:
        return parse_result(out, "the run's output")
    except UsageError:
        return None


def _render(table, keys: list[str]) -> str:
    """Each run's total per agent, one line per run."""
    ok = table[table["status"] == "ok"]
    agents = sorted(ok["agent"].dropna().unique())
    head = "".join(f"{k:>18}" for k in keys) + "".join(f"{a + ' $':>13}" for a in agents)
    lines = [head, "-" * len(head)]
    for label, run in table.groupby("label", sort=False):
        first = run.iloc[0]
        cells = "".join(f"{str(first[k]):>18}" for k in keys)
        if first["status"] != "ok":
            lines.append(cells + f"  {first['status']}: {first['error']}")
            continue
        totals = run.set_index("agent")["total"]
        lines.append(cells + "".join(f"{totals.get(a, float('nan')):>13,.2f}" for a in agents))
    return "\n".join(lines)
