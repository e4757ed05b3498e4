"""Exception types of the core, one per concern, all deriving from SwarmnavError."""


class SwarmnavError(Exception):
    """Base class: an error a user can act on (the CLI prints it without a traceback)."""


class ConfigError(SwarmnavError):
    """A scenario/config file is unreadable or invalid; the message names the field."""


class DatasetError(SwarmnavError):
    """A dataset directory is missing, malformed or of an unknown schema version."""


# what a user can change when a solver fails this way (the exception text -> advice)
_SOLVER_ADVICE = (
    ("Indeterminate linear system", "its factor graph became under-constrained or too ill-conditioned to solve; "
     "check that the scenario's sigmas ([init], [sensors.*]) are realistic (not 0 or near 0) and that every UAV "
     "has position information (GNSS, anchors or ranges)"),
    ("not positive definite", "a covariance it built is not positive definite; check the scenario's sigmas"),
)


def describe_estimator_failure(algo: str, seed: int, exc: BaseException) -> str:
    """One line for a user: which estimator failed on which seed, the error's first line, what to do."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    what = f"{type(exc).__name__}: {lines[0] if lines else '(no message)'}"
    advice = next((a for key, a in _SOLVER_ADVICE if key in str(exc)), "")
    if algo == "central" and "Indeterminate linear system" in str(exc):
        # the oracle switches from Cholesky to QR by itself on this error (central.py): QR failed too
        advice += "; the oracle had already switched from Cholesky to QR (both failed)"
    return f"{algo} failed on seed {seed} ({what})" + (f" — {advice}" if advice else "") + "; the full traceback is in the log"
