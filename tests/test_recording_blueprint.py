"""The recording is the product's main window: every view of the default blueprint must show data.

`swarmnav evaluate` on smoke (all five algorithms, one recording) is read back with Rerun's own
reader and every view of the blueprint it was written with (``recording.blueprint_views``, the
spec ``default_blueprint`` is built from) must match at least one entity carrying data of the
view's kind. The launch recording gets the same test in tests/test_services.py.
"""

import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
import rrdcheck  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
ALGOS = ["atvfg", "fg", "fkf", "ins", "central"]


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "eval"
    r = subprocess.run([sys.executable, "-m", "services.cli", "evaluate", "--config", "configs/smoke.toml", "--algos",
                        ",".join(ALGOS), "--seeds", "1", "--out", str(out)], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    return out / "evaluate.rrd"


def test_every_view_of_the_evaluate_recording_has_data(evaluated):
    from services import recording as R

    rows, static = rrdcheck.recorded(evaluated)
    link_algos = [a for a in ALGOS if R.links_path(a) in rows]
    assert link_algos == ["atvfg", "fg", "fkf"]  # ins and the oracle classify no links
    views = R.blueprint_views(ALGOS, link_algos)
    assert rrdcheck.view_problems(views, rows, static) == []
    # the 3σ bound of every algorithm, the labels only on the latest-at entity, the link legend
    for a in ALGOS:
        assert rows[R.error_path(a, "pos_3sigma", "swarm")]["Scalars:scalars"] == 60
        assert rows[R.labels_path(a)]["Points3D:labels"] == 60
        assert "Points3D:labels" not in rows[R.uav_path(a, 1)]
    assert "AnnotationContext:context" in static["/links"]


def test_the_checker_catches_an_empty_view():
    from services import recording as R

    bad = [R.ViewSpec("timeseries", "wildcard", ("/errors/*/pos_3d/swarm",), "Scalars:scalars")]
    rows = {"/errors/atvfg/pos_3d/swarm": {"Scalars:scalars": 3}}
    probs = rrdcheck.view_problems(bad, rows, {"/errors/x": {"SeriesLines:names"}})
    # the '*' query (matching nothing, too), the view without data, the named series without data
    assert len(probs) == 4, probs
