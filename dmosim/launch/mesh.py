"""The Zenoh routers ``dmosim run --routers N`` starts on this machine, each standing for one host's (docs/hosts.md):
a star of ``dmosim router`` processes around the first, which the DMO and the recorder are clients of, with the
agents spread over all of them in blocks of consecutive agents.

With N = 1 the DMO is a client like any other process instead of being the agents' router. With N > 1 the routers
log in to the first with their own credentials over mutual TLS, as routers of a mesh across hosts must.
"""

from __future__ import annotations

from pathlib import Path

from .processes import Roles, dmosim_command, free_port, wait_for_line, wait_listening

ROUTER_START_S = 60.0  # for a router to listen, and for one that connects to the first to report its link up
# The lease each router announces: how long the others wait, after its last sign of life, to take its link as down.
# The routers share this machine's cores with the agents: with Zenoh's 10 s, a thousand agents starting on 2 cores
# left the links of the mesh silent long enough to expire, and each expiry withdrew every agent behind the link (334
# incidents) and lost what was on it. A router killed is seen at once, its connections closing, whatever the lease.
ROUTER_LEASE_S = 60.0


def router_names(n: int) -> list[str]:
    """The roles, and the mesh's Zenoh users, of ``n`` routers: host1 (the hub), host2, ..."""
    return [f"host{i}" for i in range(1, n + 1)]


def spread(agents: list[str], routers: int) -> dict[str, int]:
    """Agent -> the index of the router it connects to: blocks of consecutive agents, as even as they come."""
    return {agent: i * routers // len(agents) for i, agent in enumerate(agents)}


def start_routers(roles: Roles, names: list[str], scheme: str, run_id: str, auth: Path, logs: Path) -> list[str]:
    """Start one ``dmosim router`` per name on a free loopback port, every one after the first connecting to the
    first as its own user, and wait until each listens and each link to the first is up; their endpoints."""
    at = [f"{scheme}/127.0.0.1:{free_port()}" for _ in names]
    for i, name in enumerate(names):
        relay = ["--user", name, "--connect", at[0]] if i else []
        roles.start(name, dmosim_command("router", "--run-id", run_id, "--auth-dir", str(auth), "--listen", at[i],
                                         "--lease", repr(ROUTER_LEASE_S), *relay), log=logs / f"{name}.log")
    for i, name in enumerate(names):
        alive = roles.roles[name].process.poll
        wait_listening(int(at[i].rsplit(":", 1)[1]), ROUTER_START_S, lambda poll=alive: poll() is None)
        if i:
            wait_for_line(logs / f"{name}.log", r"router link up", ROUTER_START_S, lambda poll=alive: poll() is None)
    return at
