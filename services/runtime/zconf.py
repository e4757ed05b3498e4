"""The one Zenoh config builder of every swarmnav program (router, services, tests).

Zenoh 1.10 practice (docs/deployment.md): listen endpoints explicit (loopback by default), multicast scouting off, a short
link lease so a hung process loses its liveliness token quickly. Services run in ``client`` mode
and connect to the run's router; for several hosts point ``--router`` at the router host (see
deploy/zenoh-router.json5 / deploy/zenoh-client.json5 and the README).
"""

from __future__ import annotations

import json
import socket

LEASE_MS = 3000
DROP_WAIT_US = 20_000
RETRY = {"period_init_ms": 100, "period_max_ms": 500, "period_increase_factor": 2}


def free_port(host: str = "127.0.0.1") -> int:
    """A currently free TCP port on ``host`` (the OS picks it; used once per run)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def _base(conf) -> None:
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "true")
    conf.insert_json5("transport/link/tx/lease", str(LEASE_MS))
    # reconnect within ~0.2 s of a router coming back (default schedule 1/2/4 s: up to 4 s)
    conf.insert_json5("connect/retry", json.dumps(RETRY))
    # DROP publishers (peer states) wait this long for room in a congested link queue before
    # dropping (default 1 ms): 20 processes on 2 cores starve the router for longer than that
    conf.insert_json5("transport/link/tx/queue/congestion_control/drop/wait_before_drop", str(DROP_WAIT_US))
    # no shared-memory transport: every byte goes over the authenticated (TLS) link, and no process
    # maps a 16 MB pool of every peer's (zenoh 1.10 enables it: messages > 3 KB, e.g. a UAV's input)
    conf.insert_json5("transport/shared_memory/enabled", "false")


def router_config(listen: list[str] | None, config_file: str | None = None):
    """Router-mode config: ``listen`` replaces the listen endpoints (None keeps the file's); without
    a file the router connects nowhere (the embedded router of ``swarmnav launch``)."""
    import zenoh

    conf = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    conf.insert_json5("mode", '"router"')
    if listen is not None:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if not config_file:
        conf.insert_json5("connect/endpoints", "[]")
    _base(conf)
    return conf


def client_config(connect: list[str] | str, config_file: str | None = None):
    import zenoh

    conf = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([connect] if isinstance(connect, str) else list(connect)))
    conf.insert_json5("listen/endpoints", "[]")
    _base(conf)
    return conf
