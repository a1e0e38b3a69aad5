"""The paper's reported numbers (configs/paper_numbers.yaml) as typed rows, and whether a report's runs may be
shown beside them.

``load_paper_numbers()`` reads the packaged transcription of the paper's model comparison, its ATE-3D by task
and its fine-tuned checkpoints by task and by evaluation partition (``parse_paper_numbers`` checks and types a
mapping already read). ``comparison_problem(table, paper)`` says in one line why a report's runs cannot stand
beside them (another set, an unverified copy, another protocol or perception, fewer examples), or None. The
report then adds the paper's rows to its model, task and partition tables, marked "reported in the paper, not
re-scored here" (``report/tables.py``).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from decimal import Decimal
from pathlib import Path
from typing import Any, Iterator

import yaml

from rigidbench.config import PACKAGE_CONFIG_DIR
from rigidbench.errors import ConfigError
from rigidbench.metrics import METRICS
from rigidbench.report.load import RunInfo, ScoreTable

PAPER_NUMBERS_FILE = PACKAGE_CONFIG_DIR / "paper_numbers.yaml"
BY = ("model", "task", "partition")


@dataclass(frozen=True)
class PaperColumn:
    """One column of a paper table: its heading as printed, our metric id, the task or partition id it is
    restricted to (None: all examples), printed = value x scale, at `decimals` places."""

    heading: str
    metric: str
    group: str | None
    higher_is_better: bool
    decimals: int
    scale: float = 1.0


@dataclass(frozen=True)
class PaperRow:
    """One row: the paper's label (LaTeX), our display name, our model id (None: not one of ours), the
    fine-tuned checkpoint it is (None: the released model), and per column the printed value (None: not
    printed) and the count of finite examples behind it."""

    paper_label: str
    name: str
    model: str | None
    checkpoint: str | None
    printed: tuple[float | None, ...]
    n_finite: tuple[int, ...]


@dataclass(frozen=True)
class PaperCell:
    """One number of a paper table, flat: ``value`` is unscaled (as our runs store it), ``printed`` as the
    paper prints it (``text`` at the column's decimals)."""

    table: str
    row: str
    model: str | None
    checkpoint: str | None
    metric: str
    group: str | None
    higher_is_better: bool
    printed: float
    value: float
    text: str
    n_finite: int
    n_examples: int


@dataclass(frozen=True)
class PaperTable:
    """One table of the paper: key, LaTeX label, title, caption (plain text), `by` ("model", "task" or
    "partition"), examples behind each cell, units, its columns and rows."""

    key: str
    label: str
    title: str
    caption: str
    by: str
    cell_examples: int
    units: str
    columns: tuple[PaperColumn, ...]
    rows: tuple[PaperRow, ...]

    def cells(self) -> Iterator[PaperCell]:
        """Every printed number of the table, row by row."""
        for row in self.rows:
            for col, printed, n in zip(self.columns, row.printed, row.n_finite):
                if printed is not None:
                    yield PaperCell(self.key, row.name, row.model, row.checkpoint, col.metric, col.group,
                                    col.higher_is_better, printed, unscale(printed, col.scale),
                                    printed_text(printed, col.decimals), n, self.cell_examples)

    def cell(self, row: PaperRow, metric: str, group: str | None) -> PaperCell | None:
        """The number of `row` for `metric` on `group` (None: all examples), or None when the table has none."""
        for k, col in enumerate(self.columns):
            if col.metric == metric and col.group == group and row.printed[k] is not None:
                return PaperCell(self.key, row.name, row.model, row.checkpoint, metric, group, col.higher_is_better,
                                 row.printed[k], unscale(row.printed[k], col.scale),
                                 printed_text(row.printed[k], col.decimals), row.n_finite[k], self.cell_examples)
        return None


@dataclass(frozen=True)
class PaperNumbers:
    """The whole transcription: where it comes from, the marker its rows carry, the runs it is comparable
    with (dataset, version, md5, examples, protocol, perception), what omitting non-finite values means, and
    the tables by key."""

    source: str
    marker: str
    dataset: str
    version: str
    md5: str
    examples: int
    protocol: str
    perception: str
    non_finite: str
    tables: dict[str, PaperTable]

    def tables_by(self, by: str) -> tuple[PaperTable, ...]:
        """The tables that break results down by `by` ("model": the whole set, "task", "partition")."""
        return tuple(t for t in self.tables.values() if t.by == by)


def unscale(printed: float, scale: float) -> float:
    """A printed value back in the run's units (printed / scale), exact in decimal: 0.739 / 1000 -> 0.000739."""
    return float(Decimal(repr(float(printed))) / Decimal(repr(float(scale))))


def printed_text(printed: float, decimals: int) -> str:
    """The value as the paper prints it, with a leading zero: 0.0288 at 4 -> "0.0288", 2.3 at 2 -> "2.30"."""
    return f"{printed:.{decimals}f}"


# ------------------------------------------------------------------------------------------ loading


def _fail(path: str, where: str, message: str) -> ConfigError:
    return ConfigError(f"{path}: {where}: {message}")


def _text(path: str, data: dict, key: str, where: str) -> str:
    value = data.get(key)
    if not isinstance(value, str) or not value.strip():
        raise _fail(path, f"{where}{key}", f"expected a non-empty string, got {value!r}")
    return value.strip()


def _count(path: str, data: dict, key: str, where: str) -> int:
    value = data.get(key)
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise _fail(path, f"{where}{key}", f"expected a positive whole number, got {value!r}")
    return value


def _column(path: str, data: Any, where: str) -> PaperColumn:
    if not isinstance(data, dict):
        raise _fail(path, where, f"expected a mapping, got {data!r}")
    metric = _text(path, data, "metric", where)
    if metric not in METRICS:
        raise _fail(path, f"{where}metric", f"unknown metric '{metric}'; known: {', '.join(METRICS)}")
    better = data.get("better")
    if better not in ("higher", "lower"):
        raise _fail(path, f"{where}better", f"expected 'higher' or 'lower', got {better!r}")
    if (better == "higher") != METRICS[metric].higher_is_better:
        raise _fail(path, f"{where}better", f"'{better}' disagrees with the metric registry for {metric}")
    scale = data.get("scale", 1)
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not scale > 0:
        raise _fail(path, f"{where}scale", f"expected a positive number, got {scale!r}")
    decimals = data.get("decimals")
    if isinstance(decimals, bool) or not isinstance(decimals, int) or not 0 <= decimals <= 6:
        raise _fail(path, f"{where}decimals", f"expected a whole number from 0 to 6, got {decimals!r}")
    group = data.get("group")
    if group is not None and not isinstance(group, str):
        raise _fail(path, f"{where}group", f"expected a task or partition id, got {group!r}")
    return PaperColumn(_text(path, data, "paper", where), metric, group, better == "higher", decimals, float(scale))


def _row(path: str, data: Any, where: str, columns: tuple[PaperColumn, ...], cell_examples: int,
         finite: dict[tuple[str, str], int]) -> PaperRow:
    if not isinstance(data, dict):
        raise _fail(path, where, f"expected a mapping, got {data!r}")
    values = data.get("values")
    if not isinstance(values, list) or len(values) != len(columns):
        raise _fail(path, f"{where}values", f"expected a list of {len(columns)} numbers (one per column), "
                                            f"got {values!r}")
    for k, v in enumerate(values):
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)):
            raise _fail(path, f"{where}values[{k}]", f"expected a finite number or null, got {v!r}")
    name = _text(path, data, "name", where)
    model, checkpoint = data.get("model"), data.get("checkpoint")
    for key, value in (("model", model), ("checkpoint", checkpoint)):
        if value is not None and not isinstance(value, str):
            raise _fail(path, f"{where}{key}", f"expected a string or null, got {value!r}")
    counts = tuple(finite.pop((name, col.metric), cell_examples) for col in columns)
    return PaperRow(_text(path, data, "paper", where), name, model, checkpoint,
                    tuple(None if v is None else float(v) for v in values), counts)


def _table(path: str, key: str, data: Any) -> PaperTable:
    where = f"tables.{key}."
    if not isinstance(data, dict):
        raise _fail(path, where.rstrip("."), f"expected a mapping, got {data!r}")
    by = data.get("by")
    if by not in BY:
        raise _fail(path, f"{where}by", f"expected one of {', '.join(BY)}, got {by!r}")
    cell_examples = _count(path, data, "cell_examples", where)
    raw_columns, raw_rows = data.get("columns"), data.get("rows")
    if not isinstance(raw_columns, list) or not raw_columns or not isinstance(raw_rows, list) or not raw_rows:
        raise _fail(path, where.rstrip("."), "needs a non-empty list of columns and of rows")
    columns = tuple(_column(path, c, f"{where}columns[{k}].") for k, c in enumerate(raw_columns))
    if any((c.group is None) != (by == "model") for c in columns):
        raise _fail(path, f"{where}columns", f"a table by {by} needs a group on every column exactly when it "
                                             "is not by model")
    finite: dict[tuple[str, str], int] = {}
    for k, item in enumerate(data.get("finite_counts") or []):
        at = f"{where}finite_counts[{k}]."
        if not isinstance(item, dict):
            raise _fail(path, at.rstrip("."), f"expected a mapping, got {item!r}")
        n = _count(path, item, "n", at)
        if n > cell_examples:
            raise _fail(path, f"{at}n", f"{n} finite values, but each cell has {cell_examples} examples")
        finite[(_text(path, item, "row", at), _text(path, item, "metric", at))] = n
    rows = tuple(_row(path, r, f"{where}rows[{k}].", columns, cell_examples, finite) for k, r in enumerate(raw_rows))
    if finite:
        raise _fail(path, f"{where}finite_counts", f"names no row and metric of the table: {sorted(finite)}")
    return PaperTable(key, _text(path, data, "label", where), _text(path, data, "title", where),
                      _text(path, data, "caption", where), by, cell_examples, _text(path, data, "units", where),
                      columns, rows)


def parse_paper_numbers(data: Any, path: str = "paper_numbers.yaml") -> PaperNumbers:
    """The transcription as read from YAML (a mapping) -> PaperNumbers; ConfigError naming `path` and the
    field on anything malformed."""
    if not isinstance(data, dict):
        raise _fail(path, "<root>", f"expected a mapping, got {type(data).__name__}")
    when = data.get("comparable_when")
    if not isinstance(when, dict):
        raise _fail(path, "comparable_when", f"expected a mapping, got {when!r}")
    tables = data.get("tables")
    if not isinstance(tables, dict) or not tables:
        raise _fail(path, "tables", "expected a mapping of table key -> table")
    source = data.get("source") or {}
    return PaperNumbers(
        source=str(source.get("paper", "")) if isinstance(source, dict) else str(source),
        marker=_text(path, data, "marker", ""),
        dataset=_text(path, when, "dataset", "comparable_when."),
        version=str(when.get("version", "")),
        md5=_text(path, when, "md5", "comparable_when.").lower(),
        examples=_count(path, when, "examples", "comparable_when."),
        protocol=_text(path, when, "protocol", "comparable_when."),
        perception=_text(path, when, "perception", "comparable_when."),
        non_finite=_text(path, data, "non_finite", ""),
        tables={str(key): _table(path, str(key), table) for key, table in tables.items()})


@functools.lru_cache(maxsize=4)
def load_paper_numbers(path: str | Path = PAPER_NUMBERS_FILE) -> PaperNumbers:
    """The paper's numbers from `path` (default: the packaged configs/paper_numbers.yaml)."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"{path}: cannot read the paper's numbers ({exc}); reinstall rigidbench") from None
    return parse_paper_numbers(data, str(path))


# ---------------------------------------------------------------------------------- comparability


_SINGULAR = {"is": "is", "was": "was", "s": "s"}
_PLURAL = {"is": "are", "was": "were", "s": ""}


def run_problem(run: RunInfo, paper: PaperNumbers) -> str | None:
    """Why one run's numbers cannot stand beside the paper's, as a predicate for its path ("{is} on a rendered
    set, ..."; {is}, {was}, {s} agree with the subject), or None when they can."""
    d = run.dataset or {}
    published = f"{paper.dataset} {paper.version}".strip()
    if not d:
        return "record{s} no reference set (results.json written before it was recorded; rerun `rigidbench " \
               "evaluate`)"
    if "sets" in d:
        return "{is} on a mix of reference sets"
    if d.get("dataset") == "rendered":
        return "{is} on a rendered set, not the published one"
    if d.get("dataset") != paper.dataset or str(d.get("md5") or "").lower() != paper.md5:
        name = " ".join(str(d[k]) for k in ("dataset", "version") if d.get(k)) or "an unnamed set"
        return f"{{is}} on {name}, not the paper's {published} (MD5 {paper.md5})"
    if d.get("verified") is not True:  # a missing `verified` counts as unverified
        return "{is} on a copy of the published set whose MD5 was not verified"
    if run.protocol != paper.protocol:
        return (f"{{was}} scored under protocol {run.protocol}, not {paper.protocol}" if run.protocol
                else "record{s} no evaluation protocol")
    if run.perception != paper.perception:
        return f"used {run.perception} perception, not the paper's {paper.perception} perception"
    return None


def _and(items: list[str]) -> str:
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


def comparison_problem(table: ScoreTable, paper: PaperNumbers) -> str | None:
    """One line saying why the paper's numbers are not shown beside `table`'s runs, or None when every run is
    on the verified published set under the paper's protocol and perception and the runs share all its
    examples."""
    groups: dict[str, list[str]] = {}
    for run in table.runs:
        problem = run_problem(run, paper)
        if problem is not None:
            groups.setdefault(problem, []).append(str(run.path))
    clauses = [f"{_and(paths)} {problem.format(**(_PLURAL if len(paths) > 1 else _SINGULAR))}"
               for problem, paths in groups.items()]
    n = len(table.example_ids)
    if n != paper.examples:
        clauses.append(f"the report covers {n} of the paper's {paper.examples} examples")
    if not clauses:
        return None
    return "The paper's numbers are not shown beside these runs: " + "; ".join(clauses) + "."


__all__ = ["PAPER_NUMBERS_FILE", "PaperCell", "PaperColumn", "PaperNumbers", "PaperRow", "PaperTable",
           "comparison_problem", "load_paper_numbers", "parse_paper_numbers", "printed_text", "run_problem",
           "unscale"]
