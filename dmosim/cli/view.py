"""``dmosim view``: the live page of a run, served on localhost: a read-only observer of a run over Zenoh (``--run-id``,
a reader's credentials, as the recorder), or a recording played into the same page (``dmosim view RECORDING``)."""

from __future__ import annotations

import logging
import sys
import threading
from pathlib import Path

from messages.keys import check_run_id

from ..arguments import integer, number
from ..console import UsageError
from .flags import RECORDING_HELP, add_bus_flags, bus_config, load_recording, setup_logging

HELP = "the live page of a run (or of a recording played into it), served on localhost"
log = logging.getLogger("dmosim.view")
MAX_REPLAY_RATE = 10_000.0  # a replay's rate, at most: a week's recording in a minute


def add_arguments(p) -> None:
    p.add_argument("recording", nargs="?", metavar="PATH", help=RECORDING_HELP + ", played into the page; without "
                   "it, --run-id: a run live over Zenoh")
    p.add_argument("--run-id", help="the run to watch live, as a reader (the credentials' viewer bundle; "
                                    "docs/view.md)")
    p.add_argument("--host", default="127.0.0.1",
                   help="the address the page is served on (default: 127.0.0.1, this machine only); another needs "
                        "--expose")
    p.add_argument("--port", type=integer(0, 65535), default=0, help="the page's port (default: 0, a free port, printed)")
    p.add_argument("--expose", action="store_true",
                   help="serve on a --host other than loopback: whoever reaches it sees the run's data "
                        "(docs/view.md)")
    p.add_argument("--rate", type=number(0.0, MAX_REPLAY_RATE, above=True), default=1.0,
                   help=f"a recording plays at this many times its recorded speed (default: 1, at most {MAX_REPLAY_RATE:g})")
    p.add_argument("--paused", action="store_true", help="a recording starts paused (the page plays it)")
    p.add_argument("--url-file", metavar="PATH", help="write the page's URL and a newline to this file once it serves")
    p.add_argument("--quiet", action="store_true", help="log warnings only")
    add_bus_flags(p, "client")


def run(args) -> int:
    setup_logging("view", args.quiet)
    if (args.recording is None) == (args.run_id is None):
        raise UsageError("give a recording (PATH) to play, or --run-id ID to watch a run live, not both")
    try:
        from ..view import server  # noqa: PLC0415  (the web stack only for the page)
    except ImportError as exc:
        raise UsageError(f"dmosim view needs the extra 'view' ({exc.name} is missing): pip install 'dmosim[view]'") \
            from None
    if not server.is_loopback(args.host) and not args.expose:
        raise UsageError(f"--host {args.host} is not loopback: whoever reaches it would see the run's data; add "
                         "--expose to mean it (docs/view.md)")
    from ..view.board import Board  # noqa: PLC0415

    board, stop = Board(), threading.Event()
    if args.recording is not None:
        return _replay(args, board, stop, server)
    try:
        check_run_id(args.run_id)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    return _live(args, board, stop, server)


def _replay(args, board, stop: threading.Event, server) -> int:
    from ..view.player import PagePlayer, playable  # noqa: PLC0415

    rec = load_recording(args.recording)  # not a recording: one line, exit 2
    items = playable(rec)
    if not items:
        raise UsageError(f"{args.recording}: holds no message of a run to play")
    player = PagePlayer(items, board, args.rate, args.paused)
    board.note(run_id=rec.run_id, recording=str(rec.path))
    sock = _bound(args, server)
    board.render()
    board.start(stop)
    player.start(stop)
    try:
        _announce(args, server.url_of(sock))
        server.serve(sock, server.app(board, stop, player.control), stop)
    finally:
        stop.set()
    return 0


def _live(args, board, stop: threading.Event, server) -> int:
    from messages.transport import Bus  # noqa: PLC0415

    from ..view.feed import VIEWER, LiveFeed  # noqa: PLC0415

    config = bus_config(args, "client", VIEWER)
    sock = _bound(args, server)
    with Bus(args.run_id, args.user or VIEWER, config, announce=False) as bus:
        feed = LiveFeed(bus, board)
        feed.start(stop)
        board.render()
        board.start(stop)
        try:
            _announce(args, server.url_of(sock))
            server.serve(sock, server.app(board, stop), stop)
        finally:
            stop.set()
    return 0


def _bound(args, server):
    try:
        return server.bind(args.host, args.port)
    except server.BindError as exc:
        raise UsageError(str(exc)) from None


def _announce(args, url: str) -> None:
    """The URL on stderr (stdout stays for machine-readable output), and in ``--url-file``."""
    print(f"dmosim view: the page is at {url} (Ctrl-C stops it)", file=sys.stderr, flush=True)
    if args.url_file:
        with open(Path(args.url_file), "w") as f:
            f.write(url + "\n")
