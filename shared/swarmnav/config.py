"""Scenario configuration: load a TOML file (following its ``base`` chain), apply ``--set KEY=VALUE``
overrides, and validate it into the :class:`~swarmnav.scenario.Scenario` schema.

A config file may name a ``base`` file (relative to itself); the two are deep-merged, the
derived file winning (tables merge key by key, arrays replace). ``load_config`` raises
:class:`ConfigError` whose message names the offending field and the reason. The schema models
live in :mod:`swarmnav.scenario` and are re-exported here (``from swarmnav.config import Scenario``).
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from types import UnionType
from typing import Literal, Union, get_args, get_origin

from pydantic import BaseModel, ValidationError

from .errors import ConfigError
from .scenario import (MAX_UAVS, Drift, Estimation, Evaluation, Faults, GnssOutage, GnssSpec, ImuSpec,  # noqa: F401
                       InitialKnowledge, Interference, Manoeuvre, ModuleFailure, Origin, ProcessKill, RelSpec, Scenario,
                       ScenarioMeta, Sensors, StuckModule, Swarm, Trajectory, UwbErrorModel, UwbSpec, evaluation_block,
                       parse_seed_spec)


def _deep_merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _read_toml(path: Path, seen: tuple[Path, ...] = ()) -> dict:
    path = path.resolve()
    if path in seen:
        raise ConfigError(f"{path}: 'base' chain loops back to itself")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"config file not found: {path}") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a directory, not a config file; give a TOML file, e.g. configs/smoke.toml") from None
    except UnicodeDecodeError as e:
        raise ConfigError(f"{path}: not a text (UTF-8) file, so not a TOML config ({e.reason} at byte {e.start})") from None
    except OSError as e:
        raise ConfigError(f"{path}: cannot read the config file ({e.strerror})") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: not valid TOML: {e}") from None
    base = data.pop("base", None)
    if base is None:
        return data
    if not isinstance(base, str):
        raise ConfigError(f"{path}: field 'base' must be a file name string")
    return _deep_merge(_read_toml(path.parent / base, seen + (path,)), data)


def format_validation_error(e: ValidationError, source: str) -> str:
    lines = [f"{source}: invalid configuration ({e.error_count()} problem(s)):"]
    for err in e.errors():
        loc = ".".join(str(p) for p in err["loc"]) or "(top level)"
        lines.append(f"  - field '{loc}': {err['msg']} (got {err.get('input')!r:.80})")
    return "\n".join(lines)


def parse_config(data: dict, source: str = "<config>") -> Scenario:
    try:
        return Scenario.model_validate(data)
    except ValidationError as e:
        raise ConfigError(format_validation_error(e, source)) from None


def load_estimation(path: str | Path) -> dict:
    """The validated ``[estimation]`` table of a TOML file (e.g. configs/miluv.toml: the estimator
    tuning an importer embeds in a recorded dataset's meta), as the dict given (unset fields stay
    unset, so the estimators' defaults apply to them)."""
    data = _read_toml(Path(path))
    est = data.get("estimation")
    if not isinstance(est, dict):
        raise ConfigError(f"{path}: no [estimation] table")
    try:
        Estimation.model_validate(est)
    except ValidationError as e:
        raise ConfigError(format_validation_error(e, f"{path} [estimation]")) from None
    return est


def _field_type(model: type[BaseModel], key: str, where: str):
    """The annotation of field ``key`` of ``model``; ConfigError naming the known fields if none."""
    f = model.model_fields.get(key)
    if f is None:
        raise ConfigError(f"unknown field '{where}' (fields of [{where.rpartition('.')[0] or 'top level'}]: "
                          f"{', '.join(model.model_fields)})")
    return f.annotation


def _check_key(path: list[str]) -> None:
    """Walk the Scenario schema along ``path``; ConfigError (one line) if it names no field."""
    t: object = Scenario
    for i, key in enumerate(path):
        where = ".".join(path[: i + 1])
        args = [a for a in get_args(t) if a is not type(None)]
        if get_origin(t) in (Union, UnionType) and args:  # X | None: the model or dict alternative
            t = next((a for a in args if isinstance(a, type) and issubclass(a, BaseModel)),
                     next((a for a in args if get_origin(a) is dict), args[0]))
        if isinstance(t, type) and issubclass(t, BaseModel):
            t = _field_type(t, key, where)
        elif get_origin(t) is dict:
            kt, vt = get_args(t)
            allowed = get_args(kt) if get_origin(kt) is Literal else None
            if allowed and key not in allowed:
                raise ConfigError(f"unknown key '{where}' (one of: {', '.join(map(str, allowed))})")
            t = vt
        else:
            raise ConfigError(f"'{'.'.join(path[:i])}' is a value, not a table: cannot set '{where}'")


def parse_override(text: str) -> tuple[list[str], object]:
    """``KEY=VALUE`` of ``--set``: KEY a dotted field path (``swarm.n_uavs``), VALUE a TOML value
    (``100``, ``60.0``, ``true``, ``[2, 9]``, ``"x"``) or else a bare string. ConfigError (one line)
    naming the problem."""
    try:
        str(text).encode("utf-8")
    except UnicodeEncodeError:  # bytes that are not UTF-8 on the command line: they broke the report's writing
        raise ConfigError(f"--set {text!r}: not valid UTF-8 text; use UTF-8 (or ASCII) names and values") from None
    key, eq, raw = str(text).partition("=")
    key, raw = key.strip(), raw.strip()
    path = key.split(".")
    if not eq or not key or not all(p.strip() for p in path):
        raise ConfigError(f"--set {text!r}: expected KEY=VALUE with KEY a dotted field path, e.g. --set swarm.n_uavs=100")
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw
    try:
        _check_key(path)
    except ConfigError as e:
        raise ConfigError(f"--set {text}: {e}") from None
    return path, value


def apply_overrides(data: dict, overrides) -> dict:
    """A copy of the raw config dict with each ``--set KEY=VALUE`` applied (later ones win), before
    validation, so that :func:`parse_config` names the field of a bad value."""
    out = json.loads(json.dumps(data))  # deep copy (TOML values are JSON-able)
    for text in overrides or ():
        path, value = parse_override(text)
        d = out
        for key in path[:-1]:
            if not isinstance(d.get(key), dict):
                d[key] = {}
            d = d[key]
        d[path[-1]] = value
    return out


def load_config(path: str | Path, overrides=None) -> Scenario:
    """Load and validate a scenario TOML file (following its ``base`` chain), with the ``--set
    KEY=VALUE`` ``overrides`` applied before validation. An invalid result caused with overrides
    is reported on one line naming the field(s)."""
    data = _read_toml(Path(path))
    if not overrides:
        return parse_config(data, str(path))
    data = apply_overrides(data, overrides)
    try:
        return Scenario.model_validate(data)
    except ValidationError as e:
        probs = "; ".join(f"field '{'.'.join(str(p) for p in err['loc']) or '(top level)'}': {err['msg']}"
                          + ("" if isinstance(err.get("input"), dict) else f" (got {err.get('input')!r:.60})")
                          for err in e.errors())
        raise ConfigError(f"{path} with --set {' '.join(overrides)}: invalid configuration: {probs}") from None
