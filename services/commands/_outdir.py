"""Output directories of the commands: a path that cannot be a directory, or cannot be created, is
one clear SwarmnavError naming the option (not an OSError traceback), checked before the work."""

from __future__ import annotations

from pathlib import Path


def check_out_dir(path: str | Path, flag: str = "--out") -> Path:
    """Refuse ``path`` if it, or the nearest part of it that exists, is not a directory; creates nothing."""
    from swarmnav.errors import SwarmnavError

    p = Path(path)
    if p.exists() and not p.is_dir():
        raise SwarmnavError(f"{flag} {p}: exists and is not a directory; choose another {flag}")
    for parent in p.absolute().parents:
        if parent.exists():
            if not parent.is_dir():
                raise SwarmnavError(f"{flag} {p}: {parent} is not a directory; choose another {flag}")
            break
    return p


def make_out_dir(path: str | Path, flag: str = "--out") -> Path:
    """``check_out_dir`` then create it (with its parents); an OSError (read-only, no such device,
    permission) is a SwarmnavError naming ``flag``."""
    from swarmnav.errors import SwarmnavError

    p = check_out_dir(path, flag)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise SwarmnavError(f"{flag} {p}: cannot create the directory ({e.strerror}); choose another {flag}") from None
    return p
