"""Ctrl-C (SIGINT) or SIGTERM in the middle of `swarmnav evaluate`: it says the run is incomplete,
exits non-zero, leaves no worker process running and no report.json (not even an earlier run's)."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _children(pid: int) -> list[int]:
    try:
        return [int(x) for x in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.parametrize("sig, status, says", [(signal.SIGINT, 130, "interrupted"),
                                               (signal.SIGTERM, 143, "terminated (SIGTERM)")])
def test_evaluate_stops_cleanly(tmp_path, sig, status, says):
    out = tmp_path / "ev"
    out.mkdir()
    (out / "report.json").write_text('{"schema": "an earlier run"}\n')  # must not pass for this run's
    p = subprocess.Popen([sys.executable, "-m", "services.cli", "evaluate", "--config", "configs/paper.toml",
                          "--set", "scenario.duration_s=120", "--algos", "atvfg,fg", "--seeds", "1", "--jobs", "2",
                          "--no-rrd", "--quiet", "--out", str(out)], cwd=REPO, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    try:
        t0 = time.monotonic()
        while len(_children(p.pid)) < 2 and time.monotonic() - t0 < 60 and p.poll() is None:
            time.sleep(0.2)  # the worker pool is up: the runs are under way
        workers = _children(p.pid)
        assert len(workers) >= 2 and p.poll() is None, "evaluate did not start its workers"
        time.sleep(1.0)
        os.kill(p.pid, sig)
        _, err = p.communicate(timeout=30)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == status, err
    assert says in err and "incomplete" in err and "Traceback" not in err, err
    time.sleep(0.5)
    assert not [w for w in workers if _alive(w)], "worker processes left running"
    assert not (out / "report.json").exists()


def test_forked_children_get_the_default_sigterm_back():
    """The CLI's SIGTERM handler is for its own process only: a forked child (a pool worker) must
    die on SIGTERM whichever of its threads the kernel delivers it to (a Python handler waited for
    a main thread blocked in a read: Pool.terminate() then hung)."""
    code = (
        "import os, signal, sys\n"
        "from services import cli\n"
        "cli.install_sigterm()\n"
        "assert signal.getsignal(signal.SIGTERM) not in (signal.SIG_DFL, None)\n"
        "pid = os.fork()\n"
        "if pid == 0:\n"
        "    os._exit(0 if signal.getsignal(signal.SIGTERM) == signal.SIG_DFL else 3)\n"
        "sys.exit(os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1]))\n")
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
