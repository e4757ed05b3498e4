"""Architecture rules, from the import graph: layers only look down, and nothing goes round in circles.

    core      shared/swarmnav   (models, estimators, protocol, metrics, report assembly): pure
    services  services/         (uav_node, sensor_sim, monitor, commands, runtime helpers)
    deploy    deploy/           (launcher, router, chaos, bench, screenshot): the top of the house

The core imports no services, no deploy, no zenoh and no rerun; services import no deploy (the
`launch` command's entry, which starts the deployment, excepted); no import cycle among the
project's modules (imports inside functions counted too).
"""

import ast
import pathlib

REPO = pathlib.Path(__file__).resolve().parents[1]
ROOTS = {"swarmnav": REPO / "shared" / "swarmnav", "services": REPO / "services", "deploy": REPO / "deploy"}
CORE_FORBIDDEN = {"zenoh", "rerun", "services", "deploy"}
SERVICES_MAY_IMPORT_DEPLOY = {"services.commands.launch"}


def _modname(path: pathlib.Path) -> str:
    for top, root in ROOTS.items():
        if root in path.parents:
            parts = [top, *path.relative_to(root).with_suffix("").parts]
            return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
    raise ValueError(path)


MODULES = {_modname(p): p for root in ROOTS.values() for p in root.rglob("*.py")}


def _raw_imports(name: str, path: pathlib.Path) -> set[str]:
    """Every module named by an import statement of ``path`` (relative imports resolved)."""
    pkg = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    out = set()
    for n in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(n, ast.Import):
            out |= {a.name for a in n.names}
        elif isinstance(n, ast.ImportFrom):
            if n.level:
                base = pkg.split(".")[: len(pkg.split(".")) - (n.level - 1)]
                mod = ".".join(base + ([n.module] if n.module else []))
            else:
                mod = n.module
            out |= {mod} | {f"{mod}.{a.name}" for a in n.names}
    return out


def _project_imports(name: str) -> set[str]:
    """The project modules ``name`` imports (longest known prefix of each imported name)."""
    res = set()
    for m in _raw_imports(name, MODULES[name]):
        parts = m.split(".")
        while parts and ".".join(parts) not in MODULES:
            parts.pop()
        if parts:
            res.add(".".join(parts))
    res.discard(name)
    return res


GRAPH = {m: _project_imports(m) for m in MODULES}


def test_core_imports_no_transport_recording_services_or_deploy():
    offenders = {}
    for m, p in MODULES.items():
        if m.split(".")[0] == "swarmnav":
            bad = {i.split(".")[0] for i in _raw_imports(m, p)} & CORE_FORBIDDEN
            if bad:
                offenders[m] = sorted(bad)
    assert not offenders, f"core modules import outer layers or I/O frameworks: {offenders}"


def test_services_import_no_deploy():
    offenders = {m: sorted(i for i in GRAPH[m] if i.split(".")[0] == "deploy")
                 for m in MODULES if m.startswith("services") and m not in SERVICES_MAY_IMPORT_DEPLOY}
    offenders = {m: v for m, v in offenders.items() if v}
    assert not offenders, f"services import deploy/ (move shared runtime helpers to services/runtime/): {offenders}"


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_no_import_cycles():
    assert _cycles(GRAPH) == []


def test_the_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert "swarmnav.estimators.detection" in GRAPH["swarmnav.estimators.graph"]  # the graph is read
