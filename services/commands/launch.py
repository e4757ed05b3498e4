"""`swarmnav launch` (not implemented yet)."""

HELP = "launch (not implemented yet)"


def add_arguments(p):
    pass


def run(args) -> int:
    raise SystemExit("swarmnav launch: not implemented yet")
