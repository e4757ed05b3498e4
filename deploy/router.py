"""A standalone Zenoh router for multi-host runs: ``python -m deploy.router --config FILE``.

`swarmnav launch` embeds its own router; this is for deployments where the services run on
several hosts (docs/deployment.md). It opens a router-mode session from the json5 file
(default deploy/zenoh-router.json5), optionally replacing its listen endpoints, prints the
endpoints and its zid, and holds it open until SIGINT/SIGTERM, then closes it.
"""

from __future__ import annotations

import argparse
import signal
import threading
from pathlib import Path

DEFAULT = Path(__file__).with_name("zenoh-router.json5")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m deploy.router", description=__doc__.splitlines()[0])
    p.add_argument("--config", default=str(DEFAULT), help="json5 router config (default deploy/zenoh-router.json5)")
    p.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                   help="replace the config's listen endpoints, e.g. tcp/10.0.0.1:7447 (repeatable)")
    p.add_argument("--tag", default=None, help=argparse.SUPPRESS)  # lets tests find their process
    a = p.parse_args(argv)
    import zenoh

    from services.runtime.zconf import router_config

    conf = router_config(a.listen or None, a.config)  # the file's settings + the shared base (zconf._base)
    stop = threading.Event()
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, lambda *_: stop.set())
    with zenoh.open(conf) as session:
        print(f"zenoh router {session.zid()} listening on {conf.get_json('listen/endpoints')}", flush=True)
        while not stop.wait(1.0):
            pass
    print("router closed", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
