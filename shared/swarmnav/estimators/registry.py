"""Algorithm names -> estimator classes (lazy imports), and the settings dict every estimator gets.

Names are the ones used everywhere (CLI, report keys, Rerun entity paths); docs/estimators.md
describes each.
Factories import their module only when asked, so ``swarmnav evaluate --algos ins`` never pays
for (or depends on) the gtsam graph code, and a missing estimator is reported as a clear error.

Settings (``estimator_settings``): the scenario's ``[estimation]`` table as a dict, plus
``"delta_l_m"``: Δl read from the JSON file named by ``estimation.delta_l_file`` (key
``"delta_l_m"``, written by ``swarmnav calibrate``) if that file exists, else ``None`` (each
estimator then falls back to ``delta_l_fallback_sigmas`` × UWB σ), and ``"delta_l_uwb_sigma_m"``: the
ranging σ the file was trained at (its ``uwb_sigma_m``, None if absent) — the graph estimators use
the trained Δl only on data with that σ (docs/estimators.md, "Δl"). The same function is used by
the in-process evaluation and the Zenoh node service, so both run with identical settings.
"""

from __future__ import annotations

import importlib
import json
from pathlib import Path

from ..errors import ConfigError, SwarmnavError

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

# repository root (…/shared/swarmnav/estimators/registry.py -> parents[3]); used to resolve a
# relative delta_l_file when the working directory is elsewhere
_REPO_ROOT = Path(__file__).resolve().parents[3]


class UnknownAlgorithmError(SwarmnavError):
    """An algorithm name that is not registered, or whose module cannot be imported."""


def register(name: str, cls: type, kind: str = "node") -> None:
    """Register an extra estimator class under ``name`` (tests and experiments)."""
    if kind not in ("node", "swarm"):
        raise ValueError(f"kind must be 'node' or 'swarm', not {kind!r}")
    _EXTRA[name] = (cls, kind)


def unregister(name: str) -> None:
    _EXTRA.pop(name, None)


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


def resolve_delta_l_file(path: str | Path, base_dirs: tuple[Path, ...] = ()) -> Path | None:
    """First existing candidate: absolute path; else relative to the cwd, each base dir, the repo root."""
    p = Path(path)
    if p.is_absolute():
        return p if p.is_file() else None
    for base in (Path.cwd(), *base_dirs, _REPO_ROOT):
        c = base / p
        if c.is_file():
            return c
    return None


def read_delta_l(path: Path) -> tuple[float, float | None]:
    """(Δl in m, the ranging σ in m it was trained at, or None when the file does not say)."""
    try:
        data = json.loads(Path(path).read_text())
        v = float(data["delta_l_m"])
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ConfigError(f"{path}: cannot read Δl (expected JSON with key 'delta_l_m'): {e}") from None
    if not v > 0:
        raise ConfigError(f"{path}: delta_l_m must be a positive number of metres, got {v}")
    try:
        sig = float(data.get("uwb_sigma_m"))
    except (TypeError, ValueError):
        sig = None
    return v, (sig if sig is not None and sig > 0 else None)


def estimator_settings(estimation, base_dirs: tuple[Path, ...] = ()) -> dict:
    """Settings dict for every estimator: ``estimation.model_dump()`` + ``delta_l_m`` (or None) and
    ``delta_l_uwb_sigma_m`` (the ranging σ of Δl's training data, or None).

    ``estimation`` is a :class:`swarmnav.scenario.Estimation` (or a plain dict of its fields).
    """
    s = dict(estimation.model_dump() if hasattr(estimation, "model_dump") else estimation)
    f = s.get("delta_l_file")
    found = resolve_delta_l_file(f, base_dirs) if f else None
    s["delta_l_m"], s["delta_l_uwb_sigma_m"] = read_delta_l(found) if found is not None else (None, None)
    return s


def settings_for_dataset(meta, base_dirs: tuple[Path, ...] = ()) -> dict:
    """Settings for a dataset run as-is: the ``estimation`` table of its resolved scenario config
    (simulated datasets carry it in ``meta.config``), else the defaults of ``Estimation``."""
    from ..scenario import Estimation

    cfg = (meta.config or {}).get("estimation") if meta.config else None
    return estimator_settings(Estimation.model_validate(cfg) if cfg else Estimation(), base_dirs)
