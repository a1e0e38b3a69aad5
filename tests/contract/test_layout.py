"""Where things live (tests/README.md and docs/architecture.md say why): every command's run function in the
command layer, one module per stage that imports no other stage, no path tricks in the tests, short functions."""

import ast
from pathlib import Path

from test_import_graph import PACKAGE_DIR, import_statements, module_name, our_files

TESTS_DIR = Path(__file__).resolve().parents[1]
COMMANDS_PACKAGE = "rigidbench.commands"
STAGES_PACKAGE = "rigidbench.stages"
#: (importing stage module, imported stage module): probe intervene runs the bases stage first
STAGE_IMPORTS_ALLOWED = {("rigidbench.stages.probe_intervene", "rigidbench.stages.probe_bases")}
MAX_FUNCTION_LINES = 80
#: the functions still longer than MAX_FUNCTION_LINES (module.function); shorten one and strike it here
LONG_FUNCTIONS_ALLOWED = {"rigidbench.predictors.hosted.predict", "rigidbench.train.trainer._train"}


def functions(tree: ast.AST):
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            yield node


def command_functions_outside(files: dict[str, str], package: str) -> list[str]:
    """``files``: module -> source. One line per ``def cmd_*`` in a module outside ``package``."""
    return [f"{module}:{node.lineno}: {node.name}" for module, source in files.items()
            if not (module == package or module.startswith(package + "."))
            for node in functions(ast.parse(source)) if node.name.startswith("cmd_")]


def long_functions(files: dict[str, str], limit: int) -> dict[str, int]:
    """module.function -> its length in lines (decorators aside, docstring included), for those over ``limit``."""
    return {f"{module}.{node.name}": node.end_lineno - node.lineno + 1 for module, source in files.items()
            for node in functions(ast.parse(source)) if node.end_lineno - node.lineno + 1 > limit}


def sources() -> dict[str, str]:
    return {module_name(f): f.read_text() for f in our_files()}


def test_the_checks_find_what_they_look_for():
    files = {"rigidbench.commands.data": "def cmd_render(args, ctx):\n    pass\n",
             "rigidbench.stages.render": "def cmd_show(args, ctx):\n    pass\n\ndef render_rows():\n    pass\n",
             "rigidbench.report": "def build():\n" + "    x = 1\n" * 80}
    assert command_functions_outside(files, COMMANDS_PACKAGE) == ["rigidbench.stages.render:1: cmd_show"]
    assert long_functions(files, MAX_FUNCTION_LINES) == {"rigidbench.report.build": 81}
    assert long_functions(files, 81) == {}


def test_command_run_functions_live_in_the_command_layer():
    """Each command's arguments and what it runs sit together in rigidbench/commands/: no ``cmd_*`` elsewhere."""
    problems = command_functions_outside(sources(), COMMANDS_PACKAGE)
    assert not problems, "cmd_* functions outside rigidbench.commands (move them there):\n" + "\n".join(problems)


def test_every_stage_module_holds_a_stage_and_imports_no_other_stage():
    files = our_files()
    modules = {module_name(f) for f in files}
    stage_modules = sorted(m for m in modules if m.startswith(STAGES_PACKAGE + "."))
    assert len(stage_modules) >= 9, stage_modules
    problems = []
    for f in files:
        name = module_name(f)
        if name not in stage_modules:
            continue
        tree = ast.parse(f.read_text())
        stages = [node.name for node in tree.body if isinstance(node, ast.ClassDef)
                  and any(getattr(base, "id", None) == "Stage" for base in node.bases)]
        if not stages:
            problems.append(f"{name}: defines no Stage")
        for line, target, _, _ in import_statements(f, modules):
            if target in stage_modules and (name, target) not in STAGE_IMPORTS_ALLOWED:
                problems.append(f"{f.relative_to(PACKAGE_DIR.parent)}:{line}: imports {target}")
    assert not problems, "stage modules (one stage each, none importing another):\n" + "\n".join(problems)


def test_no_test_changes_sys_path():
    """Tests import the fixtures package (pyproject.toml puts tests/ on pytest's path; children get it from
    ``fixtures.child_env()``), never by inserting folders into sys.path."""
    needle = "sys.path." + "insert"  # (split, so that this file does not match itself)
    found = [f"{path.relative_to(TESTS_DIR)}:{n}" for path in sorted(TESTS_DIR.rglob("*.py"))
             for n, line in enumerate(path.read_text().splitlines(), 1) if needle in line]
    assert not found, "sys.path changed in tests (import from the fixtures package instead):\n" + "\n".join(found)


def test_functions_are_at_most_80_lines_but_the_listed_few():
    long = long_functions(sources(), MAX_FUNCTION_LINES)
    new = {name: n for name, n in long.items() if name not in LONG_FUNCTIONS_ALLOWED}
    assert not new, f"functions over {MAX_FUNCTION_LINES} lines (split them): {new}"
    shortened = LONG_FUNCTIONS_ALLOWED - set(long)
    assert not shortened, f"now {MAX_FUNCTION_LINES} lines or fewer: strike them from LONG_FUNCTIONS_ALLOWED: {shortened}"


JSON_WRITER_MODULE = "rigidbench.jsonio"


def json_writers_outside(files: dict[str, str], module: str) -> list[str]:
    """One line per function that wraps a JSON writer (``*write_json``, ``*atomic_json``) outside ``module``."""
    return [f"{name}:{node.lineno}: {node.name}" for name, source in files.items() if name != module
            for node in functions(ast.parse(source)) if node.name.endswith(("write_json", "atomic_json"))]


def test_json_files_are_written_through_one_writer():
    """``jsonio.write_json`` (atomic, durable on request) is the one JSON writer: no module wraps it again."""
    files = {"rigidbench.probe.store": "def atomic_json(path, doc):\n    pass\n", JSON_WRITER_MODULE:
             "def write_json(path, doc):\n    pass\n"}
    assert json_writers_outside(files, JSON_WRITER_MODULE) == ["rigidbench.probe.store:1: atomic_json"]
    problems = json_writers_outside(sources(), JSON_WRITER_MODULE)
    assert not problems, "JSON writers beside rigidbench.jsonio.write_json (call it instead):\n" + "\n".join(problems)
