"""The measurement-model interface (after navlie's ``MeasurementModel``, decargroup/navlie ``types.py``).

A model maps a state vector ``x`` to the expected measurement ``h(x)``. It has

* :meth:`MeasurementModel.evaluate` — h(x);
* :meth:`MeasurementModel.jacobian` — ∂h/∂x, analytic, in the model's tangent space;
* :meth:`MeasurementModel.covariance` — the measurement noise R;
* :meth:`MeasurementModel.jacobian_fd` — the finite-difference reference for ``jacobian``
  (central differences of ``evaluate`` through ``retract``), used by the one generic test
  (tests/test_models.py) over every registered model.

State vectors are flat float arrays whose layout each model documents. A pose enters as its six
gtsam ``Pose3`` tangent coordinates ``[φ (3), p (3)]`` around (R = Exp(φ), p): the perturbation is
gtsam's — rotation on the right, translation in the body frame, (R·Exp(δφ), p + R·δt) — so an
analytic Jacobian here is the Jacobian a gtsam ``CustomFactor`` on a Pose3 key returns.

Each module also holds the *vectorised* functions the estimators call on the hot path (all links
of a round at once) and the gtsam factor builders; the class wraps them for the generic test.
A new sensor is one new module with a :func:`register`-ed model plus its import in
``models/__init__.py``.
"""

from __future__ import annotations

import abc

import numpy as np

from ..geometry import quat_from_rotvec, quat_mul, quat_to_matrix, quat_to_rotvec, skew

__all__ = ["MeasurementModel", "REGISTRY", "register", "wrap_angle", "pose_retract", "rotation_of", "skew"]

REGISTRY: dict[str, type["MeasurementModel"]] = {}


def register(cls: type["MeasurementModel"]) -> type["MeasurementModel"]:
    """Class decorator: add a model to :data:`REGISTRY` under its ``name``."""
    if cls.name in REGISTRY:
        raise ValueError(f"measurement model {cls.name!r} registered twice")
    REGISTRY[cls.name] = cls
    return cls


def wrap_angle(a):
    """Angle(s) wrapped to (−π, π] (rad)."""
    return np.pi - np.mod(np.pi - np.asarray(a, float), 2 * np.pi)


def rotation_of(x: np.ndarray) -> np.ndarray:
    """Rotation matrix Exp(φ) of a pose vector ``[φ, p, ...]``."""
    return quat_to_matrix(quat_from_rotvec(np.asarray(x[:3], float)))


def pose_retract(x: np.ndarray, dx: np.ndarray) -> np.ndarray:
    """gtsam's Pose3 perturbation on the first six entries ``[φ, p]`` (right rotation, body-frame
    translation: (R·Exp(δφ), p + R·δt)); the entries after them are vectors (x + dx)."""
    x, dx = np.asarray(x, float), np.asarray(dx, float)
    q = quat_mul(quat_from_rotvec(x[:3]), quat_from_rotvec(dx[:3]))
    out = x + dx
    out[:3] = quat_to_rotvec(q)
    out[3:6] = x[3:6] + rotation_of(x) @ dx[3:6]
    return out


class MeasurementModel(abc.ABC):
    """One sensor's measurement model h(x) with noise R (navlie's ``MeasurementModel``)."""

    name: str = "model"
    #: entries of x whose perturbation is the Pose3 one (pose_retract); False: x + dx
    pose_state: bool = False
    #: indices of measurement components that are angles (residuals wrapped to (−π, π])
    angle_rows: tuple[int, ...] = ()

    @abc.abstractmethod
    def evaluate(self, x: np.ndarray) -> np.ndarray:
        """h(x), a 1-D array."""

    @abc.abstractmethod
    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """∂h/∂x (m × dof), analytic."""

    @abc.abstractmethod
    def covariance(self) -> np.ndarray:
        """Measurement noise covariance R (m × m)."""

    def retract(self, x: np.ndarray, dx: np.ndarray) -> np.ndarray:
        """x ⊕ dx: the perturbation the Jacobian is taken with."""
        return pose_retract(x, dx) if self.pose_state else np.asarray(x, float) + dx

    def difference(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """a − b with angle components wrapped."""
        d = np.asarray(a, float) - np.asarray(b, float)
        for i in self.angle_rows:
            d[i] = wrap_angle(d[i])
        return d

    def jacobian_fd(self, x: np.ndarray, step: float = 1e-6) -> np.ndarray:
        """∂h/∂x by central differences of :meth:`evaluate` (the reference for :meth:`jacobian`)."""
        x = np.asarray(x, float)
        cols = []
        for i in range(len(x)):
            dx = np.zeros(len(x))
            dx[i] = step
            cols.append(self.difference(self.evaluate(self.retract(x, dx)), self.evaluate(self.retract(x, -dx)))
                        / (2 * step))
        return np.column_stack(cols)

    @classmethod
    @abc.abstractmethod
    def example(cls, rng: np.random.Generator) -> tuple["MeasurementModel", np.ndarray]:
        """A model instance and a state at which to test it (tests/test_models.py)."""


class DirectVelocity(MeasurementModel):
    """A direct observation of the velocity: x = v (ENU m/s), h = v, ∂h/∂v = I, isotropic σ (m/s).
    A GNSS velocity fix and the zero-velocity pseudo-measurement are this model."""

    def __init__(self, sigma: float):
        self.sigma = float(sigma)

    def evaluate(self, x):
        return np.asarray(x, float).copy()

    def jacobian(self, x):
        return np.eye(3)

    def covariance(self):
        return np.eye(3) * self.sigma ** 2
