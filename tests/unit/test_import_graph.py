"""The import graph of src/rigidbench has no cycle, counting every import statement (inside functions too)."""

import ast
from pathlib import Path

import rigidbench

PACKAGE_DIR = Path(rigidbench.__file__).parent


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_modules(path: Path, modules: set[str]) -> set[str]:
    """Our modules that the file at ``path`` imports anywhere (top level or inside functions)."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                prefix = ".".join(base + ([node.module] if node.module else []))
            else:
                prefix = node.module or ""
            targets = [prefix] + [f"{prefix}.{alias.name}" for alias in node.names]
        else:
            continue
        for target in targets:
            # the deepest module of ours that the name refers to (a module, or a name defined in one)
            while target and target not in modules:
                target = target.rpartition(".")[0]
            if target and target != name:
                found.add(target)
    return found


def import_graph() -> dict[str, set[str]]:
    files = sorted(PACKAGE_DIR.rglob("*.py"))
    modules = {module_name(f) for f in files}
    return {module_name(f): imported_modules(f, modules) for f in files}


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle as [a, b, ..., a], or None (iterative depth-first search)."""
    state: dict[str, int] = {}  # 1 on the stack, 2 done
    for root in graph:
        if state.get(root):
            continue
        stack = [(root, iter(sorted(graph[root])))]
        path = [root]
        state[root] = 1
        while stack:
            node, children = stack[-1]
            child = next(children, None)
            if child is None:
                state[node] = 2
                stack.pop()
                path.pop()
            elif state.get(child) == 1:
                return path[path.index(child):] + [child]
            elif not state.get(child):
                state[child] = 1
                stack.append((child, iter(sorted(graph.get(child, ())))))
                path.append(child)
    return None


def test_the_cycle_finder_finds_a_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_relative_imports_resolve_to_our_modules():
    graph = import_graph()
    assert "rigidbench.errors" in graph["rigidbench.registry"]
    assert "rigidbench.predictors.base" in graph["rigidbench.predictors"]
    assert "rigidbench.metrics.common" in graph["rigidbench.metrics"]


def test_no_import_cycles():
    graph = import_graph()
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


# -- function-level imports of our own modules ---------------------------------------------------------
#
# Function-level imports are kept for heavy third-party packages only: our own light modules are imported at
# the top of the file so the dependency graph is visible. A function may import one of our modules only if it
# is heavy (it, a package it lives in, or one of our modules it imports at top level, transitively, imports a
# heavy package at top level), or if the importing file is the CLI (it imports its stages lazily so that
# `rigidbench --help` is instant).

HEAVY_PACKAGES = {"bpy", "mathutils", "torch", "torchvision", "transformers", "diffusers", "peft", "matplotlib",
                  "ray", "cv2", "av", "lpips", "pytorch_msssim", "OpenEXR", "sklearn"}
LAZY_IMPORTS_ALLOWED_IN = {"rigidbench.cli"}
# (importing module, imported module) pairs whose function-level import breaks a cycle that could not be
# restructured away. Keep this empty.
CYCLE_BREAKERS: set[tuple[str, str]] = set()

_FUNCTIONS = (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)


def import_statements(path: Path, modules: set[str]):
    """(line, our module imported or None, at top level?, else the third-party top-level package or None),
    one per imported name, for each import statement in the file (the file importing itself counts as None).

    ``from . import x`` imports the submodule x where there is one; ``from .mod import name`` imports mod.
    Top level means outside any function body (module level, including under ``if``/``try`` and class bodies).
    """
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]

    def ours(target: str) -> str | None:
        while target and target not in modules:
            target = target.rpartition(".")[0]
        return target or None

    def visit(node, top: bool):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Import):
                for alias in child.names:
                    yield child.lineno, ours(alias.name), top, alias.name.partition(".")[0]
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base = package.split(".")
                    base = base[:len(base) - (child.level - 1)]
                    prefix = ".".join(base + ([child.module] if child.module else []))
                    external = None
                else:
                    prefix = child.module or ""
                    external = prefix.partition(".")[0]
                for alias in child.names:
                    yield child.lineno, ours(f"{prefix}.{alias.name}"), top, external
            else:
                yield from visit(child, top and not isinstance(child, _FUNCTIONS))

    for line, target, top, external in visit(ast.parse(path.read_text(), str(path)), True):
        yield line, (target if target != name else None), top, (None if target else external)


def heavy_modules() -> set[str]:
    """Our modules whose import (at top level, transitively, parent packages included) imports a heavy package."""
    files = sorted(PACKAGE_DIR.rglob("*.py"))
    modules = {module_name(f) for f in files}
    deps: dict[str, set[str]] = {}
    heavy = set()
    for f in files:
        name = module_name(f)
        parts = name.split(".")
        # importing a.b.c runs a/__init__ and a/b/__init__ first
        deps[name] = {".".join(parts[:i]) for i in range(1, len(parts))}
        for _, target, top, external in import_statements(f, modules):
            if top and target:
                deps[name].add(target)
            if top and external in HEAVY_PACKAGES:
                heavy.add(name)
    changed = True
    while changed:
        changed = False
        for name, targets in deps.items():
            if name not in heavy and targets & heavy:
                heavy.add(name)
                changed = True
    return heavy


def test_heavy_modules_are_found():
    heavy = heavy_modules()
    assert "rigidbench.metrics.lpips_net" in heavy  # imports torch at top level
    assert "rigidbench.blender.session" not in heavy  # imports bpy inside its functions only
    assert "rigidbench.cli" not in heavy
    assert "rigidbench" not in heavy


def test_function_level_imports_of_our_modules_are_heavy_only():
    """Our light modules are imported at the top of the file; only heavy ones (and the CLI's stages) lazily."""
    files = sorted(PACKAGE_DIR.rglob("*.py"))
    modules = {module_name(f) for f in files}
    heavy = heavy_modules()
    problems: dict[str, None] = {}  # ordered, without repeats (one line may import several names of one module)
    for f in files:
        name = module_name(f)
        if name in LAZY_IMPORTS_ALLOWED_IN:
            continue
        for line, target, top, _ in import_statements(f, modules):
            if target and not top and target not in heavy and (name, target) not in CYCLE_BREAKERS:
                problems[f"{f.relative_to(PACKAGE_DIR.parent)}:{line}: {target}"] = None
    assert not problems, ("function-level imports of light modules of ours (import them at the top of the file):\n"
                          + "\n".join(problems))
