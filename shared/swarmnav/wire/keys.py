"""Zenoh key expressions of the swarm — the ONLY place they are built and parsed.

Grammar (``<run>`` is the run id, ``<id>`` a UAV id as a decimal integer >= 1)::

    swarmnav/<run>/meta                      queryable (sensor-sim): DatasetMeta of the run
    swarmnav/<run>/clock                     sensor-sim -> all: epoch k starts (participants), or done
    swarmnav/<run>/uav/<id>/init             queryable (sensor-sim): initial knowledge of UAV <id>
    swarmnav/<run>/uav/<id>/input            sensor-sim -> node <id>: all of epoch k's inputs in one binary
                                             frame (IMU batch, GNSS fix, UWB ranges, az/el, participants)
    swarmnav/<run>/uav/<id>/state            node <id> -> peers: state of (epoch k, round r);
                                             also a queryable: latest state / short history
    swarmnav/<run>/uav/<id>/estimate         node <id> -> monitor, sensor-sim: final estimate of epoch k
    swarmnav/<run>/uav/<id>/links            node <id> -> monitor: link classifications of epoch k
    swarmnav/<run>/truth/<id>                sensor-sim -> monitor ONLY: truth of UAV <id> (nodes never read)
    swarmnav/<run>/alive/<service>/<id>      liveliness token (service in SERVICES; id = UAV id or 0)

``<run>`` must be one chunk of ``[A-Za-z0-9_.-]``: no ``/``, no ``*``, ``$``, ``?``, ``#``.
Wildcard subscriptions (``uav/*/state``) are also built here. :func:`parse` inverts every
concrete key into a :class:`Key` so ``parse(build(...)) == ...`` (tests/test_keys.py).
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass

ROOT = "swarmnav"
SENSOR_TOPICS = ("input",)
NODE_TOPICS = ("state", "estimate", "links")
UAV_TOPICS = SENSOR_TOPICS + NODE_TOPICS + ("init",)
SERVICES = ("uav", "sensor_sim", "monitor", "launcher")

_RUN_RE = re.compile(r"^[A-Za-z0-9_.\-]+$")


class KeyError_(ValueError):
    """A key expression that does not follow the grammar."""


def _run(run: str) -> str:
    if not isinstance(run, str) or not _RUN_RE.match(run):
        raise KeyError_(f"invalid run id {run!r}: use letters, digits, '_', '.', '-'")
    return run


def _id(uav: int) -> str:
    if isinstance(uav, bool) or not isinstance(uav, int) or uav < 0:
        raise KeyError_(f"invalid id {uav!r}: must be an int >= 0")
    return str(uav)


@dataclass(frozen=True)
class Key:
    """A parsed key: kind in {'uav', 'truth', 'alive', 'meta', 'clock'}."""

    run: str
    kind: str
    topic: str | None = None  # uav: one of UAV_TOPICS; alive: the service name
    uav: int | None = None


# -- builders --------------------------------------------------------------------------------


def uav(run: str, uav_id: int, topic: str) -> str:
    if topic not in UAV_TOPICS:
        raise KeyError_(f"unknown UAV topic {topic!r}; expected one of {UAV_TOPICS}")
    if uav_id < 1:
        raise KeyError_(f"UAV ids start at 1, got {uav_id}")
    return f"{ROOT}/{_run(run)}/uav/{_id(uav_id)}/{topic}"


def uav_all(run: str, topic: str) -> str:
    """Wildcard over every UAV of one topic, e.g. ``swarmnav/r/uav/*/state``."""
    if topic not in UAV_TOPICS:
        raise KeyError_(f"unknown UAV topic {topic!r}")
    return f"{ROOT}/{_run(run)}/uav/*/{topic}"


def truth(run: str, uav_id: int) -> str:
    return f"{ROOT}/{_run(run)}/truth/{_id(uav_id)}"


def truth_all(run: str) -> str:
    return f"{ROOT}/{_run(run)}/truth/*"


def meta(run: str) -> str:
    return f"{ROOT}/{_run(run)}/meta"


def clock(run: str) -> str:
    return f"{ROOT}/{_run(run)}/clock"


def uav_any(run: str, uav_id: int) -> str:
    """Every topic of one UAV, e.g. ``swarmnav/r/uav/3/*`` (a node's own inbox)."""
    if uav_id < 1:
        raise KeyError_(f"UAV ids start at 1, got {uav_id}")
    return f"{ROOT}/{_run(run)}/uav/{_id(uav_id)}/*"


def alive(run: str, service: str, ident: int = 0) -> str:
    if service not in SERVICES:
        raise KeyError_(f"unknown service {service!r}; expected one of {SERVICES}")
    return f"{ROOT}/{_run(run)}/alive/{service}/{_id(ident)}"


def alive_all(run: str, service: str | None = None) -> str:
    if service is None:
        return f"{ROOT}/{_run(run)}/alive/**"
    if service not in SERVICES:
        raise KeyError_(f"unknown service {service!r}")
    return f"{ROOT}/{_run(run)}/alive/{service}/*"


def everything(run: str) -> str:
    return f"{ROOT}/{_run(run)}/**"


# -- parser ----------------------------------------------------------------------------------


@functools.lru_cache(maxsize=4096)
def _parse_cached(key: str) -> Key:
    return _parse(key)


def parse(key) -> Key:
    """Parse a concrete key of the grammar (cached); raises KeyError_ on anything else."""
    return _parse_cached(str(key))


def _parse(key: str) -> Key:
    """Parse a concrete key of the grammar; raises KeyError_ on anything else."""
    parts = str(key).split("/")
    if len(parts) < 3 or parts[0] != ROOT or not _RUN_RE.match(parts[1]):
        raise KeyError_(f"not a swarmnav key: {key!r}")
    run, rest = parts[1], parts[2:]

    def num(s: str) -> int:
        if not s.isdigit() or (len(s) > 1 and s[0] == "0"):
            raise KeyError_(f"bad id {s!r} in {key!r}")
        return int(s)

    if rest == ["meta"]:
        return Key(run, "meta")
    if rest == ["clock"]:
        return Key(run, "clock")
    if len(rest) == 3 and rest[0] == "uav" and rest[2] in UAV_TOPICS:
        u = num(rest[1])
        if u < 1:
            raise KeyError_(f"UAV ids start at 1: {key!r}")
        return Key(run, "uav", rest[2], u)
    if len(rest) == 2 and rest[0] == "truth":
        return Key(run, "truth", None, num(rest[1]))
    if len(rest) == 3 and rest[0] == "alive" and rest[1] in SERVICES:
        return Key(run, "alive", rest[1], num(rest[2]))
    raise KeyError_(f"key {key!r} does not follow the swarmnav grammar")


def build(k: Key) -> str:
    """Inverse of :func:`parse`."""
    if k.kind == "meta":
        return meta(k.run)
    if k.kind == "clock":
        return clock(k.run)
    if k.kind == "uav":
        return uav(k.run, k.uav, k.topic)
    if k.kind == "truth":
        return truth(k.run, k.uav)
    if k.kind == "alive":
        return alive(k.run, k.topic, k.uav)
    raise KeyError_(f"unknown key kind {k.kind!r}")
