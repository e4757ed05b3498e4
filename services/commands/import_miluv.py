"""`swarmnav import-miluv` (not implemented yet)."""

HELP = "import-miluv (not implemented yet)"


def add_arguments(p):
    pass


def run(args) -> int:
    raise SystemExit("swarmnav import-miluv: not implemented yet")
