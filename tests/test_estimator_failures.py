"""Scenario values at the edge of what the schema accepts run, and a failing estimator says who and why."""

from __future__ import annotations

import numpy as np
import pytest

from swarmnav.config import load_config, parse_config
from swarmnav.errors import describe_estimator_failure
from swarmnav.evaluation import run_algorithm
from swarmnav.sim import simulate


@pytest.mark.parametrize("algo", ["central", "atvfg", "fkf"])
def test_zero_initial_sigmas_mean_known_exactly(algo):
    """[init] sigmas of 0 are valid (attitude known exactly): every estimator runs on them (central
    used to stop with gtsam's 'Indeterminate linear system')."""
    d = load_config("configs/smoke.toml").model_dump()
    d["scenario"]["duration_s"] = 8.0
    d["init"] = {"vel_sigma_mps": 0.0, "roll_pitch_sigma_deg": 0.0, "yaw_sigma_deg": 0.0}
    sc = parse_config(d)
    settings = sc.estimation.model_dump() | {"delta_l_m": None}
    res = run_algorithm(simulate(sc, 7), algo, 7, settings)
    assert np.isfinite(res.pos).all()


def test_estimator_failure_names_the_estimator_the_cause_and_the_remedy():
    e = RuntimeError("\nIndeterminate linear system detected while working near variable\n7061 (Symbol: b5).\n\n"
                     "Thrown when a linear system is ill-posed.\nfor more information.")
    msg = describe_estimator_failure("central", 7, e)
    assert msg.startswith("central failed on seed 7 (RuntimeError: Indeterminate linear system")
    assert "[init]" in msg and "for more information" not in msg and "\n" not in msg


def test_central_failure_says_qr_was_tried_too():
    """central switches to QR by itself (below): if it still fails, the message says both failed."""
    e = RuntimeError("\nIndeterminate linear system detected while working near variable\n7061 (Symbol: b5).\n")
    msg = describe_estimator_failure("central", 7, e)
    assert "Cholesky to QR" in msg and "\n" not in msg
    assert "QR" not in describe_estimator_failure("atvfg", 7, e)


def _no_link_scenario(factorization: str | None = None):
    """smoke with no UWB or az/el link in range (hold-out review: Cholesky refuses central's joint
    graph at the first epoch; QR solves it)."""
    sets = ["scenario.duration_s=4.0", "sensors.uwb.max_range_m=1.0", "sensors.rel.max_range_m=1.0"]
    if factorization:
        sets.append(f'estimation.graph.central_factorization="{factorization}"')
    sc = load_config("configs/smoke.toml", sets)
    return simulate(sc, 1), sc.estimation.model_dump() | {"delta_l_m": None}


def test_central_switches_to_qr_where_cholesky_refuses_and_equals_qr_from_the_start(monkeypatch):
    from swarmnav.estimators import central

    made = []
    init, update = central.CentralEstimator.__init__, central.CentralEstimator._update

    def keep(self, *a, **k):
        init(self, *a, **k)
        made.append(self)

    ds, settings = _no_link_scenario()
    with monkeypatch.context() as m:
        m.setattr(central.CentralEstimator, "__init__", keep)
        switched = run_algorithm(ds, "central", 1, settings)
    assert made and made[0].switched_to_qr_at == 1 and made[0].factorization == "QR"
    ds_qr, settings_qr = _no_link_scenario("QR")
    qr = run_algorithm(ds_qr, "central", 1, settings_qr)
    assert np.isfinite(switched.pos).all()
    np.testing.assert_array_equal(switched.pos, qr.pos)  # the replay is QR's run from the start

    def cholesky_alone(self, *a):  # the premise: without the switch, Cholesky refuses this graph
        self._updates = None
        return update(self, *a)

    monkeypatch.setattr(central.CentralEstimator, "_update", cholesky_alone)
    with pytest.raises(RuntimeError, match="Indeterminate linear system"):
        run_algorithm(ds, "central", 1, settings)
