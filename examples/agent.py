"""A market agent written from docs/protocol.md alone, with nothing but zenoh and the standard library.

Its strategy is naive: it bids to buy a flat FLAT_MW in every hour at any price up to the DMO's price cap, and it
meters exactly its award in every grid-connected sub-period (0 while islanded), so it is never penalised. As each
market day is settled it prints, as one JSON line, its own reckoning of that day's bill beside the DMO's
statement; it stays for as many days as the DMO's clock says the run has.

It loses nothing to a lost message: what it sends goes again until the DMO's receipt comes, and when the DMO has
been quiet for a while it asks for the latest of what it waits for.

    python examples/agent.py --id mg2 --run-id RUN --connect tcp/127.0.0.1:7447 --auth-dir DIR
"""

import argparse
import hashlib
import json
import queue
import time
from fractions import Fraction

import zenoh

FLAT_MW = 4.0
MAX_IMPORT_MW = 10.0
RESEND_S = 0.5  # send again what has no receipt after this long
ASK_S = 2.0     # ask the DMO for what we wait for after this long without news


def main() -> None:
    args = parse_args()
    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("connect/endpoints", json.dumps([args.connect]))
    if args.auth_dir:  # the bundle DIR/<id>/ of the run's credentials (docs/security.md)
        password = open(f"{args.auth_dir}/{args.id}/password").read().rstrip("\n")
        config.insert_json5("transport/auth/usrpwd/user", json.dumps(args.id))
        config.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    prefix = f"dmosim/{args.run_id}"
    incarnation = time.time_ns()  # this process: a restarted agent is a later one
    inbox: queue.Queue = queue.Queue()

    with zenoh.open(config) as session:
        # the DMO tracks our presence by this token: kept, since a token Zenoh no longer holds is undeclared
        token = session.liveliness().declare_token(f"{prefix}/alive/{args.id}")  # noqa: F841
        mine = ("clock", "call_for_bids", "grid", f"award/{args.id}", f"statement/{args.id}", "summary",
                f"receipt/{args.id}")
        for topic in mine:
            session.declare_subscriber(f"{prefix}/dmo/{topic}", lambda s: inbox.put(json.loads(s.payload.to_bytes())))

        clock = wait_for_the_dmo(session, prefix)  # it answers once it listens: the run's token, the market day
        run = clock["run"]
        seq = 0
        unreceipted = {}  # SHA-256 of each payload sent -> [key, payload, when to send it again]

        def send(topic: str, kind: str, day: str, **fields) -> None:
            nonlocal seq
            message = {"kind": kind, "schema_version": 4, "sender": args.id, "run": run, "incarnation": incarnation,
                       "market_day": day, "seq": seq, "sent_at": time.time_ns(), **fields}
            key, payload = f"{prefix}/agent/{args.id}/{topic}", json.dumps(message).encode()
            session.put(key, payload)
            unreceipted[hashlib.sha256(payload).hexdigest()] = [key, payload, time.monotonic() + RESEND_S]
            seq += 1

        send("register", "registration", clock["market_day"], case="flat", max_import_mw=MAX_IMPORT_MW,
             max_export_mw=MAX_IMPORT_MW)
        # per market day: the award, what we metered, the statement and the summary (a run may have several days)
        awards, metered, statements, summaries, bids = {}, {}, {}, {}, set()
        last_day = None  # the market day the clock says is the run's last
        heard = time.monotonic()
        while last_day is None or last_day not in statements or last_day not in summaries:
            for entry in unreceipted.values():  # no receipt yet: send it again, byte for byte
                if entry[2] <= time.monotonic():
                    session.put(entry[0], entry[1])
                    entry[2] = time.monotonic() + RESEND_S
            try:
                msg = inbox.get(timeout=RESEND_S / 2)
            except queue.Empty:
                if time.monotonic() - heard > args.timeout:
                    raise SystemExit(f"{args.id}: nothing from the DMO for {args.timeout:g} s") from None
                if time.monotonic() - heard > ASK_S:  # a message of the DMO's may be lost: ask for the latest
                    for topic in mine[:-1]:
                        for reply in session.get(f"{prefix}/dmo/{topic}", timeout=1.0):
                            if reply.ok is not None:
                                inbox.put(json.loads(reply.ok.payload.to_bytes()))
                continue
            heard = time.monotonic()
            kind, day = msg["kind"], msg["market_day"]
            if msg["run"] != run:
                continue  # not of this run
            if kind == "receipt":
                unreceipted.pop(msg["payload_sha256"], None)
                if not msg["accepted"]:
                    print(f"the DMO refused my {msg['received_kind']} #{msg['received_seq']}: {msg['code']}: "
                          f"{msg['reason']}", flush=True)
            elif kind == "clock" and msg["day"] == msg["days"]:
                last_day = day
            elif kind == "call_for_bids" and day not in bids:
                bids.add(day)
                step = {"price_per_mwh": msg["price_cap_per_mwh"], "quantity_mw": FLAT_MW}
                send("bid", "bid", day, hours=[[step]] * 24)
            elif kind == "award" and day not in awards:
                awards[day] = msg
                send("schedule", "schedule", day, status="flat", commitment={}, expected_cost=0.0,
                     p_m_expected_mw=msg["p_sch_mw"], scenarios=1, mip_gap=None)
            elif kind == "grid_state" and day in awards and msg["hour"] not in metered.get(day, {}):
                hour, award_mw = msg["hour"], awards[day]["p_sch_mw"][msg["hour"] - 1]
                p_m = [award_mw if connected else 0.0 for connected in msg["connected"]]
                metered.setdefault(day, {})[hour] = p_m
                send("meter", "meter_report", day, hour=hour, subperiods=msg["subperiods"], p_m_mw=p_m,
                     deviation_mw=[p - award_mw for p in p_m])
            elif kind == "settlement_statement":
                statements[day] = msg
            elif kind == "day_summary":
                summaries[day] = msg

    for day in sorted(statements):  # one line per day: the DMO's statement beside our own reckoning
        print(json.dumps({"agent": args.id, "market_day": day, "statement_total": statements[day]["total"],
                          "own_total": float(reckon(awards[day], metered.get(day, {}))),
                          "meter_reports": len(metered.get(day, {}))}), flush=True)


def wait_for_the_dmo(session, prefix: str) -> dict:
    """Ask the DMO for its clock until it answers (a query, so it works whenever we start)."""
    while True:
        for reply in session.get(f"{prefix}/dmo/clock", timeout=2.0):
            if reply.ok is not None:
                return json.loads(reply.ok.payload.to_bytes())
        time.sleep(0.5)


def reckon(award: dict, metered: dict) -> Fraction:
    """Our bill by the rules of docs/market.md, in exact arithmetic on the numbers as written on the wire: per hour,
    price x award, plus the penalty on imports above the award and minus the credit below it, each rounded half-even
    to the cent."""
    total = Fraction(0)
    exact = lambda x: Fraction(repr(float(x)))  # noqa: E731
    cents = lambda amount: Fraction(round(amount * 100), 100)  # noqa: E731  (round() of a Fraction is half-even)
    for h, (award_mw, price) in enumerate(zip(award["p_sch_mw"], award["clearing_price_per_mwh"]), start=1):
        p_m = metered.get(h)
        if p_m is None:
            raise RuntimeError(f"hour {h} was not metered: the DMO settles it by its missing-data rule")
        over = sum(max(exact(p) - exact(award_mw), 0) for p in p_m) / len(p_m)  # MWh: MW x dt, dt = 1/K h
        under = sum(max(exact(award_mw) - exact(p), 0) for p in p_m) / len(p_m)
        total += (cents(exact(price) * exact(award_mw)) + cents(exact(award["penalty_per_mwh"]) * over)
                  - cents(exact(award["credit_per_mwh"]) * under))
    return total


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--id", required=True, help="this agent's id, e.g. mg2")
    parser.add_argument("--run-id", required=True, help="the run to join (the DMO's --run-id)")
    parser.add_argument("--connect", required=True, help="the DMO's endpoint, e.g. tcp/127.0.0.1:7447")
    parser.add_argument("--auth-dir", help="the run's credentials (this agent uses DIR/<id>/password)")
    parser.add_argument("--timeout", type=float, default=600.0, help="give up after this long without news (s)")
    return parser.parse_args()


if __name__ == "__main__":
    main()
