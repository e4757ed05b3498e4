"""deploy/zygote.py with real processes: a zygote forks probe processes (a small module written here,
run as ``__main__`` like services.uav_node) and reports their exits; the launch stops loudly when
the zygote dies."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from deploy.zygote import EXIT_UNKNOWN, Zygote, ZygoteLost

pytestmark = [pytest.mark.integration]
REPO = Path(__file__).resolve().parents[1]

PROBE = '''
import sys, time
what = sys.argv[1]
print("probe", what, "stdin", repr(sys.stdin.read()), flush=True)
if what == "exit":
    raise SystemExit(int(sys.argv[2]))
if what == "sleep":
    time.sleep(float(sys.argv[2]))
if what == "raise":
    raise RuntimeError("probe failure")
if what == "digest":
    from services.runtime.service import code_digest
    print("cached", code_digest.cache_info().currsize, flush=True)
'''


def _env(tmp: Path) -> dict:
    (tmp / "zprobe.py").write_text(PROBE)
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp), str(REPO), str(REPO / "shared")]), OMP_NUM_THREADS="1",
                OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1", PYTHONUNBUFFERED="1")


def _argv(*args: str) -> list[str]:
    return [sys.executable, "-m", "zprobe", *args]


def _zygote(tmp: Path) -> Zygote:
    argvs = [_argv("sleep", "60", "--uav", "15", "--algo", "atvfg")]
    return Zygote(tmp, "atvfg", argvs, tmp / "zygote.log", cwd=str(REPO), env=_env(tmp))


@pytest.fixture(scope="module")
def zyg(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("zygote")
    z = _zygote(tmp)
    yield z, tmp
    z.close()


def test_exit_codes_and_log(zyg):
    z, tmp = zyg
    ok = z.spawn(_argv("exit", "0"), tmp / "ok.log")
    bad = z.spawn(_argv("exit", "3"), tmp / "bad.log")
    boom = z.spawn(_argv("raise"), tmp / "boom.log")
    assert ok.wait(60) == 0 and bad.wait(60) == 3 and boom.wait(60) == 1
    assert ok.returncode == 0 and ok.poll() == 0
    assert "probe exit stdin ''" in (tmp / "ok.log").read_text()  # stdin is /dev/null
    text = (tmp / "boom.log").read_text()
    assert "Traceback" in text and "RuntimeError: probe failure" in text
    again = z.spawn(_argv("exit", "0"), tmp / "ok.log")  # appended, as Popen did
    assert again.wait(60) == 0
    assert (tmp / "ok.log").read_text().count("probe exit") == 2


def test_killed_and_wait_timeout(zyg):
    z, tmp = zyg
    p = z.spawn(_argv("sleep", "60"), tmp / "sleep.log")
    with pytest.raises(subprocess.TimeoutExpired):
        p.wait(timeout=0.3)
    assert p.poll() is None
    p.kill()
    assert p.wait(10) == -signal.SIGKILL
    p.send_signal(signal.SIGTERM)  # reported: no signal goes to a pid that may be reused
    t = z.spawn(_argv("sleep", "60"), tmp / "sleep.log")
    time.sleep(0.5)
    t.terminate()
    assert t.wait(10) == -signal.SIGTERM


def test_cmdline_ppid_and_digest(zyg):
    z, tmp = zyg
    argv = _argv("sleep", "60", "--uav", "15", "--algo", "atvfg")
    p = z.spawn(argv, tmp / "title.log")
    try:
        ps = psutil.Process(p.pid)
        assert ps.ppid() == z.p.pid
        end = time.monotonic() + 10  # the title is set right after the fork
        while [a for a in ps.cmdline() if a] != argv and time.monotonic() < end:
            time.sleep(0.05)
        cmd = ps.cmdline()
        assert [a for a in cmd if a] == argv and cmd[:len(argv)] == argv
        assert cmd[cmd.index("--uav") + 1] == "15"
        raw = Path(f"/proc/{p.pid}/cmdline").read_bytes()  # NUL-separated, as the shared checks read it
        assert [a.decode() for a in raw.split(b"\0") if a] == argv
    finally:
        p.kill()
        p.wait(10)
    d = z.spawn(_argv("digest"), tmp / "digest.log")
    assert d.wait(60) == 0
    assert "cached 1" in (tmp / "digest.log").read_text()  # the zygote computed it before the fork


def test_bad_request_is_refused(zyg):
    z, tmp = zyg
    with pytest.raises(ZygoteLost, match="expected argv"):
        z.spawn([sys.executable, "zprobe.py"], tmp / "x.log")
    assert z.check() is None  # the zygote goes on serving
    assert z.spawn(_argv("exit", "0"), tmp / "ok2.log").wait(60) == 0


def test_children_die_with_the_zygote(tmp_path):
    z = _zygote(tmp_path)
    p = z.spawn(_argv("sleep", "60"), tmp_path / "orphan.log")
    child = psutil.Process(p.pid)
    z.p.send_signal(signal.SIGKILL)
    child.wait(10)  # PR_SET_PDEATHSIG: SIGTERM when the zygote dies
    assert p.wait(10) == EXIT_UNKNOWN
    assert "killed by SIGKILL" in z.check()
    with pytest.raises(ZygoteLost):
        z.spawn(_argv("exit", "0"), tmp_path / "late.log")
    z.close()


def test_a_stopped_zygote_is_killed_at_the_end_and_said_so(tmp_path):
    """A zygote that no longer answers (SIGSTOP) when the run ends is SIGKILLed by close(), which
    records why (the launcher prints it; its exit -9 makes the launch fail)."""
    z = _zygote(tmp_path)
    z.p.send_signal(signal.SIGSTOP)
    assert z.close() == -signal.SIGKILL
    assert z.hung and "did not exit" in z.hung


def test_launch_ends_loudly_when_the_zygote_dies(tmp_path):
    out = tmp_path / "run"
    env = dict(os.environ, PYTHONPATH=f"{REPO}:{REPO / 'shared'}")
    log = open(tmp_path / "launch.log", "w")
    launcher = subprocess.Popen([sys.executable, "-m", "services.cli", "launch", "--config", "configs/smoke.toml", "--seed", "1",
                                 "--rate", "1", "--out", str(out), "--no-progress"], cwd=REPO, env=env, stdout=log,
                                stderr=subprocess.STDOUT, start_new_session=True)
    try:
        lp = psutil.Process(launcher.pid)
        end = time.monotonic() + 120
        uavs = []
        while time.monotonic() < end and len(uavs) < 5:
            kids = lp.children(recursive=True)
            zyg = [k for k in kids if "deploy.zygote" in k.cmdline()]
            uavs = [k for k in kids if "services.uav_node" in k.cmdline()]
            time.sleep(0.2)
        assert zyg and len(uavs) == 5, [k.cmdline()[:3] for k in kids]
        time.sleep(5.0)  # running
        everyone = lp.children(recursive=True)
        zyg[0].send_signal(signal.SIGKILL)
        rc = launcher.wait(30)
        gone, alive = psutil.wait_procs(everyone, timeout=5)
        text = (tmp_path / "launch.log").read_text()
        assert rc != 0, text[-2000:]
        assert "the UAV zygote failed" in text and "killed by SIGKILL" in text, text[-2000:]
        assert "INCOMPLETE RUN" in text or "no report.json" in text, text[-2000:]
        assert not alive, [p.cmdline() for p in alive]
    finally:
        if launcher.poll() is None:
            os.killpg(launcher.pid, signal.SIGKILL)
            launcher.wait()
