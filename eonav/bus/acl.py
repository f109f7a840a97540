"""Access control for the bus: who may put, subscribe, query and declare liveliness on which eonav key.

The zenoh router enforces it (zenoh's ``access_control`` with user/password authentication, docs/zenoh.md "Access
control"): every session authenticates with its own user, and ``default_permission: "deny"`` leaves only what is
granted here. A pipeline service's user is its service name; what it may do follows from its module:

- the camera ingest puts frames, the MAVLink ingest navigation, the sync posed frames, the locator range maps, the
  obstacle service obstacle lists and tracks; each subscribes only to its inputs;
- every service puts its own health, declares its own liveliness token and answers its own config queryable;
- ``operator`` subscribes to everything and is the only user that may query the config queryables;
- ``guidance`` subscribes to obstacles and health and watches liveliness;
- ``router``: the link between two hosts' routers (each router filters its own sessions).

Every user is told of the subscribers and queryables on ``eonav/**`` (egress declarations), so that a publisher
sees who matches. ACL checks a message's key by inclusion in a rule's key: wildcard subscriptions and queries are
written so that they are included (``eonav/*/config/*`` for the config queryables).

:func:`write_acl_dir` writes a users file with fresh random passwords, the router's config and one session config
per user (``eonav acl init``; ``eonav run --secure``). No zenoh import here: plain dicts and files.
"""
from __future__ import annotations

import json
import os
import secrets
from dataclasses import dataclass
from pathlib import Path

from eonav import InputError
from eonav.bus.keys import ROOT, check_chunk

ROUTER_USER = "router"
OPERATOR_USER = "operator"
GUIDANCE_USER = "guidance"
USERS_FILE = "zenoh-users.txt"
ROUTERS_FILE = "zenoh-routers.txt"
ROUTER_FILE = "zenoh-router.json5"
DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"

# what each pipeline module produces and consumes (keys below eonav/<vehicle>/, docs/bus.md)
ROLES = {
    "camera_ingest": {"put": ["camera/*/frame"], "sub": []},
    "mavlink_ingest": {"put": ["nav/**"], "sub": []},
    "sync": {"put": ["posed/*/frame"], "sub": ["camera/*/frame", "nav/**"]},
    "locator": {"put": ["range/*"], "sub": ["posed/*/frame"]},
    "obstacles": {"put": ["obstacles/**"], "sub": ["range/*", "nav/**"]},
}
# the pipeline of one host as deploy/ names it: service name -> module
DEFAULT_SERVICES = {"camera_nose": "camera_ingest", "mavlink": "mavlink_ingest", "sync": "sync",
                    "locator": "locator", "obstacles": "obstacles"}
# deploy/zenoh/router-acl.example.json5 and users.example.txt: the generator's output with these
PLACEHOLDER = "<written by eonav acl init>"
EXAMPLE_LISTEN = ("tcp/127.0.0.1:7447", "tcp/192.0.2.10:7447")
EXAMPLE_CONNECT = ("tcp/192.0.2.11:7447",)
EXAMPLE_ZIDS = ("<zid of host a>", "<zid of host b>")
ALL_MESSAGES = ["put", "delete", "declare_subscriber", "query", "declare_queryable", "reply", "liveliness_token",
                "declare_liveliness_subscriber", "liveliness_query"]


def _k(rel: str) -> str:
    """A key below every vehicle; ``**`` is all of ``eonav/**`` (a subscription to ``eonav/**`` is not included
    in ``eonav/*/**``)."""
    return f"{ROOT}/**" if rel == "**" else f"{ROOT}/*/{rel}"


def _rule(rule_id: str, flow: str, messages: list, rel_keys: list) -> dict:
    return {"id": rule_id, "permission": "allow", "flows": [flow], "messages": messages,
            "key_exprs": [_k(k) for k in rel_keys]}


@dataclass
class Grant:
    """What one user may do: put ``put`` keys, subscribe ``sub``, answer queries on ``serve``, query ``query``,
    declare liveliness tokens on ``token`` and watch tokens on ``watch`` (keys below ``eonav/<vehicle>/``)."""
    put: tuple = ()
    sub: tuple = ()
    serve: tuple = ()
    query: tuple = ()
    token: tuple = ()
    watch: tuple = ()

    def rules(self, user: str) -> list[dict]:
        r = [_rule(f"{user}-learn", "egress", ["declare_subscriber", "declare_queryable",
                                               "declare_liveliness_subscriber"], ["**"])]
        if self.put:
            r.append(_rule(f"{user}-put", "ingress", ["put"], list(self.put)))
        if self.sub:
            r.append(_rule(f"{user}-sub", "ingress", ["declare_subscriber"], list(self.sub)))
            r.append(_rule(f"{user}-sub-in", "egress", ["put"], list(self.sub)))
        if self.serve:
            r.append(_rule(f"{user}-serve", "ingress", ["declare_queryable"], list(self.serve)))
            # a reply is checked against the query's key: the operator asks eonav/<v>/config/* too
            r.append(_rule(f"{user}-serve-reply", "ingress", ["reply"], ["config/*"]))
            r.append(_rule(f"{user}-serve-query", "egress", ["query"], ["config/*"]))
        if self.query:
            r.append(_rule(f"{user}-query", "ingress", ["query"], list(self.query)))
            r.append(_rule(f"{user}-query-reply", "egress", ["reply"], list(self.query)))
        if self.token:
            r.append(_rule(f"{user}-token", "ingress", ["liveliness_token"], list(self.token)))
        if self.watch:
            r.append(_rule(f"{user}-watch", "ingress", ["declare_liveliness_subscriber", "liveliness_query"],
                           list(self.watch)))
            r.append(_rule(f"{user}-watch-in", "egress", ["liveliness_token"], list(self.watch)))
        return r


def service_grant(name: str, module: str) -> Grant:
    """A pipeline service's grant: its module's role plus its own health, liveliness token and config."""
    short = module.rsplit(".", 1)[-1]
    role = ROLES.get(short)
    if role is None:
        raise InputError(f"access control: service {name!r} runs module {module!r}, which has no role "
                         f"(known: {', '.join(sorted(ROLES))})")
    check_chunk(name, "service name")
    return Grant(put=(*role["put"], f"health/{name}"), sub=tuple(role["sub"]), serve=(f"config/{name}",),
                 token=(f"alive/{name}",))


def grants(services: dict) -> dict[str, Grant]:
    """Every user of a pipeline: ``services`` (name -> module) plus operator and guidance."""
    out = {name: service_grant(name, module) for name, module in services.items()}
    for reserved in (ROUTER_USER, OPERATOR_USER, GUIDANCE_USER):
        if reserved in out:
            raise InputError(f"access control: {reserved!r} is a reserved user; give the service another name")
    out[OPERATOR_USER] = Grant(sub=("**",), query=("config/**",), watch=("alive/**",))
    out[GUIDANCE_USER] = Grant(sub=("obstacles/**", "health/*"), watch=("alive/**",))
    return out


def access_control(services: dict, router_zids=()) -> dict:
    """The router's ``access_control`` block for a pipeline (``services``: name -> module). ``router_zids``: the
    zenoh ids of every host's router: user/password authenticates the side that connects only, so the router
    that dialled the other one knows it by its zid (docs/zenoh.md, "Access control")."""
    rules, subjects, policies = [], [], []
    for user, g in grants(services).items():
        r = g.rules(user)
        rules += r
        subjects.append({"id": user, "usernames": [user]})
        policies.append({"id": user, "rules": [x["id"] for x in r], "subjects": [user]})
    # the other host's router relays what its own sessions were allowed to send
    rules.append({"id": "router-relay", "permission": "allow", "flows": ["ingress", "egress"],
                  "messages": ALL_MESSAGES, "key_exprs": [f"{ROOT}/**"]})
    subjects.append({"id": ROUTER_USER, "usernames": [ROUTER_USER]})
    router_subjects = [ROUTER_USER]
    if router_zids:
        subjects.append({"id": "router-zids", "zids": sorted(router_zids)})
        router_subjects.append("router-zids")
    policies.append({"id": ROUTER_USER, "rules": ["router-relay"], "subjects": router_subjects})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def router_config(services: dict, users_file: str, router_password: str, listen=(DEFAULT_ENDPOINT,),
                  connect=(), tls: dict | None = None, zid: str | None = None, router_zids=()) -> dict:
    """A router config (zenohd or ``python -m eonav.bus.router``) that authenticates every session against
    ``users_file`` and enforces :func:`access_control`. ``tls``: {"ca", "cert", "key"} file paths for ``tls/``
    endpoints (the router's certificate and key, the CA that signed the other routers' certificates). ``zid``: this
    router's zenoh id; ``router_zids``: every host router's (see :func:`access_control`)."""
    cfg = {"mode": "router", **({"id": zid} if zid else {}), "listen": {"endpoints": list(listen)},
           "scouting": {"multicast": {"enabled": False}},
           "transport": {"auth": {"usrpwd": {"user": ROUTER_USER, "password": router_password,
                                              "dictionary_file": str(users_file)}}},
           "access_control": access_control(services, router_zids)}
    if connect:
        cfg["connect"] = {"endpoints": list(connect), "exit_on_failure": False,
                          "retry": {"period_init_ms": 500, "period_max_ms": 5000, "period_increase_factor": 2}}
    if tls:
        cfg["transport"]["link"] = {"tls": {"root_ca_certificate": str(tls["ca"]),
                                            "listen_certificate": str(tls["cert"]),
                                            "listen_private_key": str(tls["key"])}}
    return cfg


def session_config(user: str, password: str, connect=(DEFAULT_ENDPOINT,), tls: dict | None = None) -> dict:
    """A service's (or a tool's) session: a client of its host's router, so every sample passes the router's
    access control (peers would talk to each other directly, past it). It waits for the router (a service may
    start first at boot) and reconnects when the router restarts. ``tls``: {"ca"} to verify the router."""
    cfg = {"mode": "client", "connect": {"endpoints": list(connect), "timeout_ms": -1, "exit_on_failure": False},
            "scouting": {"multicast": {"enabled": False}},
            "transport": {"shared_memory": {"enabled": False},
                          "auth": {"usrpwd": {"user": user, "password": password}}}}
    if tls:
        cfg["transport"]["link"] = {"tls": {"root_ca_certificate": str(tls["ca"])}}
    return cfg


def session_file(acl_dir, user: str) -> Path:
    return Path(acl_dir) / f"zenoh-{user}.json5"


def new_zid() -> str:
    """A random zenoh id: 16 bytes in hex, no leading zero (zenoh refuses one)."""
    while (z := secrets.token_hex(16))[0] == "0":
        pass
    return z


def _write_private(path: Path, text: str) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.chmod(path, 0o600)


def _dump(header: str, cfg: dict) -> str:
    """JSON (valid JSON5) under a comment header; each ACL rule, subject and policy on one line."""
    ac = cfg.get("access_control")
    body = dict(cfg, access_control={k: (f"@{k}@" if isinstance(v, list) else v) for k, v in ac.items()}) if ac \
        else cfg
    text = json.dumps(body, indent=2)
    for k, v in (ac or {}).items():
        if isinstance(v, list):
            items = ",\n".join("      " + json.dumps(x) for x in v)
            text = text.replace(f'"@{k}@"', "[\n" + items + "\n    ]")
    return "".join(f"// {line}\n" for line in header.splitlines()) + text + "\n"


def router_text(services: dict, users_file: str, router_password: str, listen=(DEFAULT_ENDPOINT,), connect=(),
                tls: dict | None = None, zid: str | None = None, router_zids=()) -> str:
    """The router config file as :func:`write_acl_dir` writes it (deploy/zenoh/router-acl.example.json5 is this
    with placeholder secrets)."""
    return _dump("zenoh router with access control, written by `eonav acl init` (eonav.bus.acl; docs/zenoh.md).\n"
                 "Users and passwords: the dictionary_file; each service connects with its own zenoh-<user>.json5.",
                 router_config(services, users_file, router_password, listen, connect, tls, zid, router_zids))


def read_users(acl_dir, name: str = USERS_FILE) -> dict[str, str]:
    """user -> password from ``<acl_dir>/zenoh-users.txt`` (``name:password`` lines); with ``name``
    ROUTERS_FILE: host -> router zid."""
    path = Path(acl_dir) / name
    if not path.is_file():
        raise InputError(f"access control: {path}: no such file (eonav acl init {acl_dir})")
    users = {}
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        user, sep, pw = line.partition(":")
        if not sep or not user or not pw:
            raise InputError(f"access control: {path}:{n}: expected name:password")
        users[user] = pw
    return users


def write_acl_dir(acl_dir, services: dict | None = None, *, listen=(DEFAULT_ENDPOINT,), connect=(),
                  session_connect=(DEFAULT_ENDPOINT,), users_file: str | None = None,
                  keep_passwords: bool = True, tls: dict | None = None, host: str = "a",
                  hosts=()) -> dict[str, str]:
    """Write the users file, the router config and one session config per user into ``acl_dir``; returns
    user -> password. Passwords already in the users file are kept (``keep_passwords``): copy the same file to
    every host of a vehicle, so that the routers' link and every user authenticate everywhere. ``users_file``:
    the path the router config names (default: the file in ``acl_dir``, absolute). ``tls``: see
    :func:`router_config` (the endpoints must then be ``tls/...``). ``host``: this host's name; ``hosts``: the
    others: each host's router gets a random zid, kept in ``zenoh-routers.txt`` (copy it with the users file)."""
    services = dict(DEFAULT_SERVICES if services is None else services)
    d = Path(acl_dir)
    d.mkdir(parents=True, exist_ok=True)
    old = read_users(d) if keep_passwords and (d / USERS_FILE).is_file() else {}
    users = [*grants(services), ROUTER_USER]
    pw = {u: old.get(u) or secrets.token_urlsafe(24) for u in users}
    _write_private(d / USERS_FILE, "".join(f"{u}:{pw[u]}\n" for u in users))
    uf = users_file or str((d / USERS_FILE).resolve())
    old_zids = read_users(d, ROUTERS_FILE) if (d / ROUTERS_FILE).is_file() else {}
    zids = dict(old_zids)
    for h in (host, *hosts):
        zids.setdefault(check_chunk(h, "host name"), new_zid())
    _write_private(d / ROUTERS_FILE, "".join(f"{h}:{z}\n" for h, z in zids.items()))
    _write_private(d / ROUTER_FILE, router_text(services, uf, pw[ROUTER_USER], listen, connect, tls, zids[host],
                                                sorted(zids.values())))
    for u in users:
        if u == ROUTER_USER:
            continue
        _write_private(session_file(d, u), _dump(
            f"zenoh session of user {u!r} (eonav acl init): a client of this host's router.",
            session_config(u, pw[u], session_connect, tls)))
    return pw
