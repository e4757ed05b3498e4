"""Bad input gets one clear line and exit 2 before any work starts: no traceback, no run directory."""

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


BROKEN_TOML = "[scenario\nname = 1\n"


# every subcommand, with the mistakes a user makes; "{out}" is where the command would have written
@pytest.mark.parametrize("args, says", [
    (["launch", "--config", "configs/smoke.toml", "--algo", "foo", "--out", "{out}"], "atvfg, atvfg_paper, fg, fkf, ins"),
    (["launch", "--config", "configs/smoke.toml", "--algo", "central", "--out", "{out}"], "in-process only"),
    (["launch", "--config", "configs/smoke.toml", "--kill", "3@999", "--out", "{out}"], "inside the scenario"),
    (["launch", "--config", "configs/smoke.toml", "--restart", "3@20", "--out", "{out}"], "not killed before"),
    (["launch", "--config", "configs/smoke.toml", "--rate", "-2", "--out", "{out}"], "real-time factor > 0"),
    (["launch", "--config", "configs/smoke.toml", "--kill", "99@10", "--out", "{out}"], "does not exist"),
    (["launch", "--config", "configs/smoke.toml", "--timeout", "-1", "--out", "{out}"], "must be > 0"),
    (["launch", "--config", "configs/smoke.toml", "--seed", "-1", "--out", "{out}"], "seed must be >= 0"),
    (["launch", "--config", "configs/smoke.toml", "--live", "--live-port", "70000", "--out", "{out}"], "1..65535"),
    (["launch", "--dataset", "{tmp}", "--out", "{out}"], "not a dataset directory"),
    (["launch", "--config", "{broken}", "--out", "{out}"], "not valid TOML"),
    (["simulate", "--config", "nope.toml", "--out", "{out}"], "config file not found"),
    (["simulate", "--config", "{broken}", "--out", "{out}"], "not valid TOML"),
    (["simulate", "--config", "configs/smoke.toml", "--seed", "-3", "--out", "{out}"], "--seed must be >= 0"),
    (["evaluate", "--config", "configs/smoke.toml", "--algos", "foo", "--out", "{out}"], "unknown algorithm 'foo'"),
    (["evaluate", "--config", "configs/smoke.toml", "--seeds", "3-1", "--out", "{out}"], "cannot parse seeds '3-1'"),
    (["evaluate", "--config", "configs/smoke.toml", "--jobs", "0", "--out", "{out}"], "--jobs 0"),
    (["evaluate", "--dataset", "{tmp}", "--out", "{out}"], "not a dataset directory"),
    (["evaluate", "--dataset", "{tmp}", "--seeds", "tuning", "--out", "{out}"], "not a dataset directory"),
    (["calibrate", "--config", "configs/paper_faultfree.toml"], "needs --out FILE"),
    (["import-miluv", "nope", "--out", "{out}"], "not a directory"),
    (["import-miluv", "{tmp}", "--out", "{out}"], "no robot folders"),
    (["report", "configs"], "no monitor journal"),
    (["report", "{tmp}/nope"], "not a directory"),
    (["keys", "--uavs", "x-y", "--out", "{out}"], "expected ids like 1-18"),
    (["keys", "--uavs", "1-3", "--router-host", "999.1.1.1", "--out", "{out}"], "not an IP address or a DNS name"),
    (["keys", "--uavs", "1-3", "--port", "0", "--out", "{out}"], "not a TCP port"),
    # hold-out review: an --out under a regular file, or a config that is a directory, was a traceback
    (["simulate", "--config", "configs/smoke.toml", "--out", "{file}/x"], "is not a directory"),
    (["evaluate", "--config", "configs/smoke.toml", "--out", "{out}/e\udcff"], "not valid UTF-8"),
    (["calibrate", "--config", "configs/smoke.toml", "--warmup-s", "nan", "--out", "{out}"], "--warmup-s nan"),
    (["calibrate", "--config", "configs/smoke.toml", "--window-s", "inf", "--out", "{out}"], "--window-s inf"),
    (["calibrate", "--dataset", "{tmp}", "--grid", "commit_weight=nan"], "expected KEY=V1,V2"),
    (["launch", "--config", "configs/dropout.toml", "--set", "scenario.duration_s=60", "--out", "{out}"],
     "faults.process_kill[0].at_s = 400 s (UAV 7) lies outside the scenario"),
    (["evaluate", "--config", "configs/smoke.toml", "--seeds", "1-100000000", "--out", "{out}"], "more than 100000"),
    (["simulate", "--config", "{tmp}", "--out", "{out}"], "is a directory, not a config file"),
    (["evaluate", "--config", "configs/smoke.toml", "--out", "{file}"], "exists and is not a directory"),
    (["launch", "--config", "configs/smoke.toml", "--out", "{file}/x"], "is not a directory"),
    (["keys", "--uavs", "1-3", "--out", "{file}/x"], "is not a directory"),
    (["calibrate", "--config", "configs/smoke.toml", "--out", "{file}/delta_l.json"], "exists and is not a directory"),
])
def test_bad_input_is_refused_before_any_work(tmp_path, args, says):
    out = tmp_path / "out"
    broken = tmp_path / "broken.toml"
    broken.write_text(BROKEN_TOML)
    (tmp_path / "empty").mkdir()
    (tmp_path / "file").write_text("a regular file\n")
    argv = [a.format(out=out, tmp=tmp_path / "empty", broken=broken, file=tmp_path / "file") for a in args]
    r = subprocess.run([sys.executable, "-m", "services.cli", *argv], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert says in r.stderr and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert r.stderr.startswith(f"swarmnav {args[0]}: error: "), r.stderr
    assert not out.exists()


@pytest.mark.parametrize("cmd", ["simulate", "evaluate", "launch", "calibrate", "import-miluv", "report", "keys"])
def test_every_subcommand_help_has_examples(cmd):
    r = subprocess.run([sys.executable, "-m", "services.cli", cmd, "--help"], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and "example" in r.stdout and f"swarmnav {cmd} " in r.stdout.split("example", 1)[1], r.stdout
    assert "Thin adapter" not in r.stdout and "``" not in r.stdout  # no internals, no RST markup


def test_output_piped_into_a_reader_that_stops_is_no_traceback(tmp_path):
    """`swarmnav import-miluv ... | head -1`: the reader closes the pipe while the summary is printed."""
    from test_miluv_synthetic import build_folder

    src = build_folder(tmp_path / "synthetic_0")
    p = subprocess.Popen([sys.executable, "-m", "services.cli", "import-miluv", str(src), "--out", str(tmp_path / "ds")],
                         cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    p.stdout.close()  # as `head -1` does once it has its line (here before any: no race with the pipe buffer)
    err = p.stderr.read().decode()
    assert p.wait(timeout=60) == 141 and "Traceback" not in err and "BrokenPipe" not in err


def test_out_of_memory_is_one_clear_line(tmp_path):
    """A scenario too large to simulate (hold-out review: a numpy _ArrayMemoryError traceback)."""
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "services.cli", "simulate", "--config", "configs/smoke.toml",
                        "--set", "scenario.duration_s=1e12", "--out", str(out)],
                       cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and "out of memory" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert not out.exists()
