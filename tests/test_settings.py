"""Typed estimator tuning: every key the estimators read is a field of EstimatorTuning with the same
default; a typo'd [estimation.graph] key fails when the config loads, naming it; docs/settings.md is
generated from the model."""

from __future__ import annotations

import ast
import pathlib

import pytest

from swarmnav.config import ConfigError, load_config, parse_config
from swarmnav.estimators import settings as S

REPO = pathlib.Path(__file__).resolve().parents[1]
EST = REPO / "shared" / "swarmnav" / "estimators"
# keys of the [estimation] table itself (config.Estimation) or filled in by the registry: not tuning
NOT_TUNING = {"rounds", "convergence_m", "fixed_lag_s", "delta_l_file", "delta_l_fallback_sigmas", "residual_window_epochs",
              "peer_timeout_s", "graph", "delta_l_m", "delta_l_uwb_sigma_m"}
# defaults written as names in the estimators, resolved here
TYPED = object()  # a read through the typed model: its default is the model's
NAMED = {"det.DEFAULT_CEIL_FACTOR": S.DEFAULT_CEIL_FACTOR, "det.DEFAULT_FLOOR_FACTOR": S.DEFAULT_FLOOR_FACTOR,
         "DRAG_SIGMA_SCALE": S.DRAG_SIGMA_SCALE}


def _reads() -> dict[str, list[tuple[str, int, object]]]:
    """Every ``s.get("key", default)`` / ``settings.get(...)`` in the estimators: key -> [(file, line,
    default)]; a typed read ``t.key`` of settings.tuning()'s model (the per-UAV graph) counts with the
    model's default (``TYPED``)."""
    out: dict[str, list] = {}
    for p in sorted(EST.glob("*.py")):
        for n in ast.walk(ast.parse(p.read_text())):
            if (isinstance(n, ast.Attribute) and ast.unparse(n.value) in ("t", "self.tuning")
                    and n.attr in S.EstimatorTuning.model_fields):
                out.setdefault(n.attr, []).append((p.name, n.lineno, TYPED))
            if (isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute) and n.func.attr == "get" and n.args
                    and isinstance(n.args[0], ast.Constant) and isinstance(n.args[0].value, str)
                    and ast.unparse(n.func.value) in ("s", "settings", "self.settings")):
                src = ast.unparse(n.args[1]) if len(n.args) > 1 else "None"
                try:
                    d = ast.literal_eval(n.args[1]) if len(n.args) > 1 else None
                except ValueError:
                    d = NAMED.get(src, src)
                out.setdefault(n.args[0].value, []).append((p.name, n.lineno, d))
    return out


def test_every_key_the_estimators_read_is_typed_with_the_same_default():
    fields = S.EstimatorTuning.model_fields
    reads = _reads()
    missing = sorted(k for k in reads if k not in fields and k not in NOT_TUNING)
    assert not missing, f"keys read by the estimators but not in EstimatorTuning: {missing}"
    unread = sorted(k for k in fields if k not in reads)
    assert not unread, f"EstimatorTuning keys no estimator reads (dead settings): {unread}"
    for k, places in reads.items():
        if k not in fields:
            continue
        want = fields[k].get_default(call_default_factory=True)
        for file, line, d in places:
            if d is TYPED or (isinstance(d, str) and d.startswith("s.get(")):
                continue  # a default derived from another key
            got = tuple(d) if isinstance(d, (list, tuple)) else d
            exp = tuple(want) if isinstance(want, (list, tuple)) else want
            assert got == exp or (got is None and exp is None), f"{k}: {file}:{line} defaults to {d!r}, the model to {want!r}"


def test_named_defaults_equal_the_estimators_constants():
    from swarmnav.estimators import detection, factors
    from swarmnav.models import rotor_drag

    assert rotor_drag.DRAG_SIGMA_SCALE == factors.DRAG_SIGMA_SCALE

    assert (detection.DEFAULT_FLOOR_FACTOR, detection.DEFAULT_CEIL_FACTOR, factors.DRAG_SIGMA_SCALE) == \
        (S.DEFAULT_FLOOR_FACTOR, S.DEFAULT_CEIL_FACTOR, S.DRAG_SIGMA_SCALE)


def _with_graph(table: dict):
    d = load_config(REPO / "configs" / "smoke.toml").model_dump()
    d["estimation"]["graph"] = table
    return parse_config(d, "test.toml")


def test_a_typo_in_estimation_graph_fails_naming_the_key():
    with pytest.raises(ConfigError) as e:
        _with_graph({"comit_weight": 0.2})
    assert "estimation.graph" in str(e.value) and "'comit_weight'" in str(e.value) and "did you mean 'commit_weight'" in str(e.value)
    with pytest.raises(ConfigError) as e:
        _with_graph({"commit_weight": 2.0})
    assert "commit_weight" in str(e.value) and "less than or equal to 1" in str(e.value)
    assert _with_graph({"commit_weight": 0.2}).estimation.graph == {"commit_weight": 0.2}


def test_shipped_configs_validate():
    from swarmnav.config import load_estimation

    for p in sorted((REPO / "configs").glob("*.toml")):
        if p.name == "miluv.toml":
            load_estimation(p)  # an [estimation]-only file (import-miluv --estimation)
        else:
            load_config(p)


def test_docs_settings_md_is_generated_from_the_model():
    assert (REPO / "docs" / "settings.md").read_text() == S.settings_table_markdown(), \
        "docs/settings.md is stale: regenerate it with python -c 'from swarmnav.estimators.settings import ...'"


def test_the_graph_estimators_read_the_typed_model():
    """settings.tuning: the [estimation.graph] table merged over the top level, validated, the
    model's defaults for the rest; non-tuning keys of the [estimation] table are ignored."""
    t = S.tuning({"rounds": 3, "commit_weight": 0.5, "graph": {"commit_weight": 0.2, "use_tdoa": False}})
    assert (t.commit_weight, t.use_tdoa, t.report) == (0.2, False, "round")
    with pytest.raises(Exception, match="commit_weight"):
        S.tuning({"graph": {"commit_weight": 2.0}})


# [estimation]-table reads with a literal default not converted yet (none left; the test fails when an
# entry here is gone, so the list only shrinks)
LITERAL_ESTIMATION_DEFAULTS: set = set()


def test_estimation_table_defaults_live_in_the_scenario_model():
    """rounds, convergence_m, fixed_lag_s, ... are read through scenario.estimation_values (the
    defaults of scenario.Estimation), never with a ``.get(key, default)`` of their own."""
    from swarmnav.scenario import Estimation, estimation_values

    keys = set(Estimation.model_fields)
    found = set()
    for p in sorted([*(REPO / "shared").rglob("*.py"), *(REPO / "services").rglob("*.py")]):
        for n in ast.walk(ast.parse(p.read_text())):
            if (isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute) and n.func.attr == "get"
                    and len(n.args) == 2 and isinstance(n.args[0], ast.Constant) and n.args[0].value in keys):
                found.add((p.relative_to(REPO).as_posix(), n.args[0].value))
    assert found <= LITERAL_ESTIMATION_DEFAULTS, f"literal defaults of [estimation] keys: {sorted(found - LITERAL_ESTIMATION_DEFAULTS)}"
    assert LITERAL_ESTIMATION_DEFAULTS <= found, f"converted, drop from the list: {sorted(LITERAL_ESTIMATION_DEFAULTS - found)}"
    e = estimation_values({"rounds": 7, "delta_l_m": 0.3, "commit_weight": 0.2})
    assert (e.rounds, e.fixed_lag_s, e.convergence_m) == (7, Estimation().fixed_lag_s, Estimation().convergence_m)
    with pytest.raises(Exception, match="rounds"):
        estimation_values({"rounds": 0})
