"""The docs name what exists: every backticked name in docs/*.md and README.md that points into the
code (``swarmnav.x.y``, ``services.x``, ``file.py``, ``dir/file.py``, ``module.attr`` of a known
core/service/deploy module, ``Class.attr`` of a project class, ``tests/x.py::test``, a bare
``_private`` helper, a bare ``test_*`` or a bare CamelCase class) resolves in the source.

Resolution reads the source with ``ast`` (nothing is imported): a module's names are its top-level
defs, classes, assignments and imports; a class's are its methods, class attributes, annotated
fields and ``self.x = ...`` attributes, with its project base classes'. Config keys, table columns
and other spans that only look like module attributes are listed in ``NOT_CODE`` with the reason;
names of other libraries in ``EXTERNAL``. docs/history.md is a dated log of what was, so it is not
checked.
"""

from __future__ import annotations

import ast
import pathlib
import re
import sys
from functools import cache

sys.path.insert(0, str(pathlib.Path(__file__).parent))
from test_architecture import ROOTS, _modname  # noqa: E402  (one module-name mapping for both tests)

REPO = pathlib.Path(__file__).resolve().parents[1]
DOCS = sorted(p for p in (REPO / "docs").glob("*.md") if p.name != "history.md") + [REPO / "README.md"]

# spans that look like ``module.attr`` / ``Class.attr`` but are not code: -> why
NOT_CODE = {
    "config.estimation": "the dataset meta's resolved config table (meta.json)",
    "imu.t": "a column of the imu table",
    "sensors.imu.slave.arw_dpsh": "a scenario config key",
    "earth.earth_rate_radps": "a scenario config key ([earth])",
    "report.json": "an output file",
    "ranges.t": "a column of the ranges table",
    "scenario.seed": "a scenario config key",
    "sensors.uwb.sigma_m": "a scenario config key",
    "evaluation.seeds_role": "a report.json key",
}
# names of other libraries (gtsam, scipy, zenoh, the MILUV recording) a doc mentions bare
EXTERNAL = {"CombinedImuFactor", "GPSFactor", "IncrementalFixedLagSmoother", "Rotation", "Slerp", "FifoChannel",
            "CongestionControl"}
_FILE_SUFFIXES = (".json", ".json5", ".md", ".toml", ".parquet", ".npz", ".rrd", ".csv", ".yaml", ".log", ".pem",
                  ".png", ".jnl", ".lock", ".txt")


@cache
def _modules() -> dict[str, pathlib.Path]:
    return {_modname(p): p for root in ROOTS.values() for p in root.rglob("*.py")}


@cache
def _tree(name: str) -> ast.Module:
    return ast.parse(_modules()[name].read_text())


def _class_names(c: ast.ClassDef) -> set[str]:
    out = set()
    for n in c.body:
        if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            out.add(n.name)
        elif isinstance(n, ast.Assign):
            out |= {t.id for t in n.targets if isinstance(t, ast.Name)}
        elif isinstance(n, ast.AnnAssign) and isinstance(n.target, ast.Name):
            out.add(n.target.id)
    for n in ast.walk(c):  # instance attributes
        if isinstance(n, ast.Attribute) and isinstance(n.ctx, ast.Store) and ast.unparse(n.value) == "self":
            out.add(n.attr)
    return out


@cache
def _classes() -> dict[str, list[tuple[set[str], list[str]]]]:
    """class name -> [(its names, its base class names)] over every project module."""
    out: dict[str, list] = {}
    for mod in _modules():
        for n in ast.walk(_tree(mod)):
            if isinstance(n, ast.ClassDef):
                bases = [ast.unparse(b).rsplit(".", 1)[-1] for b in n.bases]
                out.setdefault(n.name, []).append((_class_names(n), bases))
    return out


def _class_has(cls: str, attr: str, seen: frozenset = frozenset()) -> bool:
    for names, bases in _classes().get(cls, []):
        if attr in names or any(_class_has(b, attr, seen | {cls}) for b in bases if b not in seen | {cls}):
            return True
    return False


@cache
def _top_names(mod: str) -> set[str]:
    out = set()
    for n in _tree(mod).body:
        if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            out.add(n.name)
        elif isinstance(n, ast.Assign):
            for t in n.targets:
                out |= {e.id for e in ast.walk(t) if isinstance(e, ast.Name)}
        elif isinstance(n, ast.AnnAssign) and isinstance(n.target, ast.Name):
            out.add(n.target.id)
        elif isinstance(n, (ast.Import, ast.ImportFrom)):
            out |= {(a.asname or a.name).split(".")[0] for a in n.names}
    pkg = mod + "."
    out |= {m[len(pkg):].split(".")[0] for m in _modules() if m.startswith(pkg)}  # submodules
    return out


@cache
def _all_defined() -> set[str]:
    """Every def, class, assigned name and attribute the project defines (for bare names)."""
    out = set()
    for mod in _modules():
        for n in ast.walk(_tree(mod)):
            if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                out.add(n.name)
            elif isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store):
                out.add(n.id)
            elif isinstance(n, ast.Attribute) and isinstance(n.ctx, ast.Store):
                out.add(n.attr)
    return out


def _resolve_in_module(mod: str, chain: list[str]) -> bool:
    """``chain`` (attr, [attr]) inside module ``mod``: a top-level name, then a class's attribute,
    or a submodule's name."""
    if not chain:
        return True
    head, rest = chain[0], chain[1:]
    if f"{mod}.{head}" in _modules():
        return _resolve_in_module(f"{mod}.{head}", rest)
    if head not in _top_names(mod):
        return False
    if not rest:
        return True
    cls = [n for n in ast.walk(_tree(mod)) if isinstance(n, ast.ClassDef) and n.name == head]
    if cls:
        return _class_has(head, rest[0])
    # an imported name: resolve it where it comes from (one level: ``from .x import Name``)
    return _class_has(head, rest[0]) if head in _classes() else True


def _basenames() -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for m in _modules():
        out.setdefault(m.rsplit(".", 1)[-1], []).append(m)
    return out


@cache
def _files() -> set[str]:
    return ({p.name for d in ("shared", "services", "deploy", "tests", "bench") for p in (REPO / d).rglob("*.py")}
            | {p.name for p in REPO.glob("*.py")})  # setup.py


def check(span: str) -> str | None:
    """None if ``span`` is not a code name or resolves; else why it does not."""
    s = re.sub(r"\(.*\)$", "", span.strip())
    if s in NOT_CODE or s in EXTERNAL or "<" in s:  # <...>: a placeholder
        return None
    if s.startswith("::"):  # a test of the file named just before
        tests = {n.name for p in (REPO / "tests").glob("test_*.py") for n in ast.walk(ast.parse(p.read_text()))
                 if isinstance(n, ast.FunctionDef)}
        return None if s[2:] in tests else f"no test {s[2:]}"
    if "::" in s:
        path, func = s.split("::", 1)
        p = REPO / path
        if not p.is_file():
            return f"no file {path}"
        names = {n.name for n in ast.walk(ast.parse(p.read_text())) if isinstance(n, (ast.FunctionDef, ast.ClassDef))}
        return None if func in names else f"no {func} in {path}"
    if s.endswith(".py") or (s.endswith("/") and re.match(r"(shared|services|deploy|tests|swarmnav)/", s)):
        if "/" not in s:
            return None if s in _files() else f"no file named {s}"
        for base in (REPO, REPO / "shared", REPO / "shared" / "swarmnav", REPO / "services"):
            if (base / s).exists():
                return None
        return f"no path {s}"
    if not re.fullmatch(r"[A-Za-z_]\w*(\.\w+)*", s) or s.endswith(_FILE_SUFFIXES):
        return None
    parts = s.split(".")
    if parts[0] in ("swarmnav", "services", "deploy"):
        for i in range(len(parts), 0, -1):
            mod = ".".join(parts[:i])
            if mod in _modules():
                return None if _resolve_in_module(mod, parts[i:]) else f"{'.'.join(parts[i:])} not in {mod}"
        return f"no module {s}"
    if len(parts) > 1 and parts[0] in _basenames():
        mods = _basenames()[parts[0]]
        return None if any(_resolve_in_module(m, parts[1:]) for m in mods) else \
            f"{'.'.join(parts[1:])} not in {' / '.join(mods)}"
    if len(parts) > 1 and parts[0] in _classes():
        return None if _class_has(parts[0], parts[1]) else f"class {parts[0]} has no {parts[1]}"
    if len(parts) == 1:
        if s.startswith("_") and not s.startswith("__"):
            return None if s in _all_defined() else f"no {s} anywhere in the code"
        if s.startswith("test_"):
            tests = {n.name for p in (REPO / "tests").glob("test_*.py") for n in ast.walk(ast.parse(p.read_text()))
                     if isinstance(n, ast.FunctionDef)}
            return None if s in tests else f"no test {s}"
        if re.fullmatch(r"[A-Z][a-z0-9]+[A-Z]\w*", s):  # CamelCase (two humps or more): a class
            return None if s in _all_defined() else f"no class {s}"
    return None


def _spans(path: pathlib.Path) -> list[tuple[int, str]]:
    text = re.sub(r"```.*?```", lambda m: "\n" * m.group(0).count("\n"), path.read_text(), flags=re.S)
    return [(i + 1, m) for i, line in enumerate(text.splitlines()) for m in re.findall(r"`([^`]+)`", line)]


def test_every_code_name_in_the_docs_exists():
    bad = [f"{p.relative_to(REPO)}:{line}: `{span}`: {why}"
           for p in DOCS for line, span in _spans(p) if (why := check(span))]
    assert not bad, "docs name code that does not exist:\n" + "\n".join(bad)


def test_the_checker_catches_stale_names():
    assert check("graph.GraphEstimator._round_cov") and check("_normal_equations") and check("TruthLabel")
    assert check("swarmnav.estimators.graph.nothing") and check("estimators/nothing.py")
    assert check("tests/test_graph.py::test_nothing")
    for ok in ("rounds.normal_equations", "swarmnav.protocol.node_epoch", "EpochSlicer.epoch", "graph.py",
               "services/settings.py", "NodeState.bearings", "tests/test_graph.py::test_round_sandwich_covariance",
               "imu.InitialRest", "scenario.Estimation", "commit_weight", "report.json"):
        assert check(ok) is None, (ok, check(ok))
