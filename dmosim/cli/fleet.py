"""``dmosim fleet``: a generated fleet (diverse microgrids drawn from a seed, scenarios/diverse.py) written as a fleet
file with a case file per member, to inspect or edit before a run names it (``--fleet``). It is the fleet that
``dmosim run --generate N --seed S`` writes into its run directory, placed on ``--feeder`` as that run places it.
With ``--json`` and no ``--out`` it writes nothing and prints each member's summary only."""

from __future__ import annotations

import argparse
from pathlib import Path

from scenarios.diverse import summary
from scenarios.fleet import CASES_DIR, FleetError, FleetMember, load_fleet, member_case

from ..arguments import agents, seed
from ..console import UsageError, print_json
from ..experiment.spec import Experiment, ExperimentError, parse_experiment
from ..launch.roles import fleet_written, placed_fleet, resolved

HELP = "write N diverse microgrids drawn from a seed as a fleet file and case files, without running"
DEFAULT_OUT = "fleet.toml"  # the fleet file written when --out names none (and --json is not given)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--agents", type=agents, required=True, metavar="N", help="microgrids mg1..mgN to draw")
    p.add_argument("--seed", type=seed, default=Experiment().seed,
                   help=f"the seed they are drawn from, as a run's seed (default: {Experiment().seed})")
    p.add_argument("--feeder", metavar="NETWORK", help="write each member's bus on this feeder (built in or a file), "
                                                       "as a run on it places them (docs/network.md)")
    p.add_argument("--out", metavar="FILE",
                   help=f"the fleet file; the case files go to {CASES_DIR}/ beside it (default: {DEFAULT_OUT}; with "
                        "--json, none: nothing is written)")
    p.add_argument("--overwrite", action="store_true", help="replace FILE and case files of the same names")
    p.add_argument("--json", action="store_true", help="print one JSON object: each member's summary, and the files "
                                                       "written if --out names one (else nothing is written)")


def run(args) -> int:
    if args.json and args.out is None:  # a look at the fleet, nothing on disk
        print_json({"fleet": None, "cases": None, "seed": args.seed,
                    "members": _summaries(placed_fleet(_experiment(args)))})
        return 0
    out = Path(args.out or DEFAULT_OUT)
    if out.is_dir():
        raise UsageError(f"--out {out}: is a directory; name the fleet file to write")
    taken = [p for p in (out, *(out.parent / CASES_DIR / f"mg{i}.toml" for i in range(1, args.agents + 1)))
             if p.exists()]
    if taken and not args.overwrite:  # nothing already there is lost by mistake
        raise UsageError(f"{taken[0]} exists; choose another --out or pass --overwrite")
    experiment = _experiment(args)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        fleet_written(experiment, out)
    except OSError as exc:
        raise UsageError(f"--out {out}: cannot write: {exc.strerror or exc}") from None
    try:
        fleet = load_fleet(out)  # read back as a run will read it
    except FleetError as exc:
        raise RuntimeError(f"the fleet written cannot be read back: {exc}") from None
    rows = _summaries(fleet)
    if args.json:
        print_json({"fleet": str(out.resolve()), "cases": str((out.parent / CASES_DIR).resolve()), "seed": args.seed,
                    "members": rows})
        return 0
    print(f"{'agent':<8}{'MWh/day':>9}{'peak MW':>9}{'units':>14}{'units MW':>10}{'wind MW':>9}{'solar MW':>9}"
          f"{'store MWh':>10}{'tie MW':>8}" + ("  bus" if args.feeder else ""))
    for r in rows:
        print(f"{r['id']:<8}{r['energy_mwh']:>9.1f}{r['peak_mw']:>9.2f}{r['units']:>14}{r['dispatchable_mw']:>10.2f}"
              f"{r['wind_mw']:>9.2f}{r['solar_mw']:>9.2f}{r['storage_mwh']:>10.2f}{r['tie_mw']:>8.2f}"
              + (f"  {r['bus']}" if args.feeder else ""))
    print(f"wrote {out} and {len(fleet)} case files in {out.parent / CASES_DIR}/ (drawn from seed {args.seed}); run them "
          f"with dmosim run --fleet {out}")
    return 0


def _experiment(args) -> Experiment:
    """The experiment of a run with ``--generate N --seed S [--feeder F]``: its fleet drawn and placed as the run
    would draw and place it."""
    try:
        return resolved(parse_experiment({"seed": args.seed, "agents": {"generate": args.agents},
                                          "network": {"feeder": args.feeder}}, "flags"))
    except ExperimentError as exc:
        raise UsageError(str(exc)) from None


def _summaries(fleet: list[FleetMember]) -> list[dict]:
    """Each member's summary (``scenarios.diverse.summary``) and bus."""
    return [{"id": m.id, **summary(member_case(m)), "bus": m.bus} for m in fleet]
