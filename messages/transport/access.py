"""Who may join a run and what each process may say and hear: the router's Zenoh access-control rules, and the
Zenoh settings that make a process authenticate with a run's credentials (made by credentials.py).

Zenoh enforces all of it, not our code: the router refuses a session without a known user and password (and, with
TLS, without a certificate of the run's CA), and its ``access_control`` drops every message a process is not
allowed to send or to receive before any handler sees it. The DMO's own check that a sender owns its key
(``keys.check_route``) stays as the second line of defence.

An auth directory is the router's, with one bundle per client process inside, so each host gets only its own
secrets::

    DIR/users.txt                   user:password per process (the router's dictionary), mode 0600
    DIR/access_control.json         the router's rules for this run (no secrets)
    DIR/ca.pem cert.pem key.pem     with TLS: the run's CA, the router's certificate (for the hosts it listens on)
                                    and its key (0600)
    DIR/<name>/password             the bundle of process <name> ("dmo", "recorder", each agent id, each router
    DIR/<name>/ca.pem cert.pem key.pem   of a mesh, ...): its password (0600) and, with TLS, the CA and its client
                                    certificate, whose common name is <name>, and key (0600)

In a mesh of routers (docs/hosts.md) every router serves with the same router files and rules, and logs in to the
routers it connects to with its own bundle.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Sequence
from pathlib import Path

from scenarios.names import DMO, NAME_PATTERN, check_agent_id, is_name

from ..keys import Keys

USERS_FILE = "users.txt"
ACL_FILE = "access_control.json"
PASSWORD_FILE = "password"
CA_FILE, CERT_FILE, KEY_FILE = "ca.pem", "cert.pem", "key.pem"
READERS = ("recorder",)              # processes that may hear everything of the run and say nothing
# The common name of the routers' own certificate. Zenoh authenticates only the side that connects, so a router knows
# the router it connected to by that certificate alone; no process can be named so (a space), nor present it.
ROUTER_CERT_NAME = "dmosim router"
# What the DMO says to every agent. Not its rejections (``dmo/rejected``, for the recording): an agent learns why its
# own message was refused from its receipt, and one agent's junk, refused by the thousand, reaches no other agent.
PUBLIC_TOPICS = ("call_for_bids", "clock", "grid", "network", "summary")
PRIVATE_TOPICS = ("award", "statement", "receipt")  # what the DMO says to one agent, each on dmo/<topic>/<id>
AGENT_TOPICS = ("register", "bid", "schedule", "meter", "day")      # what an agent says, each on agent/<id>/<topic>

_ALL_MESSAGES = ("put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                 "liveliness_token", "declare_liveliness_subscriber", "liveliness_query")


class AuthError(ValueError):
    """An auth directory, password file or flag that cannot be used; the message is one line."""


# --- the rules ---------------------------------------------------------------------------------------------------

def access_control(run_id: str, agents: Sequence[str], readers: Sequence[str] = READERS, *,
                   tls: bool = False, dmo_client: bool = True, routers: Sequence[str] = ()) -> dict:
    """The router's ``access_control`` for one run: deny by default, then per process exactly what it needs.

    - ``dmo``, with ``dmo_client`` (for a DMO that is a client of a separate router): everything under the run
      prefix. A DMO that is the router itself is not a remote session, and no rule applies to it.
    - router R of a mesh (``routers``, docs/hosts.md): everything under the run prefix, both ways, since it relays
      its own clients, whom its own copy of these rules filters. A router that R connected to reaches R with no
      user name (Zenoh authenticates only the side that connects), so it is known by the routers' certificate
      (``ROUTER_CERT_NAME``, signed by the run's CA) and granted the same: a mesh needs ``tls``.
    - a reader (the recorder): subscribe to everything of the run and query it (the DMO's history of the day),
      publish nothing, announce only itself.
    - agent X: publish only its own ``agent/X/{register,bid,schedule,meter,day}``; subscribe to, receive and query
      only the public DMO topics and ``dmo/award/X``, ``dmo/statement/X``, ``dmo/receipt/X``; announce ``alive/X``; see the DMO's
      presence.

    Subjects are usernames (``transport/auth/usrpwd``); with ``tls`` a subject must also present a client
    certificate with its name as common name. Zenoh matches a rule only when the rule's key expression includes the
    message's, so a subscription to a wider pattern (``dmo/**``) is refused as a whole, not narrowed.
    """
    prefix = Keys(run_id).prefix
    check_names(agents, readers, routers)
    if routers and not tls:
        raise AuthError("routers relay for one another only over mutual TLS: a router could not tell the router it "
                        "connected to from a client; make the credentials with TLS (dmosim credentials --tls)")
    alive = f"{prefix}/alive"
    rules: list[dict] = []
    subjects: list[dict] = []
    policies: list[dict] = []

    def grant(subject: str, *grants: tuple[str, Iterable[str], Iterable[str], Iterable[str]],
              user: bool = True) -> None:
        ids = []
        for what, flows, messages, keys in grants:
            ids.append(f"{subject}:{what}")
            rules.append({"id": ids[-1], "permission": "allow", "flows": list(flows), "messages": list(messages),
                          "key_exprs": list(keys)})
        subject_rule = {"id": subject, "usernames": [subject]} if user else {"id": subject}
        if tls:
            subject_rule["cert_common_names"] = [subject]  # both must match: the password and the certificate
        subjects.append(subject_rule)
        policies.append({"id": subject, "rules": ids, "subjects": [subject]})

    everything = ("all", ("ingress", "egress"), _ALL_MESSAGES, (f"{prefix}/**",))
    if dmo_client:
        grant(DMO, everything)
    for router in routers:
        grant(router, everything)
    if routers:
        grant(ROUTER_CERT_NAME, everything, user=False)  # the router this one connected to, by its certificate
    for reader in readers:
        grant(reader,
              ("subscribe", ("ingress",), ("declare_subscriber",), (f"{prefix}/**",)),
              ("receive", ("egress",), ("put",), (f"{prefix}/**",)),
              # a late reader asks the DMO for the traffic it missed (dmo/operator/history.py)
              ("ask", ("ingress",), ("query",), (f"{prefix}/**",)),
              ("answers", ("egress",), ("reply",), (f"{prefix}/**",)),
              ("announce", ("ingress",), ("liveliness_token",), (f"{alive}/{reader}",)),
              ("watch", ("ingress",), ("declare_liveliness_subscriber", "liveliness_query"), (f"{alive}/*",)),
              ("see", ("egress",), ("liveliness_token",), (f"{alive}/*",)))
    for agent in agents:
        hears = ([f"{prefix}/dmo/{topic}" for topic in PUBLIC_TOPICS]
                 + [f"{prefix}/dmo/{topic}/{agent}" for topic in PRIVATE_TOPICS])
        grant(agent,
              ("publish", ("ingress",), ("put",), [f"{prefix}/agent/{agent}/{topic}" for topic in AGENT_TOPICS]),
              ("subscribe", ("ingress",), ("declare_subscriber",), hears),
              ("receive", ("egress",), ("put",), hears),
              # ... and may ask the DMO for the latest of what it hears (e.g. the clock, when it joins late)
              ("ask", ("ingress",), ("query",), hears),
              ("answers", ("egress",), ("reply",), hears),
              # A client sends a put only where it knows a subscriber: it must learn of the DMO's agent/**.
              ("route", ("egress",), ("declare_subscriber",), (f"{prefix}/agent/**",)),
              ("announce", ("ingress",), ("liveliness_token",), (f"{alive}/{agent}",)),
              ("watch", ("ingress",), ("declare_liveliness_subscriber", "liveliness_query"), (f"{alive}/*",)),
              ("see", ("egress",), ("liveliness_token",), (f"{alive}/{DMO}", f"{alive}/{agent}")))
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def check_names(agents: Sequence[str], readers: Sequence[str], routers: Sequence[str] = ()) -> None:
    for agent in agents:
        try:
            check_agent_id(agent)
        except ValueError as exc:
            raise AuthError(str(exc)) from None
    for what, names in (("reader", readers), ("router", routers)):
        for name in names:
            if not is_name(name) or name.lower() == DMO or name in agents:
                raise AuthError(f"{what} name {name!r} must match {NAME_PATTERN} and differ from the DMO and agents")
    names = [DMO, *readers, *routers, *agents]
    if len({n.lower() for n in names}) != len(names):
        raise AuthError("process names must be unique (case-insensitively)")


# --- Zenoh settings ----------------------------------------------------------------------------------------------

Settings = tuple[tuple[str, str], ...]  # (config key, JSON5 value) pairs for BusConfig.overrides


def router_settings(auth_dir: str | os.PathLike, run_id: str | None = None) -> Settings:
    """The router's side: require a user and password from its dictionary, enforce the run's rules and, when the
    directory has TLS material, serve ``tls/`` endpoints with mutual TLS. ``run_id`` checks the rules are this run's."""
    bundle = Path(auth_dir)
    users, acl_file = bundle / USERS_FILE, bundle / ACL_FILE
    for path in (users, acl_file):
        if not path.is_file():
            raise AuthError(f"{path} does not exist: give the directory `dmosim credentials` made (or `dmosim run` "
                            "made in its logs)")
    try:
        acl = json.loads(acl_file.read_text())
        keys = [k for rule in acl["rules"] for k in rule["key_exprs"]]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise AuthError(f"{acl_file} is not a dmosim access-control file: {exc}") from None
    if run_id is not None:
        prefix = Keys(run_id).prefix + "/"
        if not keys or not all(k.startswith(prefix) for k in keys):
            raise AuthError(f"{acl_file} was made for another run, not {run_id!r}")
    settings = [("transport/auth/usrpwd/dictionary_file", json.dumps(str(users.resolve()))),
                ("access_control", json.dumps(acl))]
    if (bundle / CA_FILE).is_file():
        settings += _tls(bundle, "listen")
    return tuple(settings)


def client_settings(user: str, password_file: str | os.PathLike, tls_bundle: str | os.PathLike | None = None) -> Settings:
    """A client's side: log in as ``user`` with the password in the file and, with a TLS bundle directory (CA,
    certificate, key), trust only that CA and present the certificate (mutual TLS)."""
    password = read_password(password_file)
    settings = [("transport/auth/usrpwd/user", json.dumps(user)),
                ("transport/auth/usrpwd/password", json.dumps(password))]
    if tls_bundle is not None:
        settings += _tls(Path(tls_bundle), "connect")
    return tuple(settings)


def bundle_settings(auth_dir: str | os.PathLike, name: str) -> Settings:
    """A client's settings from its bundle ``auth_dir/<name>``: its password and, if there, its TLS material."""
    bundle = Path(auth_dir) / name
    if not (bundle / PASSWORD_FILE).is_file():
        raise AuthError(f"{bundle / PASSWORD_FILE} does not exist: {auth_dir} has no credentials for {name!r}")
    return client_settings(name, bundle / PASSWORD_FILE, bundle if (bundle / CA_FILE).is_file() else None)


def read_password(path: str | os.PathLike) -> str:
    try:
        password = Path(path).read_text().strip()
    except OSError as exc:
        raise AuthError(f"cannot read password file {path}: {exc.strerror or exc}") from None
    if not password or "\n" in password:
        raise AuthError(f"password file {path} must hold one non-empty line")
    return password


def _tls(bundle: Path, side: str) -> list[tuple[str, str]]:
    files = {"root_ca_certificate": bundle / CA_FILE, f"{side}_certificate": bundle / CERT_FILE,
             f"{side}_private_key": bundle / KEY_FILE}
    for path in files.values():
        if not path.is_file():
            raise AuthError(f"{path} does not exist: incomplete TLS bundle {bundle}")
    return [(f"transport/link/tls/{key}", json.dumps(str(path.resolve()))) for key, path in files.items()] + [
        ("transport/link/tls/enable_mtls", "true")]


def auth_settings(auth_dir: str | None, user: str | None, password_file: str | None, name: str | None, *,
                  router: bool, run_id: str | None = None, endpoints: Sequence[str] = (),
                  connects: bool = False) -> Settings:
    """The Zenoh settings of an auth directory, or of a user and password file: a router's (``router``) or a
    client's logging in as ``user``, or else ``name``. Nothing given, no settings (an open network). A router that
    ``connects`` to other routers (a mesh, docs/hosts.md) also logs in to them as ``user`` (else ``name``) with its
    bundle, which must hold TLS material (``access_control``). ``endpoints`` (listened on, or connected to) must all be
    ``tls/`` when the credentials hold TLS material, since only a certificate then identifies a process."""
    if router:
        if password_file:
            raise AuthError("a router takes --auth-dir (and --user NAME to log in to the routers it connects to), "
                            "not --password-file")
        if user and not (connects and auth_dir):
            raise AuthError("--user: a router logs in only to the routers it connects to, with its bundle: give "
                            "--connect and --auth-dir")
        settings = router_settings(auth_dir, run_id) if auth_dir else ()
        if connects and auth_dir:
            if not (user or name):
                raise AuthError("a router that connects to other routers logs in to them: give --user NAME, its "
                                "bundle DIR/NAME/ (dmosim credentials --tls --router NAME)")
            if not (Path(auth_dir) / CA_FILE).is_file():
                raise AuthError(f"{auth_dir} holds no TLS certificates: routers relay for one another only over "
                                "mutual TLS (dmosim credentials --tls --router NAME)")
            settings += bundle_settings(auth_dir, user or name)
    else:
        user = user or name
        if password_file:
            if not user:
                raise AuthError("--password-file needs --user")
            settings = client_settings(user, password_file)
        elif auth_dir:
            if not user:
                raise AuthError("--auth-dir needs --user for this command")
            settings = bundle_settings(auth_dir, user)
        else:
            settings = ()
    if any(key.startswith("transport/link/tls/") for key, _ in settings):
        plain = [e for e in endpoints if not e.startswith("tls/")]
        if plain:
            raise AuthError(f"{auth_dir} holds TLS certificates, so every endpoint must be tls/..., not {plain[0]}")
    return settings

__all__ = ["AGENT_TOPICS", "PUBLIC_TOPICS", "READERS", "AuthError", "access_control", "auth_settings",
           "bundle_settings", "check_names", "client_settings", "read_password", "router_settings"]
