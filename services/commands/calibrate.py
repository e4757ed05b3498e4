"""`swarmnav calibrate` (not implemented yet)."""

HELP = "calibrate (not implemented yet)"


def add_arguments(p):
    pass


def run(args) -> int:
    raise SystemExit("swarmnav calibrate: not implemented yet")
