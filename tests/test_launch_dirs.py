"""Two launches without --out started in the same second get two run directories (hold-out review:
they shared one, overwrote each other's identities; one hung to its timeout, the other failed)."""

import os

from services.commands import launch as L


def test_same_second_launches_get_distinct_run_dirs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(L.time, "strftime", lambda fmt: "20260101-000000")
    a, b, c = (L.claim_default_run_dir("smoke") for _ in range(3))
    assert [p.name for p in (a, b, c)] == ["20260101-000000-smoke", "20260101-000000-smoke-2", "20260101-000000-smoke-3"]
    assert all(p.is_dir() and not any(p.iterdir()) for p in (a, b, c))


def test_point_latest_replaces_the_link(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    a, b = L.claim_default_run_dir("x"), L.claim_default_run_dir("y")
    L.point_latest(a.resolve())
    L.point_latest(b.resolve())
    latest = tmp_path / "runs" / "latest"
    assert latest.is_symlink() and os.readlink(latest) == b.name
    assert sorted(p.name for p in (tmp_path / "runs").iterdir() if p.name.startswith(".")) == []


def test_point_latest_on_a_real_directory_warns(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    a = L.claim_default_run_dir("x")
    (tmp_path / "runs" / "latest").mkdir()
    L.point_latest(a.resolve())  # no exception: the run goes on
    assert "cannot point" in capsys.readouterr().err


def test_router_port_taken_is_a_clear_error(tmp_path, monkeypatch):
    """The router's port taken by someone else: one clear SwarmnavError, no process started, no traceback."""
    import socket

    import pytest

    import deploy.launcher as DL
    from swarmnav.errors import SwarmnavError

    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 0)
        s.bind(("127.0.0.1", 0))
        s.listen()
        monkeypatch.setattr(DL, "free_port", lambda *a, **k: s.getsockname()[1])
        spec = DL.LaunchSpec(run_dir=tmp_path, dataset=tmp_path / "dataset", seed=1, algo="atvfg", uavs=[1, 2],
                             n_epochs=3, kills=[], restarts=[], progress=False, secure=False)
        with pytest.raises(SwarmnavError, match="cannot open the run's Zenoh router"):
            DL.launch(spec)
    assert not (tmp_path / "logs").exists() or not any((tmp_path / "logs").iterdir())


def test_stopped_run_reports_its_speed_over_what_it_got_through(tmp_path, monkeypatch, capsys):
    """Hold-out review: a run stopped after 6 of 60 epochs in 3 s said '20x real time' (60 s / 3 s)."""
    import json
    from types import SimpleNamespace

    import swarmnav.report as R

    monkeypatch.setattr(R, "summary_table", lambda rep: "")
    monkeypatch.setattr(R, "events_text", lambda ev: "")
    (tmp_path / "report.json").write_text(json.dumps({"epochs_expected": 60, "epochs_recorded": 6, "complete": False}))
    res = SimpleNamespace(status=1, processes={}, stop_reason="timed out after 3 s (--timeout)", events=[], security={})
    assert L.finish_report(tmp_path, res, 3.0, 60.0) == 1
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["distributed"]["realtime_factor"] == 2.0
    assert "2.0x real time over the 6 s it got through" in capsys.readouterr().out
    (tmp_path / "report.json").unlink()
    assert L.finish_report(tmp_path, res, 3.0, 60.0) == 1
    assert "stopped early" in capsys.readouterr().out
