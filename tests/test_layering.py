"""The layers of DESIGN.md hold: the domain library never reaches the orchestrator, and model code never reaches
the procedural world (a recorded log and a procedural one go through the same code)."""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LIBRARY = ROOT / "omniscs"
#: Model packages (present and future) and the viewer: they may not import the procedural world.
MODEL_PACKAGES = ("nsg", "scs", "agents", "background", "annotate", "eval", "viewer")
#: Model packages under DESIGN.md's layers: they may import the ground and data floors, never what sits above them.
MODELS = ("nsg", "agents", "background", "scs")
#: The product and wiring floors above the models (evaluation, annotation, closed loop, stages, benchmarks, CLI).
ABOVE_MODELS = ("omniscs.eval", "omniscs.annotate", "omniscs.closedloop", "omniscs.pipeline", "omniscs.bench",
                "omniscs.cli", "omniscs.server")
#: Top floors that start flows or serve requests; everything else in omniscs/ is Prefect-free.
TOP_FLOORS = ("cli",)


def imported_modules(path: Path, root: Path = ROOT) -> list[tuple[int, str]]:
    """Every module a file imports (absolute names; relative imports resolved against its package)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = ".".join(path.relative_to(root).with_suffix("").parts[:-1])
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parts + ([base] if base else []))
            found.append((node.lineno, base))
            found += [(node.lineno, f"{base}.{alias.name}") for alias in node.names]
    return found


def violations(files, forbidden, root: Path = ROOT) -> list[str]:
    return [f"{f.relative_to(root)}:{line} imports {name}" for f in files for line, name in imported_modules(f, root)
            if any(name == bad or name.startswith(bad + ".") for bad in forbidden)]


def library_files(exclude=()) -> list[Path]:
    return [f for f in LIBRARY.rglob("*.py") if f.relative_to(LIBRARY).parts[0] not in exclude]


def test_the_domain_library_never_imports_prefect_tasks_or_flows():
    assert violations(library_files(exclude=TOP_FLOORS), ("prefect", "tasks", "flows")) == []


def test_model_code_never_imports_the_procedural_world():
    files = [f for f in library_files() if f.relative_to(LIBRARY).parts[0] in MODEL_PACKAGES]
    assert files, "no model package found"
    assert violations(files, ("omniscs.world",)) == []


def test_model_code_never_imports_the_floors_above_it():
    files = [f for f in library_files() if f.relative_to(LIBRARY).parts[0] in MODELS]
    assert files, "no model package found"
    assert violations(files, ABOVE_MODELS) == []


def test_the_check_itself_sees_a_forbidden_import(tmp_path):
    fake = tmp_path / "omniscs" / "nsg" / "probe.py"
    fake.parent.mkdir(parents=True)
    fake.write_text("from omniscs.world import generate_world\nfrom ..world import layouts\nimport prefect\n"
                    "from omniscs.worldly import x\n")
    names = violations([fake], ("omniscs.world", "prefect"), root=tmp_path)
    # the module and its name, the relative module and its name, prefect; never a mere prefix like "worldly"
    assert len(names) == 5 and not any("worldly" in n for n in names)


def import_graph(root: Path = ROOT) -> dict[str, set[str]]:
    """Module -> the library modules it imports anywhere in its body (a package's own parents left out: a module
    importing the package it belongs to is how packages are built, not a circle)."""
    modules = {}
    for f in (root / "omniscs").rglob("*.py"):
        name = ".".join(f.relative_to(root).with_suffix("").parts).removesuffix(".__init__")
        modules[name] = f
    graph = {}
    for name, f in modules.items():
        deps = set()
        for _, imported in imported_modules(f, root):
            parts = imported.split(".")
            while parts and ".".join(parts) not in modules:
                parts.pop()
            dep = ".".join(parts)
            if dep and dep != name and not name.startswith(dep + "."):
                deps.add(dep)
        graph[name] = deps
    return graph


def import_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected groups of more than one module (each an import circle)."""
    order, low, stack, on_stack, circles = {}, {}, [], set(), []

    def visit(v: str) -> None:
        order[v] = low[v] = len(order)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in order:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], order[w])
        if low[v] == order[v]:
            group = []
            while not group or group[-1] != v:
                group.append(stack.pop())
                on_stack.discard(group[-1])
            if len(group) > 1:
                circles.append(sorted(group))

    for v in sorted(graph):
        if v not in order:
            visit(v)
    return circles


def test_no_two_library_modules_import_each_other_even_inside_functions():
    assert import_circles(import_graph()) == []


def test_the_circle_check_itself_finds_a_circle():
    assert import_circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
