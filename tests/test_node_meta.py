"""The meta a UAV node gets carries no fault, outage or kill schedule (issue 15 item 7): what the
sensor-sim answers on ``meta`` (its real class, the bytes it sends) and what the in-process
evaluation hands every per-UAV estimator. Scoring still reads labels and truth from the dataset."""

import logging
import re
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SCHEDULE = re.compile(r"fault|outage|kill|restart|event|interference|drift|stuck|failure|nlos|^start_s$|^end_s$|^at_s$",
                      re.I)
ALLOWED = {"fault_threshold_m"}  # 3σ of the nominal ranging noise: a number, not a schedule


def _keys(o, p=()):
    if isinstance(o, dict):
        for k, v in o.items():
            yield p + (str(k),)
            yield from _keys(v, p + (str(k),))
    elif isinstance(o, list):
        for i, v in enumerate(o):
            yield from _keys(v, p + (str(i),))


def _scenario():
    """smoke with a GNSS outage, a process kill/restart and the realistic UWB model on top of its
    module failure, stuck module and drift: every kind of schedule a dataset meta can carry."""
    from swarmnav.config import load_config, parse_config

    d = load_config(REPO / "configs/smoke.toml").to_dict()
    d["faults"]["gnss_outage"] = [{"uavs": "slaves", "start_s": 20.0, "end_s": 40.0}]
    d["faults"]["process_kill"] = [{"uav": 3, "at_s": 30.0, "restart_s": 45.0}]
    d["faults"]["interference"]["enabled"] = False
    d["faults"]["uwb"] = {"model": "realistic"}
    return parse_config(d, "test")


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory):
    from swarmnav.sim import simulate

    d = tmp_path_factory.mktemp("nodemeta") / "dataset"
    simulate(_scenario(), 1).write(d)
    return d


def _assert_no_schedule(meta: dict, full: dict):
    assert meta["gnss_outages"] == [] and meta["events"] == []
    assert meta["seed"] is None
    assert set(meta["config"] or {}) <= {"estimation"}
    bad = ["/".join(p) for p in _keys(meta) if SCHEDULE.search(p[-1]) and p[-1] not in ALLOWED
           and p[-1] not in ("gnss_outages", "events")]
    assert not bad, f"schedule-like keys in the node meta: {bad}"
    # what a UAV knows is all there
    for k in ("nodes", "earth", "origin", "uwb_sigma_m", "rel_sigma_rad", "epoch_dt_s", "duration_s", "t_start",
              "init", "fault_threshold_m", "name", "config_sha256"):
        assert meta[k] == full[k], k
    assert meta["config"]["estimation"] == full["config"]["estimation"]


def test_sensor_sim_meta_answer_carries_no_schedule(dataset_dir):
    from services.sensor_sim.sim import SensorSim, parse_args
    from swarmnav.dataset import Dataset, DatasetMeta
    from swarmnav.wire import messages as M

    full = Dataset.read(dataset_dir).meta
    # the dataset itself keeps every schedule (the monitor and evaluate score from it)
    assert full.gnss_outages and full.events and full.config["faults"]["module_failure"] and full.seed == 1
    sim = SensorSim(parse_args(["--router", "tcp/127.0.0.1:1", "--run", "r1", "--dataset", str(dataset_dir),
                                "--seed", "1"]), session=None, log=logging.getLogger("test"))
    assert sim.meta.gnss_outages and sim.meta.events  # the sensor-sim itself still needs them
    msg = M.decode(M.MetaMsg, sim.meta_msg)  # the very bytes it replies with
    _assert_no_schedule(msg.meta, full.model_dump(mode="json", by_alias=True))
    nm = DatasetMeta.model_validate(msg.meta)  # what node.py builds from it
    assert nm.uav_ids() == full.uav_ids() and nm.n_epochs() == full.n_epochs()


def test_node_view_keeps_the_settings(dataset_dir):
    from swarmnav.dataset import Dataset, node_view

    from services.settings import settings_for_dataset

    meta = Dataset.read(dataset_dir).meta
    a, b = settings_for_dataset(meta), settings_for_dataset(node_view(meta))
    assert a == b
    assert meta.gnss_outages  # node_view copies; the dataset's meta is untouched


def test_in_process_estimators_get_the_node_meta(dataset_dir, monkeypatch):
    from swarmnav.dataset import Dataset
    from swarmnav.estimators import registry
    from swarmnav import evaluation

    from services.settings import settings_for_dataset

    ds = Dataset.read(dataset_dir)
    seen = []
    real = registry.make_node

    def spy(algo, uav, meta, settings, init):
        seen.append(meta)
        return real(algo, uav, meta, settings, init)

    monkeypatch.setattr(registry, "make_node", spy)
    settings = settings_for_dataset(ds.meta)
    res = evaluation.run_algorithm(ds, "ins", 1, settings)
    assert len(seen) == len(ds.meta.uav_ids()) and np.isfinite(res.pos).all()
    full = ds.meta.model_dump(mode="json", by_alias=True)
    for m in seen:
        _assert_no_schedule(m.model_dump(mode="json", by_alias=True), full)
