"""Algorithm names -> estimator classes (lazy imports), and the settings dict every estimator gets.

Names are the ones used everywhere (CLI, report keys, Rerun entity paths); docs/estimators.md
describes each.
Factories import their module only when asked, so ``swarmnav evaluate --algos ins`` never pays
for (or depends on) the gtsam graph code, and a missing estimator is reported as a clear error.

Settings (``estimator_settings``): the scenario's ``[estimation]`` table as a dict, plus
``"delta_l_m"``: the trained Δl (written by ``swarmnav calibrate`` to ``estimation.delta_l_file``),
or ``None`` (each estimator then falls back to ``delta_l_fallback_sigmas`` × UWB σ), and
``"delta_l_uwb_sigma_m"``: the ranging σ it was trained at (None if unknown) — the graph estimators
use the trained Δl only on data with that σ (docs/estimators.md, "Δl"). The core reads no file: the
services read the Δl file (``services/settings.py``) and pass its values in, with one function for
the in-process evaluation and the Zenoh node service, so both run with identical settings.
"""

from __future__ import annotations

import importlib

from ..errors import SwarmnavError

# name -> (module, class, kind); kind "node" = NodeEstimator(uav, meta, settings, init),
# "swarm" = SwarmEstimator(meta, settings, inits)
_REGISTRY: dict[str, tuple[str, str, str]] = {
    "atvfg": ("swarmnav.estimators.graph", "AtvfgEstimator", "node"),
    "atvfg_paper": ("swarmnav.estimators.graph", "AtvfgPaperEstimator", "node"),
    "fg": ("swarmnav.estimators.graph", "FgEstimator", "node"),
    "fkf": ("swarmnav.estimators.fkf", "FkfEstimator", "node"),
    "ins": ("swarmnav.estimators.graph", "InsEstimator", "node"),
    "central": ("swarmnav.estimators.central", "CentralEstimator", "swarm"),
}
ALGORITHMS: tuple[str, ...] = tuple(_REGISTRY)
# extra entries (tests, experiments): name -> class; takes precedence over _REGISTRY
_EXTRA: dict[str, tuple[type, str]] = {}

class UnknownAlgorithmError(SwarmnavError):
    """An algorithm name that is not registered, or whose module cannot be imported."""


def register(name: str, cls: type, kind: str = "node") -> None:
    """Register an extra estimator class under ``name`` (tests and experiments)."""
    if kind not in ("node", "swarm"):
        raise ValueError(f"kind must be 'node' or 'swarm', not {kind!r}")
    _EXTRA[name] = (cls, kind)


def known() -> list[str]:
    return list(ALGORITHMS) + [n for n in _EXTRA if n not in _REGISTRY]


def kind(name: str) -> str:
    """'node' (per-UAV NodeEstimator driven by the epoch protocol) or 'swarm' (central oracle)."""
    if name in _EXTRA:
        return _EXTRA[name][1]
    if name in _REGISTRY:
        return _REGISTRY[name][2]
    raise UnknownAlgorithmError(f"unknown algorithm {name!r}; known: {', '.join(known())}")


def estimator_class(name: str) -> type:
    """The class registered under ``name`` (imported on first use)."""
    if name in _EXTRA:
        return _EXTRA[name][0]
    if name not in _REGISTRY:
        raise UnknownAlgorithmError(f"unknown algorithm {name!r}; known: {', '.join(known())}")
    mod, cls, _ = _REGISTRY[name]
    try:
        return getattr(importlib.import_module(mod), cls)
    except (ImportError, AttributeError) as e:
        raise UnknownAlgorithmError(f"algorithm {name!r} is not available ({mod}.{cls}: {e})") from e


def make_node(name: str, uav: int, meta, settings: dict, init):
    if kind(name) != "node":
        raise UnknownAlgorithmError(f"{name!r} is a whole-swarm estimator, not a per-UAV one")
    return estimator_class(name)(uav, meta, settings, init)


def make_swarm(name: str, meta, settings: dict, inits: dict):
    if kind(name) != "swarm":
        raise UnknownAlgorithmError(f"{name!r} is a per-UAV estimator, not a whole-swarm one")
    return estimator_class(name)(meta, settings, inits)


def estimator_settings(estimation, delta_l: tuple[float | None, float | None] = (None, None)) -> dict:
    """Settings dict for every estimator: ``estimation.model_dump()`` + ``delta_l_m`` and
    ``delta_l_uwb_sigma_m`` from ``delta_l`` = (Δl in m, the ranging σ of its training data in m),
    each None when unknown (the services read them from ``delta_l_file``: services/settings.py).

    ``estimation`` is a :class:`swarmnav.scenario.Estimation` (or a plain dict of its fields).
    """
    s = dict(estimation.model_dump() if hasattr(estimation, "model_dump") else estimation)
    s["delta_l_m"], s["delta_l_uwb_sigma_m"] = delta_l
    return s


def estimation_of(meta):
    """The ``[estimation]`` table of a dataset's resolved scenario config (simulated datasets carry
    it in ``meta.config``), validated, else the defaults of :class:`~swarmnav.scenario.Estimation`."""
    from ..scenario import Estimation

    cfg = (meta.config or {}).get("estimation") if meta.config else None
    return Estimation.model_validate(cfg) if cfg else Estimation()
