"""Provenance of a run: git revision, config hash and package versions. No absolute paths, no clocks."""

from __future__ import annotations

import hashlib
import json
import subprocess
from importlib import metadata
from pathlib import Path

PACKAGES = ("swarmnav", "numpy", "gtsam", "eclipse-zenoh", "rerun-sdk", "scikit-learn", "pydantic", "pyarrow",
            "pymap3d", "matplotlib")
_REPO = Path(__file__).resolve().parents[1]


def git_revision(repo: Path = _REPO) -> str:
    """`<sha>` or `<sha>-dirty` (tracked files modified); "unknown" outside a git checkout."""
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True, text=True, timeout=10,
                             check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=repo,
                               capture_output=True, text=True, timeout=10).stdout.strip()
        return sha + ("-dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def package_versions(names=PACKAGES) -> dict[str, str]:
    out = {}
    for n in names:
        try:
            out[n] = metadata.version(n)
        except metadata.PackageNotFoundError:
            continue
    return out


def dataset_sha256(meta) -> str:
    """A dataset's config hash: the one it records, else a hash of its metadata."""
    if getattr(meta, "config_sha256", None):
        return meta.config_sha256
    blob = json.dumps(meta.model_dump(mode="json", by_alias=True), sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest()


def provenance(config_sha256: str) -> dict:
    return {"git": git_revision(), "config_sha256": config_sha256, "packages": package_versions()}
