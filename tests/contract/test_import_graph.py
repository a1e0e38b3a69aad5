"""The import graph of src/rigidbench has no cycle, counting every import statement (inside functions too)."""

import ast
from pathlib import Path

import rigidbench

PACKAGE_DIR = Path(rigidbench.__file__).parent


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_prefix(node: ast.ImportFrom, package: str) -> str:
    """The absolute module a ``from X import ...`` statement in ``package`` names (relative levels resolved)."""
    if not node.level:
        return node.module or ""
    base = package.split(".")
    base = base[:len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imported_modules(path: Path, modules: set[str]) -> set[str]:
    """Our modules that the file at ``path`` imports anywhere (top level or inside functions)."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            prefix = import_prefix(node, package)
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
# heavy package at top level), or if the importing file is the command line (it imports its stages lazily so that
# `rigidbench --help` is instant).

HEAVY_PACKAGES = {"bpy", "mathutils", "torch", "torchvision", "transformers", "diffusers", "peft", "matplotlib",
                  "ray", "cv2", "av", "lpips", "pytorch_msssim", "OpenEXR", "sklearn"}
# The command line: the modules of the "entry" layer of LAYERS below (cli.py and the commands/ package).
LAZY_IMPORT_LAYER = "entry"
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
                prefix = import_prefix(child, package)
                external = None if child.level else prefix.partition(".")[0]
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
        if top_level(name) in dict(LAYERS)[LAZY_IMPORT_LAYER]:
            continue
        for line, target, top, _ in import_statements(f, modules):
            if target and not top and target not in heavy and (name, target) not in CYCLE_BREAKERS:
                problems[f"{f.relative_to(PACKAGE_DIR.parent)}:{line}: {target}"] = None
    assert not problems, ("function-level imports of light modules of ours (import them at the top of the file):\n"
                          + "\n".join(problems))


# -- layers: which packages may import which ---------------------------------------------------------------
#
# Every top-level module or package of src/rigidbench sits in one layer, lowest first. A module may import
# modules of its own layer or a lower one, never of a higher one (inside functions too): so the low layers can be
# used and tested without the stages, and a stage never needs the command line. Cycles inside a layer are
# caught by test_no_import_cycles. "rigidbench" is the package root (``__version__`` and the model-facing
# ``Benchmark``); importing it is free, since Python has run it before any module of the package.

LAYERS: list[tuple[str, tuple[str, ...]]] = [
    ("base", ("errors", "extras", "atomic", "jsonio", "hashing", "rotations", "argtypes", "registry", "folders",
              "logsafe")),
    ("core", ("config", "context", "manifest", "scene_spec", "video", "firstframe", "executors", "driver")),
    ("domain", ("rigidbench", "blender", "groundtruth", "benchmark", "datasets", "metrics", "readouts", "perception",
                "predictors", "stats", "evaluation", "submissions")),
    ("stages", ("train", "probe", "report", "validation", "preflight", "stages", "flows", "leaderboard")),
    ("entry", ("commands", "cli", "__main__")),
]
ROOT = PACKAGE_DIR.name  # "rigidbench"
# Blender's own modules, importable only inside Blender's Python (bpy) and imported only under blender/.
BLENDER_MODULES = {"bpy", "mathutils", "bmesh", "addon_utils", "bpy_extras"}
BLENDER_PACKAGE = f"{ROOT}.blender"


def layer_index() -> dict[str, int]:
    """Top-level name -> its layer's position in LAYERS (0 lowest)."""
    return {name: k for k, (_, names) in enumerate(LAYERS) for name in names}


def top_level(module: str) -> str:
    """The top-level module or package of ours that ``module`` lives in ("rigidbench" for the root)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def our_files() -> list[Path]:
    return sorted(PACKAGE_DIR.rglob("*.py"))


def layer_violations(imports: dict[str, list[tuple[str, int, str]]], layers: dict[str, int]) -> list[str]:
    """``imports``: importing module -> [(where, line, imported module)]. One line per import of a higher
    layer's module, naming both modules and their layers; imports of the package root are free."""
    names = {k: name for k, (name, _) in enumerate(LAYERS)}
    problems: dict[str, None] = {}  # ordered, without repeats (one line may import several names of one module)
    for module, found in imports.items():
        own = layers[top_level(module)]
        for where, line, target in found:
            theirs = layers[top_level(target)]
            if target != ROOT and theirs > own:
                problems[f"{where}:{line}: {module} ({names[own]}) imports {target} ({names[theirs]})"] = None
    return list(problems)


def test_the_layer_check_finds_an_upward_import():
    layers = {"rigidbench": 2, "errors": 0, "blender": 2, "report": 3}
    render = [("render.py", 3, "rigidbench.errors"), ("render.py", 9, "rigidbench.report.x"),
              ("render.py", 9, "rigidbench.report.x")]  # one line importing two names of one module
    imports = {"rigidbench.blender.render": render,
               "rigidbench.errors": [("errors.py", 1, "rigidbench")]}  # the root: free
    assert layer_violations(imports, layers) == [
        "render.py:9: rigidbench.blender.render (domain) imports rigidbench.report.x (stages)"]


def test_every_top_level_module_has_one_layer():
    listed = [name for _, names in LAYERS for name in names]
    assert len(listed) == len(set(listed)), "a name is in two layers"
    present = {top_level(module_name(f)) for f in our_files()}
    assert present - set(listed) == set(), "put these top-level modules in a layer of LAYERS"
    assert set(listed) - present == set(), "these LAYERS entries name no module of src/rigidbench any more"


def test_no_module_imports_a_higher_layer():
    files = our_files()
    modules = {module_name(f) for f in files}
    imports = {module_name(f): [(str(f.relative_to(PACKAGE_DIR.parent)), line, target)
                                for line, target, _, _ in import_statements(f, modules) if target]
               for f in files}
    problems = layer_violations(imports, layer_index())
    assert not problems, "imports of a higher layer (see LAYERS):\n" + "\n".join(problems)


def test_only_the_blender_package_imports_blender_modules():
    """bpy and Blender's other modules are imported under rigidbench/blender/ only, counting every import
    statement (inside functions too), so the rest of the package runs without Blender."""
    files = our_files()
    modules = {module_name(f) for f in files}
    seen, problems = set(), []
    for f in files:
        name = module_name(f)
        for line, _, _, external in import_statements(f, modules):
            if external in BLENDER_MODULES:
                seen.add(name)
                if not (name == BLENDER_PACKAGE or name.startswith(BLENDER_PACKAGE + ".")):
                    problems.append(f"{f.relative_to(PACKAGE_DIR.parent)}:{line}: imports {external}")
    assert not problems, "Blender modules imported outside rigidbench/blender/:\n" + "\n".join(problems)
    assert {"rigidbench.blender.session", "rigidbench.blender.render", "rigidbench.blender.assets.scenes"} <= seen


# -- private names stay in their module ----------------------------------------------------------------
#
# A name with one leading underscore is private to the module that defines it, and a module named _x to its
# package: no other module imports it, or reads it as an attribute of a module it imported. What modules
# share has a public name. (module, name) pairs in PRIVATE_IMPORTS_ALLOWED would be the justified
# exceptions; keep it empty.

PRIVATE_IMPORTS_ALLOWED: set[tuple[str, str]] = set()


def _is_private(part: str) -> bool:
    return part.startswith("_") and not part.startswith("__")


def private_reach(importer: str, dotted: str, modules: set[str]) -> str | None:
    """The first private part of ``dotted`` (a module or a name in one) that ``importer`` may not reach, as
    ``owner.part``, or None. A private module ``a._m`` is reachable from the modules of package ``a``; a
    private name ``a.m._x`` from module ``a.m`` only."""
    parts = dotted.split(".")
    for i, part in enumerate(parts):
        if _is_private(part):
            owner, reached = ".".join(parts[:i]), ".".join(parts[:i + 1])
            inside = importer.startswith(owner + ".") if reached in modules else importer == owner
            if not inside:
                return reached
    return None


def private_uses(source: str, importer: str, is_package: bool, modules: set[str]):
    """(line, private name) for each import of another module's private name in ``source`` (the module
    ``importer``), and each read of one as an attribute of a module of ours bound by an import."""
    package = importer if is_package else importer.rpartition(".")[0]
    tree = ast.parse(source)
    bound: dict[str, str] = {}  # local name -> our module it is bound to
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            prefix = import_prefix(node, package)
            for alias in node.names:
                dotted = f"{prefix}.{alias.name}"
                if dotted in modules:
                    bound[alias.asname or alias.name] = dotted
                if prefix.partition(".")[0] == ROOT and (bad := private_reach(importer, dotted, modules)):
                    yield node.lineno, bad
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name in modules and alias.asname:
                    bound[alias.asname] = alias.name
                if alias.name.partition(".")[0] == ROOT and (bad := private_reach(importer, alias.name, modules)):
                    yield node.lineno, bad
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in bound
                and (bad := private_reach(importer, f"{bound[node.value.id]}.{node.attr}", modules))):
            yield node.lineno, bad


def test_the_private_name_check():
    modules = {"rigidbench.a", "rigidbench.a.tables", "rigidbench.a._mesh", "rigidbench.a.figures", "rigidbench.b"}
    source = ("from rigidbench.a.tables import _num, fmt\n"  # a private name of another module
              "from . import _mesh\n"  # a private module of its own package: fine
              "from ._mesh import box\n"
              "from . import tables as T\n"
              "x = T._grouping(1) + T.fmt\n"  # read as an attribute
              "from rigidbench import __version__\n")
    assert list(private_uses(source, "rigidbench.a.figures", False, modules)) == [
        (1, "rigidbench.a.tables._num"), (5, "rigidbench.a.tables._grouping")]
    # the package's private module is out of reach from another package
    assert list(private_uses("from rigidbench.a._mesh import box\n", "rigidbench.b", False, modules)) == [
        (1, "rigidbench.a._mesh")]
    # a private name of a package's __init__ is its own, also for the package's modules
    assert list(private_uses("from . import _CACHE\n", "rigidbench.a.tables", False, modules)) == [
        (1, "rigidbench.a._CACHE")]


def test_no_module_uses_another_modules_private_names():
    files = our_files()
    modules = {module_name(f) for f in files}
    problems = [f"{f.relative_to(PACKAGE_DIR.parent)}:{line}: {name}"
                for f in files
                for line, name in private_uses(f.read_text(), module_name(f), f.name == "__init__.py", modules)
                if (module_name(f), name) not in PRIVATE_IMPORTS_ALLOWED]
    assert not problems, ("private names used outside their module (give them a public name):\n"
                          + "\n".join(problems))
