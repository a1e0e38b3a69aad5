"""A published dataset's description, as data: one YAML file per dataset in ``configs/datasets/``.

The file's stem is the dataset's id (``rigidbench-eval-v1.1``); ``name`` and ``version`` say which set and
which release it is. A mirror or a later release is one more file in a ``--config`` directory: a file with the
same id replaces the packaged one, and ``load_dataset(name)`` picks the highest version of that name (between
equal versions, the file from the later directory). The archive is served in parts, either listed one by one
(``parts: [{name, size_bytes, md5?, url?}, ...]``) or generated from ``parts: {count, size_bytes, name}``, where
every part is ``size_bytes`` long except the last (the remainder) and ``name`` is a format string over
``{archive}``, ``{index}`` (1-based) and ``{count}``. ``url`` is a format string over ``{part}`` and ``{archive}``.
"""

from __future__ import annotations

import difflib
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable
from urllib.parse import urlsplit

from ..config import FieldReader, config_dirs, read_config_yaml
from ..errors import ConfigError, UnknownNameError

#: the dataset ``rigidbench download`` fetches when none is named
DEFAULT_DATASET = "rigidbench-eval"

FIELDS = ("id", "name", "version", "title", "description", "archive", "size_bytes", "md5", "parts", "url",
          "licence", "doi", "record", "homepage", "citation", "examples")
_MD5 = re.compile(r"^[0-9a-fA-F]{32}$")
_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
#: file names the download keeps beside the parts (download.py); a part may not take one of them
RESERVED_NAMES = frozenset({"complete.json", "verified.json", "extracted", "extracted.tmp", ".lock"})


@dataclass(frozen=True)
class DatasetPart:
    """One file of the split archive: its name, size in bytes, byte offset in the whole, URL and MD5 (if known)."""

    name: str
    size_bytes: int
    offset_bytes: int
    url: str
    md5: str | None = None


@dataclass(frozen=True)
class DatasetDescription:
    """Everything needed to fetch, verify and identify one published dataset."""

    id: str  # the file's stem
    name: str
    version: str
    archive: str  # the whole archive's file name (the parts concatenated)
    size_bytes: int
    md5: str  # of the whole archive, lower-case hex
    parts: tuple[DatasetPart, ...]
    url_template: str
    licence: str
    title: str = ""
    description: str = ""
    doi: str | None = None
    record: str | None = None
    homepage: str | None = None
    citation: str | None = None
    source: str = ""  # the YAML file it was read from
    examples: int | None = None  # how many examples the archive holds (a complete submission scores them all)

    def identity(self) -> dict[str, Any]:
        """What a result or an imported bundle records about the dataset it came from."""
        return {"dataset": self.name, "version": self.version, "id": self.id, "archive": self.archive,
                "md5": self.md5, "doi": self.doi, "licence": self.licence}


def _fail(path: Path, field_name: str, message: str) -> ConfigError:
    return ConfigError(f"{path}: field '{field_name}': {message}")


def _safe_file_name(path: Path, field_name: str, value: str) -> str:
    if (not value or value in (".", "..") or value.startswith(".") or any(c in value for c in "/\\\0")
            or len(value) > 255):
        raise _fail(path, field_name, f"'{value}' is not a plain file name (no '/', no leading '.')")
    if value in RESERVED_NAMES:
        raise _fail(path, field_name, f"'{value}' is a name the download uses for itself; choose another")
    return value


def _md5(r: FieldReader, key: str, default: Any = ...) -> str | None:
    if isinstance(r.raw(key, default), int) and not isinstance(r.raw(key, default), bool):
        raise _fail(r.path, r.prefix + key, "YAML read the MD5 as a number: quote it")
    value = r.str(key, default)
    if value is None:
        return None
    if not _MD5.match(value):
        raise _fail(r.path, r.prefix + key, f"expected 32 hexadecimal digits, got {value!r}")
    return value.lower()


def _url(path: Path, field_name: str, template: str, part: str, archive: str) -> str:
    try:
        url = template.format(part=part, archive=archive)
    except (KeyError, IndexError, ValueError) as exc:
        raise _fail(path, field_name, f"bad placeholder {exc} in {template!r}; use {{part}} and {{archive}}") from None
    split = urlsplit(url)
    if split.scheme not in ("http", "https") or not split.hostname:
        raise _fail(path, field_name, f"expected an http(s) URL, got {url!r}")
    return url


def _parts(r: FieldReader, archive: str, size_bytes: int, template: str | None) -> tuple[DatasetPart, ...]:
    path = r.path
    raw = r.raw("parts")
    entries: list[tuple[str, int, str | None, str | None]] = []  # name, size, md5, own url
    if isinstance(raw, list):
        if not raw:
            raise _fail(path, "parts", "expected at least one part")
        for item in r.items("parts"):
            item.reject_unknown(("name", "size_bytes", "md5", "url"))
            name = _safe_file_name(path, item.prefix + "name", item.str("name"))
            entries.append((name, item.int("size_bytes", lo=1), _md5(item, "md5", None), item.str("url", None)))
    else:
        g = r.sub("parts")
        g.reject_unknown(("count", "size_bytes", "name"))
        count, each = g.int("count", lo=1), g.int("size_bytes", lo=1)
        if not (count - 1) * each < size_bytes <= count * each:
            raise _fail(path, "parts", f"{count} parts of {each:,} bytes (the last one the remainder) cannot make "
                                       f"size_bytes {size_bytes:,}; it needs {-(-size_bytes // each)} parts")
        pattern = g.str("name")
        for index in range(1, count + 1):
            try:
                name = pattern.format(archive=archive, index=index, count=count)
            except (KeyError, IndexError, ValueError) as exc:
                raise _fail(path, "parts.name", f"bad placeholder {exc} in {pattern!r}; "
                                                "use {archive}, {index} and {count}") from None
            last = size_bytes - (count - 1) * each
            entries.append((_safe_file_name(path, "parts.name", name), each if index < count else last, None, None))
    names = [e[0] for e in entries]
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise _fail(path, "parts", f"part name '{dup}' is used twice (does the name pattern use {{index}}?)")
    taken = set(names)
    for n in names:  # a part's temporary name is "<name>.part": it must not be another part's name
        if f"{n}.part" in taken:
            raise _fail(path, "parts", f"part names '{n}' and '{n}.part' collide")
    total = sum(e[1] for e in entries)
    if total != size_bytes:
        raise _fail(path, "parts", f"the parts add up to {total:,} bytes, but size_bytes is {size_bytes:,}")
    out, offset = [], 0
    for i, (name, size, md5, own_url) in enumerate(entries):
        if own_url is not None:
            url = _url(path, f"parts[{i}].url", own_url, name, archive)
        elif template is not None:
            url = _url(path, "url", template, name, archive)
        else:
            raise _fail(path, "url", "is required (or give every part its own url)")
        out.append(DatasetPart(name=name, size_bytes=size, offset_bytes=offset, url=url, md5=md5))
        offset += size
    return tuple(out)


def parse_dataset(path: str | Path, data: Any) -> DatasetDescription:
    """Validate one dataset file's content; ConfigError names the file and the field."""
    path = Path(path)
    r = FieldReader(path, data)
    r.reject_unknown(FIELDS)
    dataset_id = path.stem
    if r.has("id") and r.str("id") != dataset_id:
        raise _fail(path, "id", f"id '{r.str('id')}' must match the file name '{dataset_id}'")
    if not _ID.match(dataset_id):
        raise _fail(path, "id", f"the file name '{dataset_id}' is not a usable id (letters, digits, '.', '_', '-')")
    version = r.raw("version")
    if not isinstance(version, str) or not version.strip():
        raise _fail(path, "version", f"expected a string (quote it: version: \"{version}\"), got {version!r}")
    archive = _safe_file_name(path, "archive", r.text("archive"))
    size_bytes = r.int("size_bytes", lo=1)
    template = r.str("url", None)
    record = r.raw("record", None)
    if record is not None and (isinstance(record, bool) or not isinstance(record, (int, str))):
        raise _fail(path, "record", f"expected a record number or string, got {record!r}")
    return DatasetDescription(
        id=dataset_id, name=r.text("name"), version=version.strip(), archive=archive, size_bytes=size_bytes,
        md5=_md5(r, "md5"), parts=_parts(r, archive, size_bytes, template), url_template=template or "",
        licence=r.text("licence"), title=r.str("title", ""), description=r.str("description", ""),
        doi=r.text("doi", None), record=None if record is None else str(record), homepage=r.text("homepage", None),
        citation=r.text("citation", None), source=str(path),
        examples=r.int("examples", lo=1) if r.has("examples") else None)


def list_datasets(extra_dirs: Iterable[str | Path] = ()) -> dict[str, DatasetDescription]:
    """Every dataset described in the configuration directories, by id (later directories override earlier
    ones), in the order they were found (the packaged ones first)."""
    table: dict[str, DatasetDescription] = {}
    for d in config_dirs(extra_dirs):
        sub = d / "datasets"
        for path in sorted(sub.glob("*.yaml")) if sub.is_dir() else []:
            desc = parse_dataset(path, read_config_yaml(path))
            table.pop(desc.id, None)  # re-insert: a replacement counts as found later
            table[desc.id] = desc
    return table


def _version_key(version: str) -> tuple:
    return tuple((0, int(p), "") if p.isdigit() else (1, 0, p) for p in re.split(r"[.\-+]", version))


def load_dataset(name_or_id: str | None = None, extra_dirs: Iterable[str | Path] = ()) -> DatasetDescription:
    """The dataset with this id (``rigidbench-eval-v1.1``), else the highest version with this name
    (``rigidbench-eval``; between equal versions the one found last); None means ``DEFAULT_DATASET``.
    Raises UnknownNameError (a did-you-mean) or ConfigError (a bad file, naming it and the field)."""
    key = DEFAULT_DATASET if name_or_id is None else name_or_id
    table = list_datasets(extra_dirs)
    if key in table:
        return table[key]
    found = [(i, d) for i, d in enumerate(table.values()) if d.name == key]
    if found:
        return max(found, key=lambda pair: (_version_key(pair[1].version), pair[0]))[1]
    known = sorted(set(table) | {d.name for d in table.values()})
    close = difflib.get_close_matches(key, known, n=1)
    hint = f" (did you mean '{close[0]}'?)" if close else ""
    dirs = config_dirs(extra_dirs)
    looked = ", ".join(str(d / "datasets") for d in dirs)
    stray = [d / f"{key}.yaml" for d in dirs[1:] if (d / f"{key}.yaml").is_file()]
    moved = f"; {stray[0]} is not read there: move it to {stray[0].parent / 'datasets' / stray[0].name}" if stray else ""
    raise UnknownNameError(f"unknown dataset '{key}'{hint}; known datasets: {', '.join(known) or 'none'}; looked "
                           f"for {key}.yaml in {looked} (a dataset is a file DIR/datasets/<id>.yaml, DIR the "
                           f"packaged configs or a `rigidbench --config DIR` directory){moved}")
