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
