"""One generic test for every registered measurement model (swarmnav.models): the analytic
Jacobian equals the finite-difference reference, the noise is a covariance, shapes agree."""

from __future__ import annotations

import numpy as np
import pytest

from swarmnav.models import REGISTRY

EXPECTED = {"gnss", "gnss_velocity", "uwb_range", "bearing", "anchor_range", "tdoa", "altimeter", "rotor_drag",
            "zero_velocity"}


def test_every_sensor_has_a_registered_model():
    assert EXPECTED <= set(REGISTRY)


@pytest.mark.parametrize("name", sorted(REGISTRY))
@pytest.mark.parametrize("seed", range(5))
def test_model_jacobian_matches_finite_differences(name, seed):
    model, x = REGISTRY[name].example(np.random.default_rng(seed))
    h = model.evaluate(x)
    J = model.jacobian(x)
    R = model.covariance()
    assert h.ndim == 1 and J.shape == (len(h), len(x)) and R.shape == (len(h), len(h))
    assert np.allclose(R, R.T) and np.all(np.linalg.eigvalsh(R) > 0)
    np.testing.assert_allclose(J, model.jacobian_fd(x), rtol=1e-5, atol=1e-6)


def test_vectorised_linearisations_match_the_models_h():
    """The rounds' vectorised h (models.uwb_range.ranges, models.bearing.azel_jacobians) equals the
    h the simulator uses (distance, azimuth_elevation)."""
    from swarmnav.models import bearing, uwb_range

    rng = np.random.default_rng(0)
    a, b = rng.normal(0, 30, (50, 3)), rng.normal(0, 30, (50, 3))
    np.testing.assert_allclose(uwb_range.ranges(a - b)[0], uwb_range.distance(a, b), rtol=1e-14)
    az, el, _ = bearing.azel_jacobians(b - a)
    np.testing.assert_allclose(np.c_[az, el], np.c_[bearing.azimuth_elevation(a, b)], rtol=1e-13, atol=1e-15)
