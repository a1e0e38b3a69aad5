"""configs/paper_numbers.yaml against the paper itself, and its loader.

The LaTeX tables are read here with a small parser of their own (rows split at \\\\, cells at &, \\textbf and
\\underline dropped), independent of the loader: every number of the data file must equal the table's as
printed, at its precision, and every row and column of the table must be in the file. Skipped when the
paper (shared/paper/rigidbench.tex beside the checkout) is not there.
"""

from __future__ import annotations

import math
import re
import tomllib
from decimal import Decimal
from pathlib import Path

import pytest
import yaml

from rigidbench.config import PACKAGE_CONFIG_DIR
from rigidbench.errors import ConfigError
from rigidbench.metrics import GROUPS, METRICS
from rigidbench.predictors import PREDICTORS, Kind
from rigidbench.report.analysis import PARTITION_LABELS, TASK_ORDER
from rigidbench.report.paper import PAPER_NUMBERS_FILE, load_paper_numbers, parse_paper_numbers, unscale

PAPER_TEX = Path(__file__).parents[2].parent / "shared/paper/rigidbench.tex"
REPO = Path(__file__).parents[2]


@pytest.fixture(scope="module")
def tex() -> str:
    if not PAPER_TEX.is_file():
        pytest.skip(f"the paper is not at {PAPER_TEX} (shared/ is absent beside this checkout)")
    return PAPER_TEX.read_text()


@pytest.fixture(scope="module")
def raw() -> dict:
    return yaml.safe_load(PAPER_NUMBERS_FILE.read_text())


# -------------------------------------------------------------------------- an independent LaTeX reader


def braced(text: str, start: int) -> tuple[str, int]:
    """The content of the {...} group opening at text[start] and the index after its closing brace."""
    assert text[start] == "{", text[start:start + 20]
    depth = 0
    for i in range(start, len(text)):
        depth += {"{": 1, "}": -1}.get(text[i], 0)
        if depth == 0:
            return text[start + 1:i], i + 1
    raise AssertionError("unbalanced braces")


def table_env(tex: str, label: str) -> str:
    """The table environment that holds \\label{label}."""
    at = tex.index(f"\\label{{{label}}}")
    return tex[tex.rindex("\\begin{table}", 0, at):tex.index("\\end{table}", at)]


def plain(text: str) -> str:
    """LaTeX cell or caption text as plain text: formatting commands dropped, ~ a space, $...$ unwrapped."""
    while True:
        new = re.sub(r"\\(?:textbf|underline|mathbf)\{([^{}]*)\}", r"\1", text)
        if new == text:
            break
        text = new
    text = text.replace("~", " ").replace("$", "")
    return re.sub(r"\s+", " ", text).strip()


def split_rows(block: str) -> list[list[str]]:
    """Rows of a tabular block (split at \\\\), each a list of raw cells (split at &); rules and spacing
    commands removed; empty rows dropped."""
    block = re.sub(r"\\cmidrule\([a-z]*\)\{[^}]*\}|\\addlinespace(\[[^]]*\])?", "", block)
    rows = [r.strip() for r in block.split("\\\\")]
    return [[c.strip() for c in r.split("&")] for r in rows if r]


def arrow(cell: str) -> str:
    return "higher" if "\\uparrow" in cell else "lower" if "\\downarrow" in cell else ""


def heading(cell: str) -> str:
    return plain(re.sub(r"\\(?:up|down)arrow", "", cell))


def spans(cells: list[str]) -> list[str]:
    """One entry per column of a header row with \\multicolumn{n}{c}{text}: text repeated n times."""
    out = []
    for cell in cells:
        m = re.fullmatch(r"\\multicolumn\{(\d+)\}\{[^}]*\}\{(.*)\}", cell)
        out += [m.group(2)] * int(m.group(1)) if m else [cell]
    return out


def parse_table(tex: str, label: str) -> dict:
    """{title, caption, header: [cells], groups: [cell per column] or None, rows: [[label, cells...]]}."""
    env = table_env(tex, label)
    cap_at = env.index("\\caption{")
    caption, _ = braced(env, cap_at + len("\\caption"))
    title_raw, after = braced(caption, caption.index("\\textbf{") + len("\\textbf"))
    head = split_rows(env[env.index("\\toprule") + len("\\toprule"):env.index("\\midrule")])
    body = split_rows(env[env.index("\\midrule") + len("\\midrule"):env.index("\\bottomrule")])
    groups = spans(head[0]) if len(head) > 1 else None
    return {"title": plain(title_raw).rstrip("."), "caption": plain(caption[after:]), "header": head[-1],
            "groups": groups, "rows": body}


def number(cell: str) -> Decimal:
    text = plain(cell).replace(",", "")
    assert re.fullmatch(r"-?\d*\.\d+|-?\d+", text), cell
    return Decimal(text)


# ------------------------------------------------------------------------------------- the reader itself


def test_the_reader_reads_a_hand_written_table():
    tex = r"""\begin{table}[H]
  \begin{tabular}{lrr}
    \toprule
    & \multicolumn{2}{c}{Motion} \\
    \cmidrule(lr){2-3}
    Model & IoU$\uparrow$ & L2$\downarrow$ \\
    \midrule
    Wan~2.2 & \textbf{.183} & \underline{1.20} \\
    \addlinespace[2pt]
    Base & .5 & 2 \\
    \bottomrule
  \end{tabular}
  \caption{\textbf{A title.} Means over 100 examples. BGDrift is multiplied by $10^3$.}
  \label{tab:x}
\end{table}"""
    t = parse_table(tex, "tab:x")
    assert t["title"] == "A title" and t["caption"] == "Means over 100 examples. BGDrift is multiplied by 10^3."
    assert [heading(c) for c in t["header"]] == ["Model", "IoU", "L2"]
    assert [arrow(c) for c in t["header"]] == ["", "higher", "lower"]
    assert t["groups"] == ["", "Motion", "Motion"]
    assert [plain(r[0]) for r in t["rows"]] == ["Wan 2.2", "Base"]
    assert [number(c) for c in t["rows"][0][1:]] == [Decimal(".183"), Decimal("1.20")]
    assert -number(t["rows"][0][2]).as_tuple().exponent == 2  # the printed precision survives


# ------------------------------------------------------------------------------ the data file vs. the paper


def test_every_number_row_and_column_equals_the_papers_table(tex, raw):
    for key, table in raw["tables"].items():
        t = parse_table(tex, table["label"])
        where = f"{key} ({table['label']})"
        # every column of the paper, in order, with its heading; every row, in order, with its label
        assert [heading(c) for c in t["header"][1:]] == [c["paper"] for c in table["columns"]], where
        assert [plain(r[0]) for r in t["rows"]] == [plain(r["paper"]) for r in table["rows"]], where
        for row, tex_row in zip(table["rows"], t["rows"]):
            assert len(tex_row) == 1 + len(table["columns"]) == 1 + len(row["values"]), (where, row["paper"])
            for col, value, cell in zip(table["columns"], row["values"], tex_row[1:]):
                printed = number(cell)
                decimals = -printed.as_tuple().exponent
                assert col["decimals"] == decimals, (where, row["paper"], col["paper"], cell)
                assert Decimal(repr(float(value))) == printed, (where, row["paper"], col["paper"], value, cell)


def test_titles_captions_and_examples_per_cell_are_the_papers(tex, raw):
    for key, table in raw["tables"].items():
        t = parse_table(tex, table["label"])
        assert table["title"] == t["title"], key
        assert " ".join(table["caption"].split()) == t["caption"], key
        counts = {int(n) for n in re.findall(r"(\d+)(?:-example| examples)", t["caption"])}
        assert counts == {table["cell_examples"]}, (key, counts)


def test_directions_and_metric_ids_agree_with_the_paper_and_our_registry(tex, raw):
    for key, table in raw["tables"].items():
        t = parse_table(tex, table["label"])
        columns = table["columns"]
        for k, col in enumerate(columns):
            info = METRICS[col["metric"]]
            assert col["better"] == info.direction, (key, col)
            printed = arrow(t["header"][1 + k]) or (arrow(t["groups"][1 + k]) if t["groups"] else "")
            if printed:
                assert printed == col["better"], (key, col)
            elif "Lower is better" in t["caption"]:
                assert col["better"] == "lower", (key, col)
            else:
                pytest.fail(f"{key}: the paper gives no direction for {col['paper']}")
            if table["by"] == "model":
                # the paper's column groups are our metric groups; its headings our display names
                assert heading(t["groups"][1 + k]) == GROUPS[info.group], (key, col)
                assert col["paper"] == info.display_name, (key, col)
            elif t["groups"]:  # the metric heads a group of columns
                assert heading(t["groups"][1 + k]) == info.display_name, (key, col)
            else:  # one metric: the title or caption names it
                assert info.display_name in f"{t['title']} {t['caption']}", (key, col)
            if col.get("scale", 1) != 1:
                assert f"{info.display_name} is multiplied by 10^{round(math.log10(col['scale']))}" in t["caption"]
                assert col["scale"] == info.display_scale, (key, col)


def test_group_ids_name_our_tasks_and_partitions(raw):
    for key, table in raw["tables"].items():
        groups = [c.get("group") for c in table["columns"]]
        if table["by"] == "model":
            assert groups == [None] * len(groups), key
        elif table["by"] == "task":
            assert all(g in TASK_ORDER for g in groups), key
            assert [c["paper"] for c in table["columns"]] == [g.replace("_", " ").capitalize() for g in groups]
        else:
            assert [c["paper"] for c in table["columns"]] == [PARTITION_LABELS[g] for g in groups], key


def test_model_ids_are_ours(raw):
    hosted = set(yaml.safe_load((PACKAGE_CONFIG_DIR / "models.yaml").read_text())["models"])
    seen = set()
    for table in raw["tables"].values():
        for row in table["rows"]:
            model = row.get("model")
            if model is None:
                continue
            seen.add(model)
            assert model in PREDICTORS, model
            if PREDICTORS[model].kind == Kind.HOSTED:
                assert model in hosted, model
    # the eight models of the comparison each map to a distinct model of ours
    assert len({r["model"] for r in raw["tables"]["model-results"]["rows"]}) == 8
    assert seen == {r["model"] for r in raw["tables"]["model-results"]["rows"]}


def test_the_papers_own_tables_agree_with_one_another():
    """Cross-checks within the paper (no LaTeX needed): each model's ATE-3D is the mean of its five task means
    (20 examples each) within rounding, and base Wan's rows in the fine-tuning tables are Wan 2.2's."""
    paper = load_paper_numbers()
    overall = {c.row: c.printed for c in paper.tables["model-results"].cells() if c.metric == "ate3d"}
    by_task: dict[str, list[float]] = {}
    for c in paper.tables["task-ate3d"].cells():
        by_task.setdefault(c.row, []).append(c.printed)
    assert set(by_task) == set(overall) and all(len(v) == 5 for v in by_task.values())
    for row, values in by_task.items():
        # five means rounded to +-0.005 each, and the overall mean rounded to +-0.005
        assert abs(sum(values) / 5 - overall[row]) <= 0.010 + 1e-9, row
    base = [c.printed for c in paper.tables["finetuning-tasks"].cells() if c.row == "Wan 2.2"]
    assert base == by_task["Wan 2.2"]
    splits = paper.tables["finetuning-splits"]
    wan = {c.metric: c.printed for c in paper.tables["model-results"].cells() if c.row == "Wan 2.2"}
    for metric in ("ate3d", "ssim"):
        values = [c.printed for c in splits.cells() if c.row == "Wan 2.2" and c.metric == metric]
        full = wan[metric]
        assert len(values) == 4 and abs(sum(values) / 4 - full) <= (0.010 if metric == "ate3d" else 0.001) + 1e-9


# ------------------------------------------------------------------------------------------ the loader


def test_loader_returns_typed_rows_with_unscaled_values_and_finite_counts():
    paper = load_paper_numbers()
    assert paper.marker == "reported in the paper, not re-scored here"
    assert (paper.dataset, paper.protocol, paper.perception, paper.examples) == \
        ("rigidbench-eval", "rigidbench-v1", "neural", 100)
    t = paper.tables["model-results"]
    assert (t.label, t.by, t.cell_examples, len(t.rows), len(t.columns)) == ("tab:model-results", "model", 100, 8, 10)
    cells = {(c.row, c.metric): c for c in t.cells()}
    assert len(cells) == 80
    bg = cells[("Wan 2.2", "bgdrift")]
    assert (bg.printed, bg.value, bg.text) == (0.739, 0.000739, "0.739")  # printed x 10^3, stored as the runs do
    assert cells[("Grok Imagine", "ate3d")].text == "2.30"  # the printed precision, trailing zero kept
    assert cells[("Veo 3.1", "iddrift")].n_finite == 98  # the paper's only cell with non-finite values
    assert sum(c.n_finite != 100 for c in cells.values()) == 1
    lora = next(r for r in paper.tables["finetuning-splits"].rows if r.paper_label == "LoRA 1k")
    assert (lora.model, lora.checkpoint) == ("wan-2.2", "LoRA (rank 32) at step 1,000")
    assert paper.tables["finetuning-splits"].cell(lora, "ssim", "ood_scene").printed == 0.916
    assert paper.tables["finetuning-splits"].cell(lora, "iou", None) is None
    assert unscale(1.094, 1000.0) == 0.001094 and unscale(2.64, 1.0) == 2.64


def test_the_data_file_is_package_data():
    rules = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["rigidbench"]
    package = PAPER_NUMBERS_FILE.parents[1]
    assert any(PAPER_NUMBERS_FILE in set(package.glob(rule)) for rule in rules), rules


@pytest.mark.parametrize("edit, message", [
    (lambda d: d["tables"]["task-ate3d"]["rows"][0]["values"].pop(), "tables.task-ate3d.rows[0].values"),
    (lambda d: d["tables"]["model-results"]["columns"][0].update(metric="iuo"), "unknown metric 'iuo'"),
    (lambda d: d["tables"]["model-results"]["columns"][1].update(better="higher"), "disagrees with the metric"),
    (lambda d: d["tables"]["model-results"]["finite_counts"][0].update(row="Veo 9"), "names no row and metric"),
    (lambda d: d["tables"]["finetuning-splits"]["columns"][0].pop("group"), "needs a group on every column"),
    (lambda d: d["tables"]["model-results"]["rows"][2]["values"].__setitem__(3, ".2"), "values[3]"),
    (lambda d: d["comparable_when"].pop("protocol"), "comparable_when.protocol"),
])
def test_a_malformed_file_is_refused_naming_the_field(edit, message):
    data = yaml.safe_load(PAPER_NUMBERS_FILE.read_text())
    edit(data)
    with pytest.raises(ConfigError, match=re.escape(message)) as info:
        parse_paper_numbers(data, "somewhere/paper_numbers.yaml")
    assert str(info.value).startswith("somewhere/paper_numbers.yaml: ") and "\n" not in str(info.value)
