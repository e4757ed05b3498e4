"""Estimator settings of a run: the scenario's ``[estimation]`` table plus the trained Δl, read
here from the JSON file ``estimation.delta_l_file`` names (the core reads no file; it takes the
values: :func:`swarmnav.estimators.registry.estimator_settings`).

The Δl file (key ``"delta_l_m"``, written by ``swarmnav calibrate``; ``"uwb_sigma_m"`` the ranging
σ it was trained at) is looked up as given when absolute, else relative to the working directory,
each of ``base_dirs`` and the repository root, the first existing one winning (`evaluate`'s base dirs
are the config's parent's parent and its own directory; `launch` hands its processes the same list
in ``SWARMNAV_DELTA_L_DIRS``, since they run in the repository). No file: Δl is
None and the estimators fall back to ``delta_l_fallback_sigmas`` × UWB σ. The in-process
evaluation, the Zenoh node and the monitor all get their settings here, so they run with the same.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from swarmnav.errors import ConfigError
from swarmnav.estimators import registry

REPO_ROOT = Path(__file__).resolve().parents[1]  # a relative delta_l_file resolves here when the cwd is elsewhere
# `swarmnav launch` sets this (os.pathsep-separated) for the processes it starts, which run in the
# repository: the directories the command itself looked in (its cwd, the config's directories), in
# place of their own cwd, so that the nodes and the monitor find the Δl file `evaluate` finds
LOOKUP_DIRS_ENV = "SWARMNAV_DELTA_L_DIRS"


def lookup_dirs(config: str | Path | None = None) -> tuple[Path, ...]:
    """Where a relative delta_l_file is looked up, before the repository root: the cwd, then (with a
    config file) its parent's parent and its own directory; LOOKUP_DIRS_ENV replaces the cwd."""
    env = [Path(d) for d in os.environ.get(LOOKUP_DIRS_ENV, "").split(os.pathsep) if d]
    dirs = tuple(env) if env else (Path.cwd(),)
    if config is not None:
        c = Path(config).resolve()
        dirs += (c.parent.parent, c.parent)
    return dirs


def resolve_delta_l_file(path: str | Path, base_dirs: tuple[Path, ...] = ()) -> Path | None:
    """First existing candidate: absolute path; else relative to the cwd (or LOOKUP_DIRS_ENV's
    directories), each base dir, the repo root."""
    p = Path(path)
    if p.is_absolute():
        return p if p.is_file() else None
    for base in (*lookup_dirs(), *base_dirs, REPO_ROOT):
        c = base / p
        if c.is_file():
            return c
    return None


def warn_missing_delta_l(estimation, command: str, base_dirs: tuple[Path, ...] = ()) -> None:
    """A delta_l_file that names no file: say so on stderr (the estimators then fall back to
    delta_l_fallback_sigmas × the UWB σ, which report.json's thresholds.delta_l_source records)."""
    import sys

    f = estimation.delta_l_file
    if f and resolve_delta_l_file(f, base_dirs) is None:
        print(f"swarmnav {command}: warning: estimation.delta_l_file {f!r} not found (looked in "
              f"{', '.join(dict.fromkeys(str(d) for d in (*lookup_dirs(), *base_dirs, REPO_ROOT)))}): Δl falls back to "
              f"{estimation.delta_l_fallback_sigmas:g} × the UWB σ", file=sys.stderr)


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
    """registry.estimator_settings with Δl read from ``estimation``'s delta_l_file (if it exists)."""
    f = estimation.delta_l_file if hasattr(estimation, "delta_l_file") else dict(estimation).get("delta_l_file")
    found = resolve_delta_l_file(f, base_dirs) if f else None
    return registry.estimator_settings(estimation, read_delta_l(found) if found is not None else (None, None))


def settings_for_dataset(meta, base_dirs: tuple[Path, ...] = ()) -> dict:
    """Settings for a dataset run as-is: the ``estimation`` table of its resolved scenario config
    (simulated datasets carry it in ``meta.config``), else the defaults of ``Estimation``."""
    return estimator_settings(registry.estimation_of(meta), base_dirs)
