"""`swarmnav simulate` (not implemented yet)."""

HELP = "simulate (not implemented yet)"


def add_arguments(p):
    pass


def run(args) -> int:
    raise SystemExit("swarmnav simulate: not implemented yet")
