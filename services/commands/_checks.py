"""Checks shared by the commands: output directories (a path that cannot be a directory, or cannot be
created, is one clear SwarmnavError naming the option, not an OSError traceback, checked before the
work) and notes on a scenario (fault windows that never happen)."""

from __future__ import annotations

from pathlib import Path


def check_out_dir(path: str | Path, flag: str = "--out") -> Path:
    """Refuse ``path`` if it, or the nearest part of it that exists, is not a directory; creates nothing."""
    from swarmnav.errors import SwarmnavError

    p = Path(path)
    try:
        str(p.absolute()).encode("utf-8")
    except UnicodeEncodeError:  # the Rerun recording (and JSON) need a UTF-8 path: it failed after the work
        raise SwarmnavError(f"{flag} {p}: the path is not valid UTF-8; choose a UTF-8 (or ASCII) name") from None
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


def note_faults_after_end(sc, command: str) -> None:
    """Say on stderr which of the scenario's fault windows never happen (they start after its end)."""
    import sys

    late = sc.faults_after_end()
    if late:
        print(f"swarmnav {command}: note: {', '.join(late)} start(s) after the scenario's end "
              f"({sc.scenario.duration_s:g} s) and will not happen", file=sys.stderr)
