"""Low-level readers of a MILUV experiment folder: CSV tables (csv module + numpy, no pandas: the
UWB files contain quoted fields such as ``"(11, 2)"``), the YAML config (PyYAML), vectors, numbers,
time-series cleaning, the robot folders and the experiment's row of ``config/experiments.csv``."""

from __future__ import annotations

import csv
import math
import re
from pathlib import Path

import numpy as np
import yaml

from swarmnav.errors import DatasetError

from .constants import ANCHOR_NODE_OFFSET

_ROBOT_RE = re.compile(r"^ifo0*(\d+)$")


def read_csv(path: Path, columns: list[str]) -> dict[str, np.ndarray]:
    """Numeric columns of a CSV file (csv module: quoted fields are fine), as float arrays.

    Rows are returned in file order. Raises DatasetError naming the file, column and line for a
    missing file/column or a value that is not a number.
    """
    if not path.is_file():
        raise DatasetError(f"{path}: missing file{compressed_hint(path)}")
    with open(path, newline="", encoding="utf-8-sig") as f:  # -sig: a byte-order mark is not part of the first name
        reader = csv.reader(f)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise DatasetError(f"{path}: empty file (no header)") from None
        missing = [c for c in columns if c not in header]
        if missing:
            raise DatasetError(f"{path}: missing columns {missing} (has {header[:12]}{'...' if len(header) > 12 else ''})")
        idx = [header.index(c) for c in columns]
        out: list[list[float]] = []
        for line, row in enumerate(reader, start=2):
            if not row or all(not x.strip() for x in row):
                continue  # blank line
            if len(row) != len(header):
                raise DatasetError(f"{path}:{line}: {len(row)} fields, header has {len(header)} (unquoted comma?)")
            vals = []
            for c, i in zip(columns, idx):
                s = row[i].strip()
                try:
                    vals.append(float(s) if s else math.nan)
                except ValueError:
                    raise DatasetError(f"{path}:{line}: column {c!r} is not a number: {s[:40]!r}") from None
            out.append(vals)
    arr = np.array(out, float).reshape(-1, len(columns))
    return {c: arr[:, j] for j, c in enumerate(columns)}


def compressed_hint(path: Path) -> str:
    for ext in (".gz", ".bz2", ".xz", ".zip"):
        if path.with_name(path.name + ext).is_file():
            return f" (found {path.name + ext}: decompress it first, the importer reads plain .csv as MILUV ships them)"
    return ""


def read_yaml(path: Path) -> dict:
    """A MILUV config file as a dict (PyYAML ``safe_load``), every mapping key as a string.

    MILUV quotes its keys (``"0":``, ``"10":``) and most values (``"[1.0, 2.0, 3.0]"``,
    ``"-0.0924"``); keys are turned into strings so that an unquoted ``0:`` means the same.
    Raises DatasetError naming the file for a missing file, invalid YAML or a top level that is not
    a mapping.
    """
    if not path.is_file():
        raise DatasetError(f"{path}: missing config file")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise DatasetError(f"{path}: not valid YAML: {' '.join(str(e).split())}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a mapping at the top level, got {type(data).__name__}")
    return _str_keys(data)


def _str_keys(d: dict) -> dict:
    return {str(k): _str_keys(v) if isinstance(v, dict) else v for k, v in d.items()}


def parse_vector(s, n: int, where: str) -> tuple[float, ...]:
    """'[a, b, c]', '[a b c]' or a YAML list [a, b, c] -> n finite floats."""
    parts = list(s) if isinstance(s, (list, tuple)) else [p for p in re.split(r"[\s,]+", str(s).strip().strip("[]()")) if p]
    try:
        v = tuple(float(p) for p in parts)
    except (TypeError, ValueError):
        raise DatasetError(f"{where}: not a vector of numbers: {s!r}") from None
    if len(v) != n or not all(math.isfinite(x) for x in v):
        raise DatasetError(f"{where}: expected {n} finite numbers, got {s!r}")
    return v


def nonneg_float(d: dict, key: str, where: str) -> float:
    """d[key] as a finite float >= 0 (a YAML number or a numeric string)."""
    if key not in d:
        raise DatasetError(f"{where}: missing key {key!r}")
    try:
        v = float(d[key])
    except (TypeError, ValueError):
        raise DatasetError(f"{where}: {key} is not a number: {d[key]!r}") from None
    if not math.isfinite(v) or v < 0:
        raise DatasetError(f"{where}: {key} must be finite and >= 0, got {v}")
    return v


def clean_time_series(t: np.ndarray, cols: dict[str, np.ndarray], where: str, summary: dict) -> tuple[np.ndarray, dict]:
    """Drop non-finite rows, sort by time (stable), drop repeated timestamps (keep first)."""
    ok = np.isfinite(t)
    for v in cols.values():
        ok &= np.isfinite(v)
    n_bad = int((~ok).sum())
    t = t[ok]
    cols = {k: v[ok] for k, v in cols.items()}
    order = np.argsort(t, kind="stable")
    n_unsorted = int(np.any(np.diff(t) < 0))
    t = t[order]
    cols = {k: v[order] for k, v in cols.items()}
    keep = np.ones(len(t), bool)
    keep[1:] = np.diff(t) > 0
    n_dup = int((~keep).sum())
    if n_bad or n_dup or n_unsorted:
        summary.setdefault("cleaning", {})[where] = {"non_finite_rows": n_bad, "repeated_timestamps": n_dup, "was_unsorted": bool(n_unsorted)}
    if keep.sum() < 2:
        raise DatasetError(f"{where}: fewer than 2 valid rows")
    return t[keep], {k: v[keep] for k, v in cols.items()}


def warn(summary: dict, msg: str) -> None:
    """A warning for the user: kept in the summary and printed by ``import-miluv`` on stderr."""
    summary.setdefault("warnings", []).append(msg)


def robot_folders(src: Path) -> list[tuple[str, int]]:
    """[(folder name, UAV id)] of the ``ifo00N`` folders, sorted by name."""
    out = []
    for d in sorted(src.iterdir()):
        m = _ROBOT_RE.match(d.name)
        if d.is_dir() and m:
            out.append((d.name, int(m.group(1))))
    if not out:
        raise DatasetError(f"{src}: no robot folders (ifo001, ifo002, ...) — is this a MILUV experiment folder? "
                           "Give the folder of one experiment, e.g. .../data/default_3_random_0")
    ids = [i for _, i in out]
    if len(set(ids)) != len(ids) or min(ids) < 1 or max(ids) >= ANCHOR_NODE_OFFSET:
        raise DatasetError(f"{src}: robot ids {ids} must be unique and in 1..{ANCHOR_NODE_OFFSET - 1}")
    return out


def find_config(src: Path, config_dir: str | Path | None = None) -> Path:
    """MILUV's ``config/`` folder: the one given, else ``SRC/config`` (an experiment copied with its
    config), ``SRC/../config`` or ``SRC/../../config`` (the devkit's layout: ``miluv/data/<exp>/`` beside
    ``miluv/config/``) — the first that has ``experiments.csv``."""
    if config_dir is not None:
        cfg = Path(config_dir)
        if not (cfg / "experiments.csv").is_file():
            raise DatasetError(f"--config-dir {cfg}: no experiments.csv there (expected MILUV's config/ folder: "
                               "experiments.csv, uwb/anchors.yaml, uwb/tags.yaml, height/bias.yaml, imu/ifo00N/px4_imu.yaml)")
        return cfg
    tried = [src / "config", src.parent / "config", src.parent.parent / "config"]
    for cfg in tried:
        if (cfg / "experiments.csv").is_file():
            return cfg
    raise DatasetError(f"{src}: MILUV's config/ folder not found (looked for experiments.csv in "
                       f"{', '.join(str(c) for c in tried)}); give it with --config-dir "
                       "(the devkit's config/ folder: github.com/decargroup/miluv)")


def experiment_row(cfg: Path, name: str) -> dict[str, str]:
    """The row of ``config/experiments.csv`` whose ``experiment`` is ``name``."""
    p = cfg / "experiments.csv"
    with open(p, newline="", encoding="utf-8-sig") as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        if (r.get("experiment") or "").strip() == name:
            return {k.strip(): (v or "").strip() for k, v in r.items() if k is not None}
    raise DatasetError(f"{p}: experiment {name!r} not listed (the source folder must keep its MILUV name, "
                       "or give the name with --experiment)")
