"""The Zenoh routers ``dmosim run --routers N`` starts on this machine, each standing for one host's (docs/hosts.md):
a star of ``dmosim router`` processes around the first, which the DMO and the recorder are clients of, with the
agents spread over all of them in blocks of consecutive agents.

With N = 1 the DMO is a client like any other process instead of being the agents' router. With N > 1 the routers
log in to the first with their own credentials over mutual TLS, as routers of a mesh must, and the run starts once
the first router holds every other's link to it: each router declares a liveliness token per link it has
(``Keys.link``, dmosim/cli/router.py), and the token can only reach the first router over that link.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path

import zenoh

from messages.keys import Keys
from messages.transport import BusConfig
from messages.transport.access import bundle_settings
from scenarios.names import DMO

from .processes import Roles, dmosim_command, free_port, wait_listening

ROUTER_START_S = 60.0  # for a router to listen, and for the routers that connect to the first to be linked to it
# The lease each router announces: how long the others wait, after its last sign of life, to take its link as down.
# The routers share this machine's cores with the agents: with Zenoh's 10 s, a thousand agents starting on 2 cores
# left the links of the mesh silent long enough to expire, and each expiry withdrew every agent behind the link (334
# incidents) and lost what was on it. A router killed is seen at once, its connections closing, whatever the lease.
ROUTER_LEASE_S = 60.0
ALIVE_CHECK_S = 1.0  # while waiting for links: how often to look whether a router has exited meanwhile

Link = tuple[str, str]  # (router, peer): router's link to peer, by their Zenoh ids


def router_names(n: int) -> list[str]:
    """The roles, and the mesh's Zenoh users, of ``n`` routers: host1 (the hub), host2, ..."""
    return [f"host{i}" for i in range(1, n + 1)]


def spread(agents: list[str], routers: int) -> dict[str, int]:
    """Agent -> the index of the router it connects to: blocks of consecutive agents, as even as they come."""
    return {agent: i * routers // len(agents) for i, agent in enumerate(agents)}


def start_routers(roles: Roles, names: list[str], scheme: str, run_id: str, auth: Path, logs: Path,
                  starting_s: float = ROUTER_START_S) -> list[str]:
    """Start one ``dmosim router`` per name on a free loopback port, every one after the first connecting to the
    first as its own user, and wait (at most ``starting_s``, while they run) until each listens and the first holds
    every other's link to it; their endpoints."""
    at = [f"{scheme}/127.0.0.1:{free_port()}" for _ in names]
    for i, name in enumerate(names):
        relay = ["--user", name, "--connect", at[0]] if i else []
        roles.start(name, dmosim_command("router", "--run-id", run_id, "--auth-dir", str(auth), "--listen", at[i],
                                         "--lease", repr(ROUTER_LEASE_S), *relay), log=logs / f"{name}.log")
    for i, name in enumerate(names):
        alive = roles.roles[name].process.poll
        wait_listening(int(at[i].rsplit(":", 1)[1]), starting_s, lambda poll=alive: poll() is None)
    if len(names) > 1:
        running = lambda: all(roles.roles[name].process.poll() is None for name in names)  # noqa: E731
        with MeshLinks(at[0], run_id, auth) as mesh:
            mesh.wait(lambda up: len({router for router, peer in up if peer == mesh.router}) == len(names) - 1,
                      starting_s, running)
    return at


class MeshLinks:
    """The links between the routers of a run's mesh as a client of one of them sees them: the liveliness tokens
    the routers hold for their links (``Keys.link``), ``up`` now and every one that ``ever`` was, as they come and
    go. ``router`` is the Zenoh id of the router it is a client of. It logs in as ``user`` with that bundle of the
    run's credentials ``auth`` (the DMO's by default, which may see every key of the run)."""

    def __init__(self, endpoint: str, run_id: str, auth: Path, user: str = DMO):
        self.keys = Keys(run_id)
        self.config = BusConfig(mode="client", connect=(endpoint,), connect_timeout_s=ROUTER_START_S,
                                overrides=bundle_settings(auth, user))
        self.up: set[Link] = set()
        self.ever: set[Link] = set()
        self.router = ""
        self._changed = threading.Condition()
        self._session: zenoh.Session | None = None

    def __enter__(self) -> MeshLinks:
        self._session = zenoh.open(self.config.to_zenoh())
        try:
            self.router = str(self._session.info.routers_zid()[0])
            self._session.liveliness().declare_subscriber(self.keys.link("*", "*"), self._seen, history=True)
        except BaseException:
            self._session.close()
            raise
        return self

    def _seen(self, sample: zenoh.Sample) -> None:
        router, peer = str(sample.key_expr).rsplit("/", 2)[1:]
        with self._changed:
            if sample.kind == zenoh.SampleKind.PUT:
                self.up.add((router, peer))
                self.ever.add((router, peer))
            else:
                self.up.discard((router, peer))
            self._changed.notify_all()

    def wait(self, linked: Callable[[set[Link]], bool], timeout_s: float, alive: Callable[[], bool]) -> None:
        """Return once ``linked(up)``, woken by each token that comes or goes; fail if ``alive()`` turns false (a
        router exited) or ``timeout_s`` passes."""
        deadline = time.monotonic() + timeout_s
        with self._changed:
            while not linked(self.up):
                left = deadline - time.monotonic()
                if not alive():
                    raise RuntimeError("a router of the mesh exited before its links were up")
                if left <= 0:
                    raise RuntimeError(f"the mesh's routers were not linked within {timeout_s:g} s: links up "
                                       f"{sorted(self.up) or 'none'}")
                self._changed.wait(min(left, ALIVE_CHECK_S))

    def __exit__(self, *exc) -> None:
        if self._session is not None:
            self._session.close()
