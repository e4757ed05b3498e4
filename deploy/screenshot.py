"""Screenshot a Rerun recording as shown by Rerun's web viewer in headless Chromium.

    python -m deploy.screenshot RRD --out docs/img/viewer.png [--width 1600 --height 1000] [--wait 20]

Serves RRD with `rerun --serve-web` (gRPC proxy + web viewer on free ports of 127.0.0.1, no browser
opened) and points headless Chromium (software WebGL via SwiftShader) at it. After --wait s the whole
file is loaded and, since a file streamed through the proxy is shown in "follow" mode, the time cursor
sits at the last sample. The page is grabbed over the DevTools protocol on a pipe (stdlib only), retried
until the PNG is not blank/uniform; unless --keep-panels, the blueprint/time/selection panel toggles
(top right of the 0.41 viewer) are clicked first so the views fill the window. Every process started
is stopped on exit, also on error. Needs `apt-get install chromium`.
"""
import argparse, base64, contextlib, fcntl, io, json, os, select, shutil, signal, socket
import subprocess, sys, tempfile, time, urllib.parse, urllib.request
from pathlib import Path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def find_chromium() -> str:
    for name in (os.environ.get("CHROMIUM", ""), "chromium", "chromium-browser", "google-chrome"):
        if name and (path := shutil.which(name)):
            return path
    sys.exit("error: chromium not found: install it with `apt-get install chromium` (or set CHROMIUM=/path)")


def stop(proc: subprocess.Popen | None) -> None:
    """Stop a process started with start_new_session=True together with its children (its own process group)."""
    for sig, grace in ((signal.SIGTERM, 5), (signal.SIGKILL, 5)):
        if proc is None or proc.poll() is not None:
            return
        with contextlib.suppress(ProcessLookupError, subprocess.TimeoutExpired):
            os.killpg(proc.pid, sig)
            proc.wait(grace)


class DevTools:
    """Minimal Chrome DevTools Protocol client over --remote-debugging-pipe (fd 3: commands in, fd 4: replies out)."""

    def __init__(self, chrome: str, args: list[str]):
        cmd_r, self.cmd_w = os.pipe()
        self.res_r, res_w = os.pipe()
        def child_fds() -> None:  # runs in the child: move the pipe ends to fds 3 and 4
            hi = [fcntl.fcntl(fd, fcntl.F_DUPFD, 10) for fd in (cmd_r, res_w)]
            os.dup2(hi[0], 3), os.dup2(hi[1], 4)
        self.proc = subprocess.Popen([chrome, "--remote-debugging-pipe", *args], preexec_fn=child_fds, pass_fds=(3, 4),
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        os.close(cmd_r), os.close(res_w)
        self.buf, self.next_id = b"", 0

    def call(self, method: str, session: str | None = None, timeout: float = 60, **params) -> dict:
        self.next_id += 1
        msg = {"id": self.next_id, "method": method, "params": params} | ({"sessionId": session} if session else {})
        os.write(self.cmd_w, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + timeout
        while True:
            while b"\0" in self.buf:
                raw, self.buf = self.buf.split(b"\0", 1)
                if (reply := json.loads(raw)).get("id") == self.next_id:  # skip events
                    if "error" in reply:
                        raise RuntimeError(f"{method}: {reply['error']}")
                    return reply["result"]
            if not select.select([self.res_r], [], [], max(0.0, deadline - time.monotonic()))[0]:
                raise TimeoutError(f"chromium did not answer {method} within {timeout} s")
            if not (chunk := os.read(self.res_r, 1 << 20)):
                raise RuntimeError(f"chromium exited (code {self.proc.poll()}) during {method}")
            self.buf += chunk


def looks_rendered(png: bytes) -> bool:
    """True if the image is not blank: many distinct colours and no colour covering 90 % (loading screen)."""
    from PIL import Image
    counts = sorted((c for c, _ in Image.open(io.BytesIO(png)).convert("RGB").resize((400, 250)).getcolors(10**5)))
    return len(counts) > 200 and counts[-1] < 0.9 * sum(counts)


def serve(rrd: Path, log) -> tuple[subprocess.Popen, str]:
    """Start `rerun --serve-web RRD` on free local ports; return it and the viewer URL once it answers."""
    grpc, web = free_port(), free_port()
    rerun = Path(sys.executable).with_name("rerun")  # the venv's CLI, else the one on PATH
    server = subprocess.Popen([str(rerun) if rerun.exists() else "rerun", "--serve-web", "--bind", "127.0.0.1",
                               "--port", str(grpc), "--web-viewer-port", str(web), str(rrd)],
                              stdout=log, stderr=log, start_new_session=True)
    for _ in range(300):  # wait up to 30 s for the web viewer's HTTP server
        if server.poll() is not None:
            raise RuntimeError(f"rerun exited early:\n{Path(log.name).read_text()[-2000:]}")
        with contextlib.suppress(OSError):
            urllib.request.urlopen(f"http://127.0.0.1:{web}/", timeout=1).close()
            return server, f"http://127.0.0.1:{web}/?url=" + urllib.parse.quote(f"rerun+http://127.0.0.1:{grpc}/proxy")
        time.sleep(0.1)
    stop(server)
    raise RuntimeError(f"rerun web viewer did not come up on port {web}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rrd", type=Path), ap.add_argument("--out", type=Path, default=Path("docs/img/viewer.png"))
    ap.add_argument("--width", type=int, default=1600), ap.add_argument("--height", type=int, default=1000)
    ap.add_argument("--wait", type=float, default=20, help="seconds to let the viewer load before the first shot")
    ap.add_argument("--retry", type=float, default=60, help="extra seconds to retry while the image is blank")
    ap.add_argument("--keep-panels", action="store_true", help="keep the blueprint/selection/streams panels open")
    a = ap.parse_args(argv)
    if not a.rrd.is_file():
        sys.exit(f"error: {a.rrd} not found (make demo writes runs/demo/evaluate.rrd)")
    chrome, t0, server, dt = find_chromium(), time.monotonic(), None, None
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # so `finally` also runs when we are terminated
    with tempfile.TemporaryDirectory(prefix="rr-shot-") as tmp, open(Path(tmp) / "rerun.log", "wb+") as log:
        try:
            server, url = serve(a.rrd, log)
            flags = ["--headless", f"--window-size={a.width},{a.height}", "--hide-scrollbars", "--no-first-run",
                     "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
                     "--disable-dev-shm-usage", f"--user-data-dir={tmp}/chrome"]
            flags += ["--no-sandbox"] if os.geteuid() == 0 else []  # chromium refuses to run as root otherwise
            dt = DevTools(chrome, [*flags, url])
            page = next(t for t in dt.call("Target.getTargets")["targetInfos"] if t["type"] == "page")
            session = dt.call("Target.attachToTarget", targetId=page["targetId"], flatten=True)["sessionId"]
            dt.call("Emulation.setDeviceMetricsOverride", session, width=a.width, height=a.height,
                    deviceScaleFactor=1, mobile=False)
            shot = lambda: base64.b64decode(dt.call("Page.captureScreenshot", session, format="png")["data"])
            time.sleep(a.wait)
            deadline = time.monotonic() + a.retry
            while not looks_rendered(png := shot()):
                if time.monotonic() > deadline:
                    raise RuntimeError(f"viewer still blank/loading after {a.wait + a.retry:.0f} s (no WebGL?)")
                time.sleep(3)
            if not a.keep_panels:  # the toggle icons sit 79, 52, 24 px left of the top bar's right edge
                for dx in (79, 52, 24):
                    for kind in ("mouseMoved", "mousePressed", "mouseReleased"):
                        dt.call("Input.dispatchMouseEvent", session, type=kind, x=a.width - dx, y=17,
                                button="left", clickCount=1)
                    time.sleep(0.5)
                time.sleep(2)
                png = shot()
            a.out.parent.mkdir(parents=True, exist_ok=True)
            a.out.write_bytes(png)
            print(f"wrote {a.out} ({a.width}x{a.height}, {len(png) // 1024} KiB) in {time.monotonic() - t0:.0f} s")
        except (RuntimeError, TimeoutError) as e:
            sys.exit(f"error: {e}")
        finally:
            stop(dt.proc if dt else None)
            stop(server)


if __name__ == "__main__":
    main()
