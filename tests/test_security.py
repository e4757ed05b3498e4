"""Secure by default: the per-run identities, the ACL generated from wire/keys.py, and a real router
enforcing both (mutual TLS on loopback, real Zenoh sessions opened from the generated config files).

What a principal may do is asserted by what *arrives* at another principal's session: a Zenoh put
returns OK even when the router drops it, and a session always receives its own puts locally.
"""

import json
import os
import stat
import time

import pytest

from swarmnav.wire import acl, keys

RUN = "rtest"
UAVS = [1, 2, 3, 4]


# -- the ACL as data ------------------------------------------------------------------------------


def _ingress_puts(principal):
    return {k for r in acl.grants(RUN, principal) if "put" in r["messages"] and r["flows"] == ["ingress"] for k in r["key_exprs"]}


def test_acl_writes_per_principal():
    R = f"swarmnav/{RUN}"
    assert _ingress_puts("uav-3") == {f"{R}/uav/3/state", f"{R}/uav/3/estimate", f"{R}/uav/3/links"}
    assert _ingress_puts("sensor-sim") == {f"{R}/uav/*/input", f"{R}/truth/*", f"{R}/clock"}
    assert _ingress_puts("monitor") == set()
    assert _ingress_puts("launcher") == {f"{R}/clock"}
    # only the sensor-sim and the launcher may put the clock (control)
    for p in acl.principals(UAVS):
        assert (f"{R}/clock" in _ingress_puts(p)) == (p in ("sensor-sim", "launcher")), p


def test_acl_uav_never_reads_truth_or_other_uavs_private_keys():
    R = f"swarmnav/{RUN}"
    forbidden = {f"{R}/{k}" for k in ("uav/4/input", "uav/4/init", "uav/*/input", "uav/*/init", "truth/*", "truth/3")}
    for r in acl.grants(RUN, "uav-3"):
        for k in r["key_exprs"]:
            assert "/truth" not in k and k not in forbidden, r
            if k == keys.everything(RUN):  # the whole run only for seeing others' declarations
                assert r["flows"] == ["egress"] and set(r["messages"]) <= {"declare_subscriber", "declare_queryable"}, r


def test_acl_is_generated_for_every_principal_default_deny():
    a = acl.access_control(RUN, UAVS)
    assert a["enabled"] is True and a["default_permission"] == "deny"
    names = [s["cert_common_names"][0] for s in a["subjects"]]
    assert names == ["uav-1", "uav-2", "uav-3", "uav-4", "sensor-sim", "monitor", "launcher"]
    ids = [r["id"] for r in a["rules"]]
    assert len(ids) == len(set(ids))
    assert all(r["permission"] == "allow" for r in a["rules"])
    for pol in a["policies"]:
        assert set(pol["rules"]) <= set(ids)
    # every key an ACL names is a key of this run (built by wire/keys.py)
    for r in a["rules"]:
        for k in r["key_exprs"]:
            assert k.startswith(f"swarmnav/{RUN}/"), k


# -- identities on disk ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def identities(tmp_path_factory):
    from services.runtime.security import make_identities
    from services.runtime.zconf import free_port

    d = tmp_path_factory.mktemp("sec") / "security"
    ep = f"tls/127.0.0.1:{free_port()}"
    make_identities(d, RUN, UAVS, "127.0.0.1", [ep], ep)
    return d, ep


def test_identity_files_private_and_complete(identities):
    d, ep = identities
    assert stat.S_IMODE(os.stat(d).st_mode) == 0o700
    files = sorted(p.name for p in d.iterdir())
    assert files == sorted(["ca.pem", "router.json5"] + [f"{p}.json5" for p in acl.principals(UAVS)])
    for p in d.iterdir():
        assert stat.S_IMODE(os.stat(p).st_mode) == 0o600, p
    assert "PRIVATE KEY" not in (d / "ca.pem").read_text()  # the CA key never reaches the disk
    c = json.loads((d / "uav-3.json5").read_text())
    assert c["mode"] == "client" and c["connect"]["endpoints"] == [ep]
    tls = c["transport"]["link"]["tls"]
    assert tls["enable_mtls"] and tls["connect_certificate_base64"] and tls["connect_private_key_base64"]


# -- a real router enforcing it -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def bus(identities):
    import zenoh

    from services.runtime.zconf import router_config

    d, ep = identities
    router = zenoh.open(router_config(None, str(d / "router.json5")))
    sessions = {}
    try:
        for p in ("uav-3", "uav-4", "monitor", "sensor-sim"):
            sessions[p] = zenoh.open(zenoh.Config.from_file(str(d / f"{p}.json5")))
        for _ in range(50):
            if all(s.info.routers_zid() for s in sessions.values()):
                break
            time.sleep(0.1)
        yield sessions, d, ep
    finally:
        for s in sessions.values():
            s.close()
        router.close()


class Listener:
    def __init__(self, session, key):
        self.got = []
        self.sub = session.declare_subscriber(key, lambda s: self.got.append((str(s.key_expr), s.payload.to_bytes())))

    def keys(self):
        return {k for k, _ in self.got}


def _settle():
    time.sleep(0.6)


def test_router_enforces_who_writes_what(bus):
    s, _, _ = bus
    R = f"swarmnav/{RUN}"
    mon = Listener(s["monitor"], f"{R}/**")
    peer = Listener(s["uav-4"], keys.uav_all(RUN, "state"))
    _settle()
    u3 = s["uav-3"]
    u3.put(f"{R}/uav/3/state", b"own")  # allowed
    for k in ("uav/4/state", "clock", "uav/3/input", "truth/3", "uav/4/estimate"):
        u3.put(f"{R}/{k}", b"forged")  # denied: never arrives
    for k in ("clock", "uav/1/state", "uav/3/input", "uav/1/estimate", "truth/1"):
        s["monitor"].put(f"{R}/{k}", b"monitor-forged")  # the monitor writes nothing
    s["sensor-sim"].put(f"{R}/clock", b"tick")  # control from the sensor-sim: allowed
    _settle()
    assert (f"{R}/uav/3/state", b"own") in mon.got and (f"{R}/uav/3/state", b"own") in peer.got
    assert not [g for g in mon.got if g[1] == b"forged"], mon.got
    assert not [g for g in peer.got if g[1] == b"monitor-forged"], peer.got
    assert (f"{R}/clock", b"tick") in mon.got
    mon.sub.undeclare()
    peer.sub.undeclare()


def test_uav_cannot_read_truth_nor_other_uavs_inputs(bus):
    s, _, _ = bus
    R = f"swarmnav/{RUN}"
    spy = Listener(s["uav-3"], "swarmnav/**/truth/**")
    spy_in = Listener(s["uav-3"], keys.uav(RUN, 4, "input"))
    mon = Listener(s["monitor"], keys.truth_all(RUN))
    _settle()
    s["sensor-sim"].put(keys.truth(RUN, 3), b"truth")
    s["sensor-sim"].put(keys.uav(RUN, 4, "input"), b"input4")
    _settle()
    assert mon.got == [(keys.truth(RUN, 3), b"truth")]  # the control: truth flows to the monitor
    assert spy.got == [] and spy_in.got == []
    for x in (spy, spy_in, mon):
        x.sub.undeclare()


def test_queries_follow_the_acl(bus):
    import zenoh

    s, _, _ = bus
    qs = s["sensor-sim"].declare_queryable(keys.uav_all(RUN, "init"), lambda q: q.reply(str(q.key_expr), b"init"))
    _settle()

    def ask(who, key):
        return [r.ok.payload.to_bytes() for r in s[who].get(key, timeout=1.5) if r.ok is not None]

    assert ask("uav-3", keys.uav(RUN, 3, "init")) == [b"init"]
    assert ask("uav-3", keys.uav(RUN, 4, "init")) == []  # another UAV's initial knowledge: denied
    qs.undeclare()
    del zenoh


def test_unauthenticated_client_is_refused(bus):
    import zenoh

    _, d, ep = bus
    port = ep.rsplit(":", 1)[1]
    for endpoint, tls in ((f"tcp/127.0.0.1:{port}", False), (ep, True)):
        c = zenoh.Config()
        c.insert_json5("mode", '"client"')
        c.insert_json5("connect/endpoints", json.dumps([endpoint]))
        c.insert_json5("scouting/multicast/enabled", "false")
        c.insert_json5("connect/timeout_ms", "2000")
        if tls:  # trusts the run's CA but has no certificate of its own
            ca = json.loads((d / "monitor.json5").read_text())["transport"]["link"]["tls"]["root_ca_certificate_base64"]
            c.insert_json5("transport/link/tls/root_ca_certificate_base64", json.dumps(ca))
        try:
            sess = zenoh.open(c)
        except Exception:
            continue  # refused at open: what we want
        try:  # if it opened at all, it must reach no router
            assert list(sess.info.routers_zid()) == [], endpoint
        finally:
            sess.close()
