"""`swarmnav keys`: identities for a multi-host deployment (mutual TLS + the router's ACL).

Writes, for one run id and a list of UAVs, a fresh certificate authority's certificate, the
router's config (TLS listen endpoint, mutual TLS required, the ACL generated from
swarmnav.wire.keys) and one complete Zenoh client config per principal (``uav-<id>``,
``sensor-sim``, ``monitor``, ``launcher``), every file mode 0600 (see services/runtime/security.py and
docs/deployment.md "Several hosts"). Copy each principal's file to the host that runs it, and only
that file.
"""

from __future__ import annotations

from pathlib import Path

HELP = "make the identities (mTLS certificates + router ACL) of a multi-host deployment"
DESCRIPTION = HELP + """

example:
  swarmnav keys --out keys/demo --run demo --uavs 1-5 --router-host 10.0.0.1
  python -m deploy.router --config keys/demo/router.json5
  python -m services.uav_node --router tls/10.0.0.1:7447 --run demo --uav 3 --zenoh-config keys/demo/uav-3.json5
"""


def add_arguments(p):
    p.add_argument("--out", required=True, help="directory for the identities (created, mode 0700; must be new or empty)")
    p.add_argument("--uavs", required=True, help="UAV ids: ranges and lists, e.g. 1-18 or 1,3,7")
    p.add_argument("--run", default="demo", help="the run id every service will be started with (--run); default demo")
    p.add_argument("--router-host", default="127.0.0.1",
                   help="address the services reach the router at (IP or DNS name; in its certificate)")
    p.add_argument("--port", type=int, default=7447, help="router TLS port (default 7447)")


def check_host(host: str) -> None:
    """An IP address or a DNS name (RFC 1123 labels); a dotted quad must be a valid IPv4 address."""
    import ipaddress
    import re

    from swarmnav.errors import SwarmnavError

    try:
        ipaddress.ip_address(host)
        return
    except ValueError:
        pass
    label = r"(?!-)[A-Za-z0-9-]{1,63}(?<!-)"
    if re.fullmatch(r"[0-9.]+", host) or not re.fullmatch(rf"{label}(\.{label})*\.?", host) or len(host) > 253:
        raise SwarmnavError(f"--router-host {host!r}: not an IP address or a DNS name (e.g. 10.0.0.1 or router.local)")


def run(args) -> int:
    from services.runtime.security import make_identities
    from swarmnav.errors import SwarmnavError
    from services.commands.evaluate import parse_seeds
    from swarmnav.wire import keys as K

    try:
        uavs = parse_seeds(args.uavs)
    except Exception:
        raise SwarmnavError(f"--uavs {args.uavs!r}: expected ids like 1-18 or 1,3,7") from None
    if not uavs or min(uavs) < 1:
        raise SwarmnavError(f"--uavs {args.uavs!r}: UAV ids start at 1")
    try:
        K.everything(args.run)
    except ValueError as e:
        raise SwarmnavError(f"--run: {e}") from None
    check_host(args.router_host)
    if not 0 < args.port < 65536:
        raise SwarmnavError(f"--port {args.port}: not a TCP port")
    from ._checks import make_out_dir

    out = make_out_dir(args.out)
    if out.exists() and any(out.iterdir()):
        raise SwarmnavError(f"--out {out} is not empty: identities are never overwritten; choose a new directory")
    ep = f"tls/{args.router_host}:{args.port}"
    make_identities(out, args.run, uavs, args.router_host, [f"tls/0.0.0.0:{args.port}" if args.router_host not in ("127.0.0.1", "localhost") else ep], ep)
    print(f"identities of run {args.run!r} for UAVs {uavs} in {out}/ (router endpoint {ep}):")
    for f in sorted(out.iterdir()):
        print(f"  {f.name}")
    print("start the router with: python -m deploy.router --config " + str(out / "router.json5"))
    return 0
