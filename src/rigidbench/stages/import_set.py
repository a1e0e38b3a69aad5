"""The ``import`` stage: the published evaluation set into bundles in ``DATA/eval/<id>/``, on the stage driver
(the conversion of one sample: ``datasets.convert``; the module is not named ``import``, a Python keyword).

Each sample is built in the stage's staging folder and renamed into place, keyed by a digest of its source
files' content (and the conversion's version and the dataset identity), so an interrupted import resumes without
redoing finished samples, a rerun skips what is unchanged, and one damaged sample is reported without stopping
the others. Only one download or import at a time may write into a ``--data`` folder (``datadir.data_lock``); a
folder holding another source's examples is refused (mixing two sets) unless ``replace`` deletes them; the free
disk is checked against what the import will write before it starts.
"""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path
from typing import Callable

from ..config import registry as load_registry
from ..datasets.convert import DIGEST_VERSION, convert_sample, find_published_root, published_samples, source_digest
from ..datasets.datadir import data_lock, format_bytes, prepare_data_dir
from ..driver import Adopted, ItemResult, Key, RunOptions, Stage, StageReport, StageWorker, ledger_path, run_stage
from ..errors import EXAMPLE_ERRORS, BundleError, UserError
from ..groundtruth import bundle as B
from ..hashing import digest as driver_digest

log = logging.getLogger(__name__)


#: free space kept beyond what the import writes
DISK_MARGIN_BYTES = 256 * 1024 * 1024


def _is_current(final: Path, digest: str) -> bool:
    """A bundle imported before the stage ledger existed, from these very source files."""
    try:
        meta = json.loads((final / B.METADATA_FILE).read_text())
    except (OSError, ValueError):
        return False
    return isinstance(meta, dict) and (meta.get("source") or {}).get("sample_digest") == digest \
        and not B.check_bundle(final, check_video=False)


class ImportWorker(StageWorker):
    """Converts one published sample (payload: its folder and manifest row; facts: its source ``digest``) into
    ``<id>/`` in staging."""

    def __init__(self, job: dict, registry=None):
        super().__init__(job)
        self.registry = registry if registry is not None else load_registry(job["config_dirs"])

    def run(self, item_id: str, payload: dict, staging: Path, progress, facts: dict) -> ItemResult:
        folder = Path(payload["folder"])
        (staging / item_id).mkdir()
        try:
            convert_sample(folder, staging / item_id, item_id, payload["row"], registry=self.registry,
                           dataset=self.job["dataset"], digest=facts["digest"])
        except EXAMPLE_ERRORS:
            raise
        except (ValueError, KeyError, TypeError) as exc:  # a malformed published file we did not foresee
            raise BundleError(f"{folder}: cannot be converted ({exc!r}); extract the archive again") from None
        problems = B.check_bundle(staging / item_id)
        if problems:
            raise BundleError(f"{folder}: the imported bundle fails its check: {'; '.join(problems[:3])}")
        return ItemResult(outputs=[item_id], result={"digest": facts["digest"]})


class ImportStage(Stage):
    """``rigidbench import`` on the stage driver: one published sample per item into ``DATA/eval/<id>/``,
    keyed by a digest of its source files, the conversion's version and the dataset identity recorded."""

    name = "import"
    worker = "rigidbench.stages.import_set:ImportWorker"

    def __init__(self, root: Path, split_dir: Path, samples, dataset: dict | None, registry, config_dirs=(),
                 replace: bool = False):
        self.source_root, self.split_dir = root, split_dir
        self.samples = {sample_id: (folder, row) for sample_id, folder, row in samples}
        self.dataset, self.registry, self.config_dirs = dataset or {}, registry, config_dirs
        self.identity, self.replace = dataset, replace

    @property
    def root(self) -> Path:
        return self.split_dir

    @property
    def where(self) -> str:
        return str(self.source_root)

    def check(self, selected: list[str]) -> None:
        """One source per folder (``replace`` deletes the others' examples) and room on the disk, before any
        sample is read."""
        _keep_one_source(self.split_dir, self.source_root, list(self.samples), selected, self.identity, self.replace)
        _check_free_disk(self.split_dir, [(self.samples[sample_id][0], sample_id) for sample_id in selected])

    def items(self):
        return {sample_id: {"folder": str(folder), "row": row} for sample_id, (folder, row) in self.samples.items()}

    def key(self, item_id, payload) -> Key:
        digest = source_digest(Path(payload["folder"]))
        return Key(driver_digest("import", DIGEST_VERSION, digest, self.dataset), {"digest": digest})

    def job(self):
        return {"dataset": self.dataset, "config_dirs": [str(d) for d in self.config_dirs]}

    def worker_instance(self):
        return ImportWorker(self.job(), registry=self.registry)

    def intact(self, item_id):
        return (self.split_dir / item_id).is_dir() and not B.check_bundle(self.split_dir / item_id, check_video=False)

    def adopt(self, item_id, payload, key):
        digest = key.facts["digest"]
        current = _is_current(self.split_dir / item_id, digest)
        return Adopted({"digest": digest}, "a bundle converted from these source files") if current else None


def import_published(src: str | Path, data: str | Path, *, dataset: dict | None = None, registry=None,
                     run: RunOptions = RunOptions(), on_sample: Callable[[str, str], None] | None = None,
                     config_dirs=(), replace: bool = False) -> StageReport:
    """Convert the selected published samples under ``src`` into ``data/eval/<id>/`` on the stage driver;
    ``dataset`` is the identity recorded in each bundle's ``source`` (``DatasetDescription.identity()`` with
    ``verified`` and ``verification``). Resumable: a sample whose source files, conversion and identity are
    unchanged is up to date; per-sample failures are in the report, never raised. ``config_dirs``: what a
    worker elsewhere rebuilds ``registry`` from (this process uses ``registry`` itself). Holds ``data``'s lock
    (DataBusyError while another download or import holds it); UserError when ``data/eval`` holds examples of
    another source that this import would leave beside its own (``replace`` deletes them instead), or when the
    disk cannot hold what it writes."""
    root = find_published_root(Path(src))
    samples = published_samples(root)
    data = prepare_data_dir(data)
    with data_lock(data):
        split_dir = data / "eval"
        split_dir.mkdir(exist_ok=True)
        if split_dir.resolve() == (root / "eval").resolve():
            raise UserError(f"--data {data}: the published set itself is there; import into another folder")
        for stale in split_dir.glob(".*.tmp"):  # an interrupted import of an earlier version
            shutil.rmtree(stale, ignore_errors=True)
        stage = ImportStage(root, split_dir, samples, dataset, registry, config_dirs, replace)
        report = run_stage(stage, run, on_result=None if on_sample is None else
                           lambda sample_id, entry: on_sample(sample_id, "done" if entry.get("status") == "succeeded"
                                                              else "failed"))
    for sample_id, reason in report.failed.items():
        log.warning("sample %s not imported: %s", sample_id, reason)
    return report


def _set_of(identity: dict | None) -> tuple:
    """(dataset, version, MD5): which published set an identity names (verification aside)."""
    identity = identity or {}
    return identity.get("dataset"), identity.get("version"), identity.get("md5")


def _keep_one_source(split_dir: Path, root: Path, source_ids: list[str], selected: list[str], dataset: dict | None,
                     replace: bool) -> None:
    """Refuse (or, with ``replace``, delete) the bundles in ``split_dir`` that this import would leave beside
    its own although they come from elsewhere: an id the source does not have, or one this run does not
    import again whose bundle records another set (a rendered bundle, another release)."""
    ours, redone, wanted = set(source_ids), set(selected), _set_of(dataset)
    foreign = []
    for bundle in B.bundle_dirs(split_dir):
        if bundle.name in redone:
            continue  # imported again now: replaced by this source's
        if bundle.name not in ours:
            foreign.append(bundle.name)
            continue
        try:
            meta = json.loads((bundle / B.METADATA_FILE).read_text())
        except (OSError, ValueError):
            continue  # damaged: a later import of this id replaces it
        if _set_of(B.dataset_identity(meta)) != wanted:
            foreign.append(bundle.name)
    if not foreign:
        return
    shown = ", ".join(foreign[:5]) + (" ..." if len(foreign) > 5 else "")
    if not replace:
        what = f"{wanted[0]} {wanted[1]}" if wanted[0] else str(root)
        raise UserError(f"{split_dir}: holds {len(foreign)} example(s) that are not from {what} ({shown}); importing "
                        "there would leave two sets mixed. Import into another --data, or pass --replace to delete "
                        "them first")
    for sample_id in foreign:
        shutil.rmtree(split_dir / sample_id)
        ledger_path(split_dir, ImportStage.name, sample_id).unlink(missing_ok=True)
    log.warning("deleted %d example(s) of another source from %s (--replace): %s", len(foreign), split_dir, shown)


def import_write_bytes(folder: Path, device: int) -> int:
    """About what importing the published sample ``folder`` writes on the file system ``device``: its depth,
    masks, trajectories and small files rewritten; frames and video nothing when they can be linked (the same
    device), their size when copied; frames decoded from the video at most W x H x 3 bytes each."""
    total = 0
    for name in ("depth.npz", "masks.npz", "trajectories.npz", "contacts.json", "metadata.json", "prompt.txt"):
        p = folder / name
        total += p.stat().st_size if p.is_file() else 0
    meta_path = folder / "metadata.json"
    total += meta_path.stat().st_size if meta_path.is_file() else 0  # again: the bundle's metadata keeps it whole
    frames, video = folder / B.FRAMES_DIR, folder / B.VIDEO_FILE
    if frames.is_dir():
        if frames.stat().st_dev != device:
            total += sum(p.stat().st_size for p in frames.glob("*.png"))
    else:
        try:
            meta = json.loads((folder / "metadata.json").read_text())
            W, H = (int(v) for v in meta["render"]["resolution"])
            total += W * H * 3 * int(meta.get("frames", 0))
        except (OSError, ValueError, KeyError, TypeError):
            pass  # the sample fails on its own, writing nothing
    if video.is_file() and video.stat().st_dev != device:
        total += video.stat().st_size
    return total


def _check_free_disk(split_dir: Path, samples: list[tuple[Path, str]]) -> None:
    """UserError before anything is written when the disk under ``split_dir`` cannot hold what importing the
    samples not yet there writes, plus a margin (a sample imported before is replaced in place)."""
    device = split_dir.stat().st_dev
    todo = [folder for folder, sample_id in samples if not (split_dir / sample_id).is_dir()]
    need = sum(import_write_bytes(folder, device) for folder in todo)
    free = shutil.disk_usage(split_dir).free
    if todo and free < need + DISK_MARGIN_BYTES:
        raise UserError(f"not enough free disk space in {split_dir} to import {len(todo)} sample(s): they write about "
                        f"{format_bytes(need)} (depth, masks, tracks; frames and video are linked, or copied from "
                        f"another file system), {format_bytes(DISK_MARGIN_BYTES)} kept spare, and "
                        f"{format_bytes(free)} is free; free space there or choose another --data")


__all__ = ["ImportStage", "ImportWorker", "import_published", "import_write_bytes"]
