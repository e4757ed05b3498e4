"""Architecture rules: the core (package `swarmnav`) is pure — no zenoh, no rerun imports."""

import ast
import pathlib

CORE = pathlib.Path(__file__).resolve().parents[1] / "shared" / "swarmnav"
FORBIDDEN = {"zenoh", "rerun"}


def _imports(path: pathlib.Path) -> set[str]:
    tree = ast.parse(path.read_text(), str(path))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module.split(".")[0])
    return out


def test_core_never_imports_transport_or_recording():
    offenders = {str(p.relative_to(CORE)): sorted(_imports(p) & FORBIDDEN) for p in CORE.rglob("*.py")}
    offenders = {k: v for k, v in offenders.items() if v}
    assert not offenders, f"core modules import I/O frameworks: {offenders}"


def test_core_files_exist():
    assert len(list(CORE.rglob("*.py"))) >= 5
