"""The router's access-control list of a run, generated from :mod:`swarmnav.wire.keys` (pure: a dict).

Zenoh's ``access_control`` (default deny) is enforced by the router on every client session. Each
principal is identified by the common name of its client certificate (mutual TLS, services/runtime/security.py)
or by its usrpwd user name: ``uav-<id>``, ``sensor-sim``, ``monitor``, ``launcher``.

Flows are the router's: *ingress* is what a principal sends to the router (its puts, declarations,
queries, replies), *egress* what the router forwards to it. Who may do what (R = ``swarmnav/<run>``):

==========  =====================================================  ==============================================
principal   may write (ingress put / reply / token)                may read (subscribe, get, egress)
==========  =====================================================  ==============================================
uav-i       R/uav/i/{state,estimate,links}; replies on its own      R/uav/i/input, R/uav/i/init, R/meta, R/clock,
            state queryable; token R/alive/uav/i                     peers' R/uav/*/state; liveliness R/alive/**
sensor-sim  R/uav/*/input, R/truth/*, R/clock; replies on R/meta,  R/uav/*/estimate, R/uav/*/state (missing
            R/uav/*/init; token R/alive/sensor_sim/0               estimates after an outage); liveliness
monitor     nothing but its token R/alive/monitor/0                 every key of its run R/**
launcher    R/clock (control); token R/alive/launcher/0             R/clock, liveliness
==========  =====================================================  ==============================================

Nobody but the sensor-sim and the launcher may put the clock (the control channel: epochs, holds,
done); no UAV reads truth or another UAV's input/init. Declarations flow everywhere inside the run
(a writer must see the wildcard subscriptions of its readers, e.g. ``uav/*/state``, or Zenoh sends
nothing): they reveal who listens, never data.
"""

from __future__ import annotations

from . import keys

WRITE = ["put"]
SUBSCRIBE = ["declare_subscriber"]
QUERY = ["query"]
REPLY = ["reply"]
QUERYABLE = ["declare_queryable"]
TOKEN = ["liveliness_token"]
LIVELINESS_READ = ["declare_liveliness_subscriber", "liveliness_query"]


def principals(uavs: list[int]) -> list[str]:
    """Every identity of a run, in a stable order."""
    return [f"uav-{u}" for u in sorted(uavs)] + ["sensor-sim", "monitor", "launcher"]


def _rule(rid: str, messages: list[str], flow: str, key_exprs: list[str]) -> dict:
    return {"id": rid, "messages": list(messages), "flows": [flow], "permission": "allow", "key_exprs": sorted(set(key_exprs))}


def grants(run: str, principal: str) -> list[dict]:
    """The rules of one principal (ids unique per principal)."""
    R = keys.everything(run)  # swarmnav/<run>/**
    alive_all = keys.alive_all(run)
    common = [  # declarations and liveliness flow everywhere inside the run; nothing else
        ("decl_out", SUBSCRIBE + QUERYABLE, "egress", [R]),
        ("liveliness_read", LIVELINESS_READ, "ingress", [alive_all]),
        ("liveliness_out", TOKEN + LIVELINESS_READ, "egress", [alive_all]),
    ]
    if principal.startswith("uav-"):
        u = int(principal[4:])
        own = [keys.uav(run, u, t) for t in keys.NODE_TOPICS]
        peers_state = keys.uav_all(run, "state")
        mine = [
            ("put", WRITE, "ingress", own),
            ("token", TOKEN, "ingress", [keys.alive(run, "uav", u)]),
            ("queryable", QUERYABLE, "ingress", [keys.uav(run, u, "state")]),
            # queries reach its queryable as sent: exact (uav/i/state?k=..) or the peers' wildcard (bootstrap)
            ("queried", QUERY, "egress", [keys.uav(run, u, "state"), peers_state]),
            ("reply", REPLY, "ingress", [keys.uav(run, u, "state")]),
            ("subscribe", SUBSCRIBE, "ingress", [keys.uav(run, u, "input"), peers_state, keys.clock(run)]),
            ("receive", WRITE, "egress", [keys.uav(run, u, "input"), peers_state, keys.clock(run)]),
            ("get", QUERY, "ingress", [keys.meta(run), keys.uav(run, u, "init"), peers_state]),
            ("answers", REPLY, "egress", [keys.meta(run), keys.uav(run, u, "init"), peers_state]),
        ]
    elif principal == "sensor-sim":
        served = [keys.meta(run), keys.uav_all(run, "init")]
        mine = [
            ("put", WRITE, "ingress", [keys.uav_all(run, "input"), keys.truth_all(run), keys.clock(run)]),
            ("token", TOKEN, "ingress", [keys.alive(run, "sensor_sim", 0)]),
            ("queryable", QUERYABLE, "ingress", served),
            ("queried", QUERY, "egress", served),
            ("reply", REPLY, "ingress", served),
            ("subscribe", SUBSCRIBE, "ingress", [keys.uav_all(run, "estimate")]),
            ("receive", WRITE, "egress", [keys.uav_all(run, "estimate")]),
            ("get", QUERY, "ingress", [keys.uav_all(run, "state")]),
            ("answers", REPLY, "egress", [keys.uav_all(run, "state")]),
        ]
    elif principal == "monitor":
        mine = [
            ("token", TOKEN, "ingress", [keys.alive(run, "monitor", 0)]),
            ("subscribe", SUBSCRIBE, "ingress", [R]),
            ("receive", WRITE, "egress", [R]),
            ("get", QUERY, "ingress", [keys.uav_all(run, "state"), keys.meta(run)]),
            ("answers", REPLY, "egress", [keys.uav_all(run, "state"), keys.meta(run)]),
        ]
    elif principal == "launcher":
        mine = [
            ("put", WRITE, "ingress", [keys.clock(run)]),
            ("token", TOKEN, "ingress", [keys.alive(run, "launcher", 0)]),
            ("subscribe", SUBSCRIBE, "ingress", [keys.clock(run)]),
            ("receive", WRITE, "egress", [keys.clock(run)]),
        ]
    else:
        raise ValueError(f"unknown principal {principal!r}")
    tag = principal.replace("-", "_")
    return [_rule(f"{tag}.{name}", msgs, flow, kx) for name, msgs, flow, kx in common + mine]


def access_control(run: str, uavs: list[int], subject_key: str = "cert_common_names") -> dict:
    """The router's ``access_control`` section: default deny, one subject per principal identified
    by ``subject_key`` (``cert_common_names`` for mutual TLS, ``usernames`` for usrpwd)."""
    rules, subjects, policies = [], [], []
    for p in principals(uavs):
        g = grants(run, p)
        rules += g
        sid = f"subject.{p.replace('-', '_')}"
        subjects.append({"id": sid, subject_key: [p]})
        policies.append({"id": f"policy.{p.replace('-', '_')}", "rules": [r["id"] for r in g], "subjects": [sid]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}
