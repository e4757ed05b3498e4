"""One measurement model per sensor (navlie's ``MeasurementModel``: models/base.py).

Each module documents its h(x), Jacobian, noise, frames and units, and holds the vectorised
functions the simulator and the estimators call; every model is registered in :data:`REGISTRY`
and finite-difference tested by one generic test (tests/test_models.py).
"""

from . import altimeter, anchor_range, bearing, gnss, rotor_drag, tdoa, uwb_range, zero_velocity
from .base import REGISTRY, MeasurementModel, register, wrap_angle

__all__ = ["REGISTRY", "MeasurementModel", "register", "wrap_angle", "altimeter", "anchor_range", "bearing",
           "gnss", "rotor_drag", "tdoa", "uwb_range", "zero_velocity"]
