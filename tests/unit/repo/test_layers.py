"""Who may import whom (docs/architecture.md, Layers), read from the code itself.

    roguecli  (the console script: the library's commands + serve + make-pairs)
      |-> service  -> jobs -> roguenerf     (the API)
      |   workers  -> jobs -> roguenerf     (the worker: a process of its own, nothing imports it)
      |-> roguefit -> roguenerf
      '-> roguenerf (the library imports nothing above it)

``service`` and ``workers`` share ``jobs`` (job table, layout, settings, queue, the job lifecycle)
and never import each other.

Every import counts, a function's lazy one included.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]
PACKAGES = ("roguenerf", "roguefit", "jobs", "service", "workers", "roguecli")
MAY_IMPORT = {
    "roguenerf": {"roguenerf"},
    "roguefit": {"roguefit", "roguenerf"},
    "jobs": {"jobs", "roguenerf"},
    "workers": {"workers", "jobs", "roguenerf"},
    "service": {"service", "jobs", "roguenerf"},
    "roguecli": {"roguecli", "roguenerf", "roguefit", "service", "jobs"},
}


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every import in a file, at any depth, relative ones resolved."""
    package = ".".join(path.relative_to(ROOT).with_suffix("").parts)
    if path.name != "__init__.py":
        package = package.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            module = node.module or ""
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                module = ".".join(base + ([module] if module else []))
            found += [(node.lineno, module)] + [(node.lineno, f"{module}.{a.name}") for a in node.names
                                                 if (ROOT / module.replace(".", "/") / f"{a.name}.py").is_file()]
    return found


def _files(package: str) -> list[Path]:
    return sorted((ROOT / package).rglob("*.py"))


@pytest.mark.parametrize("package", PACKAGES)
def test_each_package_imports_only_the_layers_below_it(package):
    offenders = [f"{path.relative_to(ROOT)}:{line}: {module}"
                 for path in _files(package) for line, module in _imports(path)
                 if module.split(".")[0] in PACKAGES and module.split(".")[0] not in MAY_IMPORT[package]]
    assert offenders == []


def test_nothing_imports_the_console_script_package():
    offenders = [f"{path.relative_to(ROOT)}:{line}" for package in PACKAGES if package != "roguecli"
                 for path in _files(package) for line, module in _imports(path)
                 if module.split(".")[0] == "roguecli"]
    assert offenders == []


def test_the_issue_grep_finds_nothing_in_the_library():
    proc = subprocess.run(["grep", "-rnE", r"^\s*(from|import) (jobs|service|workers|roguefit|roguecli)", "roguenerf/"],
                          cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 1 and proc.stdout == ""  # 1: no line matched


def _module_graph(package: str) -> dict[str, set[str]]:
    """The imports between a package's modules (its ``__init__`` as the package's own name)."""
    graph = {}
    for path in _files(package):
        name = f"{package}.{path.stem}" if path.stem != "__init__" else package
        graph[name] = {m for _, m in _imports(path) if m != name and (
            m == package or m.startswith(f"{package}.") and (ROOT / (m.replace(".", "/") + ".py")).is_file())}
    return graph


def _workers_graph() -> dict[str, set[str]]:
    return _module_graph("workers")


def _jobs_graph() -> dict[str, set[str]]:
    return _module_graph("jobs")


def _circles(graph: dict[str, set[str]]) -> list[str]:
    """Every import circle a depth-first walk meets (a node still on its own path), as "a -> b -> a"."""
    state: dict[str, str] = {}
    found: list[str] = []

    def visit(node: str, trail: list[str]) -> None:
        state[node] = "open"
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == "open":
                found.append(" -> ".join(trail + [node, nxt]))
            elif nxt not in state:
                visit(nxt, trail + [node])
        state[node] = "done"

    for node in sorted(graph):
        if node not in state:
            visit(node, [])
    return found


TASKS = ("workers.tasks", "workers.paths", "workers.imports")
"""The worker's kinds of job: each a body run through the one lifecycle, ``jobs.lifecycle``."""


def test_workers_modules_import_each_other_without_cycles():
    graph = _workers_graph()
    # The tasks share the job lifecycle (jobs/lifecycle.py) and never import each other.
    for task in TASKS:
        assert not graph[task] & set(TASKS), task
    assert set(TASKS) <= graph["workers.dispatch"] and "workers.dispatch" in graph["workers.worker"]
    # A DAG: a depth-first walk never meets a module still on its own path.
    circles = _circles(graph)
    assert not circles, f"import cycle: {circles[0]}"


def test_jobs_modules_import_each_other_without_cycles():
    """Bottom up: ``db``, ``layout``, ``settings`` and ``queue`` import nothing of the package,
    ``store`` the database, ``data`` the layout and the store, ``lifecycle`` (the one job lifecycle
    the tasks share) the database, the layout and the store; nothing of the package imports it."""
    graph = _jobs_graph()
    # A DAG: a depth-first walk never meets a module still on its own path.
    circles = _circles(graph)
    assert not circles, f"import cycle: {circles[0]}"
    assert graph["jobs"] == set()  # the package's __init__ holds only its docstring
    for leaf in ("jobs.db", "jobs.layout", "jobs.settings", "jobs.queue"):
        assert graph[leaf] == set(), leaf
    assert graph["jobs.store"] == {"jobs.db"}
    assert graph["jobs.data"] <= {"jobs.layout", "jobs.store"}
    assert graph["jobs.lifecycle"] <= {"jobs.db", "jobs.layout", "jobs.store"}
    assert not [name for name, deps in graph.items() if "jobs.lifecycle" in deps]


@pytest.mark.parametrize("graph_of, check, importer, imported, circle", [
    # worker -> dispatch -> tasks: tasks -> worker closes it.
    ("_workers_graph", test_workers_modules_import_each_other_without_cycles, "workers.tasks", "workers.worker",
     "workers.tasks -> workers.worker"),
    # store -> db: db -> store closes it.
    ("_jobs_graph", test_jobs_modules_import_each_other_without_cycles, "jobs.db", "jobs.store",
     "jobs.store -> jobs.db -> jobs.store"),
])
def test_the_cycle_check_catches_a_cycle(monkeypatch, graph_of, check, importer, imported, circle):
    """The checks above can fail: one arrow more closes a circle, and the check names it."""
    graph = getattr(sys.modules[__name__], graph_of)()
    graph[importer] = graph[importer] | {imported}
    monkeypatch.setattr(sys.modules[__name__], graph_of, lambda: graph)
    with pytest.raises(AssertionError, match=f"import cycle: .*{circle}"):
        check()


def test_roguefit_modules_import_each_other_without_cycles():
    """A kind of field's module (its config and fitter) imports neither the orchestration
    (``pairs``), nor the registry that lists it, nor the package: ``registry`` imports the kinds,
    ``pairs`` the registry (CONTRIBUTING.md, Adding a kind of field)."""
    graph = _module_graph("roguefit")
    above = {"roguefit", "roguefit.pairs", "roguefit.registry", "roguefit.batch"}
    for kind in ("roguefit.fit", "roguefit.field", "roguefit.hashfield", "roguefit.splats"):
        assert not graph[kind] & above, kind
    assert graph["roguefit.fitter"] <= {"roguefit.photos"}
    assert "roguefit.registry" in graph["roguefit.pairs"]
    assert {"roguefit.fit", "roguefit.hashfield", "roguefit.splats"} <= graph["roguefit.registry"]
    assert "roguefit.splats" not in graph["roguefit.fit"]  # the import circle of issue 50
    circles = _circles(graph)
    assert not circles, f"import cycle: {circles[0]}"


@pytest.mark.parametrize("package", ["jobs", "service", "workers"])
def test_the_job_layer_the_api_and_the_workers_take_only_the_library_public_names(package):
    """``jobs``, ``service`` and ``workers`` use the library as its users do: ``from roguenerf
    import NAME`` with NAME in ``roguenerf.__all__`` (the public submodules ``runtime`` and
    ``native`` among them), never a module inside it."""
    import roguenerf

    found = []
    for path in _files(package):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                found += [(path.name, a.name, None) for a in node.names if a.name.split(".")[0] == "roguenerf"]
            elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "roguenerf":
                found += [(path.name, node.module, a.name) for a in node.names]
    assert found, f"{package} uses the library"
    # ``import roguenerf`` (the package itself: its import sets the process's OpenMP policy) is public too.
    offenders = [f for f in found if f[1] != "roguenerf" or (f[2] is not None and f[2] not in roguenerf.__all__)]
    assert offenders == []


def test_the_api_settings_live_in_the_service_and_extend_the_shared_ones():
    from jobs import settings as job_settings
    from jobs.settings import JobSettings
    from service.settings import Settings

    assert issubclass(Settings, JobSettings) and Settings.__module__ == "service.settings"
    assert not hasattr(job_settings, "Settings")
    assert {"api_key", "max_body_bytes", "cors_origins"} <= set(Settings.model_fields)
    assert not {"api_key", "max_body_bytes", "cors_origins"} & set(JobSettings.model_fields)


def _dotted_graph(package: str) -> dict[str, set[str]]:
    """Every module of ``package`` (sub-packages included, a package as its ``__init__``) and the
    modules of the same package it imports, at any depth. A module's import of a package it
    belongs to (its ``__init__``) is not an arrow: Python runs that ``__init__`` first anyway."""
    names = {}
    for path in _files(package):
        parts = path.relative_to(ROOT).with_suffix("").parts
        names[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    graph = {}
    for name, path in names.items():
        edges = set()
        for _, module in _imports(path):
            while module and module not in names:
                module = module.rpartition(".")[0]
            if module and module != name and not name.startswith(module + "."):
                edges.add(module)
        graph[name] = edges
    return graph


@pytest.mark.parametrize("package", [*PACKAGES, "bench"])
def test_no_package_has_an_import_circle(package):
    graph = _dotted_graph(package)
    assert len(graph) > 3
    circles = _circles(graph)
    assert not circles, f"import cycle: {circles[0]}"
    # The check can fail: an arrow back from the first module a module imports closes a circle.
    name = next(n for n in sorted(graph) if graph[n])
    target = sorted(graph[name])[0]
    graph[target] = graph[target] | {name}
    assert _circles(graph)


def test_service_and_workers_never_import_each_other():
    """The issue's check: both import ``jobs`` and the library, and neither imports the other
    (the grep, and every import the AST holds, a function's lazy one included)."""
    for package, other in (("service", "workers"), ("workers", "service")):
        proc = subprocess.run(["grep", "-rnE", rf"^\s*(from|import) {other}\b", f"{package}/"],
                              cwd=ROOT, capture_output=True, text=True)
        assert proc.returncode == 1 and proc.stdout == "", proc.stdout  # 1: no line matched
        assert not [m for path in _files(package) for _, m in _imports(path) if m.split(".")[0] == other]


def test_routers_take_shared_dependencies_from_deps_not_from_each_other():
    offenders = [f"{path.name}:{line}: {module}" for path in _files("service/routers")
                 for line, module in _imports(path) if module.startswith("service.routers.")]
    assert offenders == []


LIBRARY_LAYERS = (
    ("errors", "fastpath", "profiling", "runtime"),
    ("images", "native"),
    ("geometry", "imageio", "metrics", "video"),  # camera maths and files
    ("ops",),  # the kernels: native, fast or reference per op
    ("reprojection",),  # checked reprojection on the ops
    ("data", "models", "enhance"),
    ("checkpoint", "inference", "trajectory"),
    ("splats", "training"),
    ("__main__",),  # says where the command line is (package roguecli, above the library)
)
"""Inside the library, bottom up: a module imports only its own unit and units of lower layers
(docs/architecture.md, Layers). A unit is a top-level module or sub-package of ``roguenerf``."""


def _library_arrows() -> list[tuple[str, str, str]]:
    """(importer unit, imported unit, where) for every import between units of the library."""
    arrows = []
    for path in _files("roguenerf"):
        parts = path.relative_to(ROOT).with_suffix("").parts
        if len(parts) < 2 or parts[1] == "__init__":
            continue  # the package's own lazy re-exports
        for line, module in _imports(path):
            target = module.split(".")
            if target[0] == "roguenerf" and len(target) > 1 and target[1] != parts[1]:
                arrows.append((parts[1], target[1], f"{path.relative_to(ROOT)}:{line}"))
    return arrows


def _library_problems(arrows: list[tuple[str, str, str]]) -> list[str]:
    """Arrows that run up a layer, and import circles between units (same layer included)."""
    layer = {unit: k for k, units in enumerate(LIBRARY_LAYERS) for unit in units}
    problems = [f"{where}: {a} -> {b} runs up" for a, b, where in arrows if layer[b] > layer[a]]
    graph: dict[str, set[str]] = {}
    for a, b, _ in arrows:
        graph.setdefault(a, set()).add(b)
    return problems + [f"import circle: {c}" for c in _circles(graph)]


def test_no_arrow_inside_the_library_runs_back_up():
    units = {p.relative_to(ROOT / "roguenerf").with_suffix("").parts[0] for p in _files("roguenerf")} - {"__init__"}
    assert units == {u for layer in LIBRARY_LAYERS for u in layer}, "every unit of the library has a layer"
    assert _library_problems(_library_arrows()) == []


def test_the_library_layer_check_catches_an_arrow_up_and_a_circle():
    arrows = _library_arrows()
    assert ("reprojection", "ops", "roguenerf/reprojection.py") in {(a, b, w.split(":")[0]) for a, b, w in arrows}
    up = _library_problems(arrows + [("geometry", "ops", "x.py:1")])
    assert up[0] == "x.py:1: geometry -> ops runs up"  # and it closes the circle ops -> geometry -> ops
    assert len(up) == 2 and up[1].startswith("import circle") and up[1].endswith("geometry -> ops -> geometry")
    circle = _library_problems(arrows + [("data", "enhance", "x.py:1"), ("enhance", "data", "y.py:1")])
    assert circle and all("import circle" in c for c in circle) and "data -> enhance -> data" in circle[0]
