"""`launch --live`: the monitor serves the recording over gRPC while it writes swarm.rrd.

A real smoke launch (router, sensor-sim, 5 UAV processes, monitor) is followed by Rerun's own
client (`rerun --save FILE URL`, the viewer's network code saving what it receives): the live
stream must carry the same estimates as the .rrd on disk. Bad --live ports are refused up front.
"""

import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
import rrdcheck  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
RERUN = Path(sys.executable).with_name("rerun")


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_live_view_streams_what_the_recording_holds(tmp_path):
    from services import recording as R

    live, web = _free_port(), _free_port()
    out = tmp_path / "run"
    env_no_display = {k: v for k, v in __import__("os").environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    launch = subprocess.Popen([sys.executable, "-m", "services.cli", "launch", "--config", "configs/smoke.toml", "--live",
                               "--live-port", str(live), "--web-port", str(web), "--out", str(out), "--no-progress"],
                              cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env_no_display)
    client_rrd = tmp_path / "client.rrd"
    client = None
    try:
        deadline = time.monotonic() + 120
        while client is None and time.monotonic() < deadline and launch.poll() is None:
            # the monitor's gRPC server comes up with the monitor; Rerun's client retries a refused connection
            # only for a while, so wait for the port first
            import socket

            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", live)) == 0:
                    client = subprocess.Popen([str(RERUN), "--save", str(client_rrd), R.live_url("127.0.0.1", live)],
                                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            time.sleep(0.2)
        assert client is not None, "the live server never came up"
        text, _ = launch.communicate(timeout=300)
        assert launch.returncode == 0, text[-3000:]
        client.wait(timeout=60)  # the client stops when the monitor's server goes away
    finally:
        for p in (launch, client):
            if p is not None and p.poll() is None:
                p.kill()
    assert f"rerun+http://127.0.0.1:{live}/proxy" in text and f"web viewer at http://127.0.0.1:{web}/" in text
    import psutil

    time.sleep(0.5)
    left = [p.pid for p in psutil.process_iter(["cmdline"]) if str(web) in " ".join(p.info["cmdline"] or [])]
    assert not left, f"the web viewer outlived the run: {left}"
    disk, _ = rrdcheck.recorded(out / "swarm.rrd")
    seen, _ = rrdcheck.recorded(client_rrd)
    # every UAV's estimate track and the error series reached the live viewer in full
    want = [(R.uav_path("atvfg", u), "Points3D:positions") for u in range(1, 6)]
    want += [(R.error_path("atvfg", q, who), "Scalars:scalars") for q in ("pos_3d", "pos_3sigma") for who in ("swarm", "uav1")]
    for path, col in want:
        assert seen[path][col] == disk[path][col] == 60, (path, seen.get(path), disk.get(path))


def test_live_port_in_use_is_refused_before_any_work(tmp_path):
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        out = tmp_path / "run"
        r = subprocess.run([sys.executable, "-m", "services.cli", "launch", "--config", "configs/smoke.toml", "--live",
                            "--live-port", str(port), "--out", str(out)], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and f"--live-port {port}" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert not out.exists()
