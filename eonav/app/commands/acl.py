"""``eonav acl init DIR``: the access-control files of one vehicle (``eonav.bus.acl``): a users file with fresh random
passwords (kept when it exists), the router config that enforces the ACL, and one session config per user
(``zenoh-<user>.json5``). Run it on one host, copy its users and routers files to the others and run it there with
their ``--host`` (deploy/README.md)."""
from __future__ import annotations

import argparse
import json


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="acl_command", metavar="ACTION", required=True)
    init = sub.add_parser("init", help="write the users file, router config and session configs into DIR")
    init.add_argument("dir", metavar="DIR", help="output directory, e.g. /etc/eonav (files are mode 0600)")
    init.add_argument("--service", action="append", default=[], metavar="NAME=MODULE",
                      help="a service of the vehicle (repeatable; default camera_nose=camera_ingest, "
                           "mavlink=mavlink_ingest, sync=sync, locator=locator, obstacles=obstacles)")
    init.add_argument("--camera-ids", default=None, metavar="IDS",
                      help="comma-separated camera ids: shorthand for --service camera_ID=camera_ingest each (with the "
                           "other default services)")
    init.add_argument("--listen", default=None, metavar="ENDPOINTS",
                      help="comma-separated router listen endpoints (default tcp/127.0.0.1:7447; add this host's LAN "
                           "address), as every eonav process's --listen")
    init.add_argument("--connect", default=None, metavar="ENDPOINTS",
                      help="comma-separated endpoints of the other hosts' routers, as every eonav process's --connect")
    init.add_argument("--host", default="a", metavar="NAME",
                      help="this host's name (its router's zenoh id is kept in DIR/zenoh-routers.txt)")
    init.add_argument("--other-host", action="append", default=[], metavar="NAME",
                      help="another host of the vehicle whose router this one trusts (repeatable)")
    init.add_argument("--session-connect", default="tcp/127.0.0.1:7447", metavar="ENDPOINT",
                      help="where the sessions connect: this host's router")
    init.add_argument("--users-file", default=None, metavar="PATH",
                      help="the users file's path as the router sees it (default: DIR/zenoh-users.txt)")
    init.add_argument("--tls-ca", default=None, metavar="PEM", help="TLS: the CA certificate (tls/ endpoints)")
    init.add_argument("--tls-cert", default=None, metavar="PEM", help="TLS: this host's router certificate")
    init.add_argument("--tls-key", default=None, metavar="PEM", help="TLS: this host's router private key")
    init.add_argument("--print", action="store_true", help="print the access_control block as JSON too")


def services_from(args) -> dict | None:
    from eonav import InputError
    from eonav.bus.acl import DEFAULT_SERVICES
    out = {}
    for s in args.service:
        name, sep, module = s.partition("=")
        if not sep or not name or not module:
            raise InputError(f"--service {s!r}: expected NAME=MODULE, e.g. locator=locator")
        out[name] = module
    cams = [c.strip() for c in (args.camera_ids or '').split(',') if c.strip()]
    if cams:
        if not out:
            out = {k: v for k, v in DEFAULT_SERVICES.items() if v != "camera_ingest"}
        out.update({f"camera_{c}": "camera_ingest" for c in cams})
    return out or None


def run(args) -> int:
    from eonav import InputError
    from eonav.bus import acl
    tls_parts = [args.tls_ca, args.tls_cert, args.tls_key]
    if any(tls_parts) and not all(tls_parts):
        raise InputError("--tls-ca, --tls-cert and --tls-key go together")
    tls = {"ca": args.tls_ca, "cert": args.tls_cert, "key": args.tls_key} if all(tls_parts) else None
    services = services_from(args)
    from eonav.bus.session import split_endpoints
    acl.write_acl_dir(args.dir, services, listen=split_endpoints(args.listen) or [acl.DEFAULT_ENDPOINT],
                      connect=split_endpoints(args.connect),
                      session_connect=[args.session_connect], users_file=args.users_file, tls=tls,
                      host=args.host, hosts=args.other_host)
    users = sorted(acl.read_users(args.dir))
    print(f"eonav acl: wrote {args.dir}/{acl.USERS_FILE} (users {', '.join(users)}), {acl.ROUTERS_FILE} (hosts "
          f"{', '.join(sorted(acl.read_users(args.dir, acl.ROUTERS_FILE)))}), {acl.ROUTER_FILE} (host {args.host}) "
          f"and zenoh-<user>.json5 for each user but {acl.ROUTER_USER}")
    if args.print:
        print(json.dumps(acl.access_control(services or acl.DEFAULT_SERVICES), indent=2))
    return 0
