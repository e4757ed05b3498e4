"""Bad input gets one clear line and exit 2 before any work starts: no traceback, no run directory."""

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("args, says", [
    (["launch", "--config", "configs/smoke.toml", "--algo", "foo"], "atvfg, atvfg_paper, fg, fkf, ins"),
    (["launch", "--config", "configs/smoke.toml", "--algo", "central"], "in-process only"),
    (["launch", "--config", "configs/smoke.toml", "--kill", "3@999"], "inside the scenario"),
    (["launch", "--config", "configs/smoke.toml", "--restart", "3@20"], "not killed before"),
    (["launch", "--config", "configs/smoke.toml", "--rate", "-2"], "real-time factor > 0"),
    (["launch", "--config", "configs/smoke.toml", "--kill", "99@10"], "does not exist"),
    (["report", "configs"], "no monitor journal"),
    (["keys", "--uavs", "x-y"], "expected ids like 1-18"),
])
def test_bad_input_is_refused_before_any_work(tmp_path, args, says):
    out = tmp_path / "out"
    argv = [sys.executable, "-m", "services.cli", *args] + (["--out", str(out)] if args[0] in ("launch", "keys") else [])
    r = subprocess.run(argv, cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert says in r.stderr and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert not out.exists()
