"""A relative estimation.delta_l_file resolves to the same file in `evaluate` and in the processes
`launch` starts (which run in the repository). Hold-out review: a config beside its own Δl file
gave Δl 0.5 m in evaluate and the 0.3 m fallback in launch, silently, so the two disagreed."""

import json

from services import settings as SS
from swarmnav.config import load_config

CONFIGS = SS.REPO_ROOT / "configs"


def test_launch_processes_find_the_delta_l_file_evaluate_finds(tmp_path, monkeypatch):
    (tmp_path / "mydl.json").write_text(json.dumps({"delta_l_m": 0.5, "uwb_sigma_m": 0.1}))
    cfg = tmp_path / "x.toml"
    cfg.write_text(f'base = "{CONFIGS / "smoke.toml"}"\n[estimation]\ndelta_l_file = "mydl.json"\n')
    sc = load_config(cfg)
    work = tmp_path / "elsewhere"
    work.mkdir()
    monkeypatch.chdir(work)
    monkeypatch.delenv(SS.LOOKUP_DIRS_ENV, raising=False)
    # evaluate: the cwd and the config's directories
    ev = SS.estimator_settings(sc.estimation, base_dirs=SS.lookup_dirs(cfg)[-2:])
    assert ev["delta_l_m"] == 0.5
    # launch: sets the variable for its processes, which run in the repository with no base dirs
    monkeypatch.setenv(SS.LOOKUP_DIRS_ENV, ":".join(str(d) for d in SS.lookup_dirs(cfg)))
    monkeypatch.chdir(SS.REPO_ROOT)
    node = SS.estimator_settings(sc.estimation)
    assert node["delta_l_m"] == ev["delta_l_m"]


def test_shipped_delta_l_file_still_found_from_anywhere(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv(SS.LOOKUP_DIRS_ENV, raising=False)
    sc = load_config(CONFIGS / "smoke.toml")
    assert SS.resolve_delta_l_file(sc.estimation.delta_l_file) == CONFIGS / "delta_l.json"


def test_missing_delta_l_file_warns(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    sc = load_config(CONFIGS / "smoke.toml", ["estimation.delta_l_file=nope.json"])
    SS.warn_missing_delta_l(sc.estimation, "evaluate")
    err = capsys.readouterr().err
    assert "warning: estimation.delta_l_file 'nope.json' not found" in err and "falls back to 3" in err
