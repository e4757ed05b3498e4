"""`swarmnav evaluate` (not implemented yet)."""

HELP = "evaluate (not implemented yet)"


def add_arguments(p):
    pass


def run(args) -> int:
    raise SystemExit("swarmnav evaluate: not implemented yet")
