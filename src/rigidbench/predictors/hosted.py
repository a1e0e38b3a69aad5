"""The hosted video models (Veo 3.1 and its fast variant, Kling 3.0, Seedance 2.0 and its fast
variant, Grok Imagine), called through Replicate's HTTP API with ``replicate.ReplicateClient``.

One ``HostedPredictor`` class serves all of them: it finds its row of ``configs/models.yaml`` (a
copy in a ``--config`` directory replaces the packaged file) by its registry name. That row holds
the Replicate model, the names of the inputs that receive the first frame, the prompt and the
negative prompt, and the fixed inputs exactly as the paper's table gives them; nothing about a
model is written in code.

Every example sends the first frame resized (Lanczos) to 1280x720 as a lossless PNG, as the paper's
runs did (the authors' release, ``eval/generate/remote.py``): inline as a data URI when that is small
enough, else uploaded through the files endpoint and sent as its URL (``image.format: jpeg`` in the YAML
sends a JPEG instead, this adapter's choice before issue 24); the task prompt with the paper's suffix and,
for models that take one, the paper's negative prompt. No seed is sent: the paper's table lists every input of
its calls and none is a seed (``seed_field`` in the YAML sends each example's seed, derived from ``--seed`` and
the example id, to a model that takes one).

Resume (``OUT/.hosted/<item>.json``, written atomically and fsynced; the item is the prediction's name,
``PredictContext.item``: ``<id>``, or ``<id>.s<k>`` for sample k of several, so each sample is paid for once and
never adopts another sample's prediction): before a prediction is created an
*intent* is stored there (the model, a SHA-256 of the exact input sent, and the time), and right after
Replicate answers, the prediction's id. A rerun of an example with a stored id fetches that prediction
instead of creating a new one: a succeeded prediction is downloaded again, one still running is waited
for, and only a failed or canceled one is created anew. A rerun of an example with an intent but no id
(the run was killed while the creation request was in flight, or before its answer was saved) lists the
account's recent predictions (``GET /v1/predictions``) and adopts the one of the same model and input
created after the intent (less ``CLOCK_SKEW_S``); only when there is none is a new one created. So
neither a kill nor an interrupted download costs a second paid prediction. A succeeded prediction whose
output Replicate has already deleted (after about an hour) fails the example with that reason; the option
``repay_expired`` (``--repay-expired``) pays for a new one instead. When the example is done, the state
also keeps its generation record, from which the predict stage rebuilds a record that was lost.

Stopping (``request_stop``, on SIGTERM or Ctrl-C in the predict stage): no new prediction is created and
no more polls are made; requests already sent get ``client.stop_grace_s`` (3 s) more, so a creation answered
by then has its id saved and an output that has already succeeded is downloaded (it was paid for, and
Replicate deletes it after an hour); then they are cut off. A creation cut off keeps its intent, so the rerun
adopts the prediction it made, and a prediction cut off while running or downloading keeps its id.
Stale temporaries of a prediction (``.hosted/.<item>.*.part.mp4``, ``.hosted/.<item>.json.*.tmp``) are removed
when it runs again (only its own: not those of another sample of the example, which may be downloading).
"""

from __future__ import annotations

import base64
import glob
import hashlib
import io
import json
import logging
import os
import re
import threading
import time
from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..config import FieldReader, config_file, read_config_yaml
from ..errors import ConfigError, PredictionError
from ..jsonio import write_json
from ..folders import VIDEO_EXTENSIONS, PredictionsFolder
from .base import SEED_RULE, PredictContext, Prediction, Predictor, PredictorInfo, model_inputs
from .options import HostedOptions
from .replicate import (TOKEN_ENV, CallStats, ClientSettings, CreationUncertain, Deadline, ReplicateClient,
                        ReplicateError, StopRequested, base_url_from_env, output_url, public_url, token_from_env)

log = logging.getLogger(__name__)

MODELS_FILE = "models.yaml"
RESTART_STATUSES = ("failed", "canceled", "aborted")
#: how much earlier than its intent a prediction may be stamped and still be adopted (clocks differ)
CLOCK_SKEW_S = 120.0
_SLUG = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*/[A-Za-z0-9][A-Za-z0-9_.-]*$")


# -- configs/models.yaml ------------------------------------------------------------------------


@dataclass(frozen=True)
class HostedModel:
    """One row of models.yaml: the Replicate model, where each input goes, and the fixed inputs."""

    name: str
    replicate: str  # owner/name
    image_field: str
    prompt_field: str
    negative_prompt_field: str | None
    seed_field: str | None
    inputs: Mapping[str, Any]


IMAGE_FORMATS = {"png": "image/png", "jpeg": "image/jpeg"}
#: Replicate recommends a data URI only for files under 1 MB ("Option 3: Data URI ... only recommended if the
#: file is less than 1MB", https://replicate.com/docs/topics/predictions/input-files); larger inputs go through
#: POST /v1/files, which takes up to 100 MiB (replicate/replicate-javascript#286). We compare the whole URI.
DATA_URI_LIMIT_BYTES = 1_000_000


@dataclass(frozen=True)
class ImageSettings:
    width: int = 1280
    height: int = 720
    jpeg_quality: int = 95  # used only with format "jpeg"
    upload_threshold_bytes: int = DATA_URI_LIMIT_BYTES
    format: str = "png"

    @property
    def mime(self) -> str:
        return IMAGE_FORMATS[self.format]

    def record(self) -> dict[str, Any]:
        """What of these settings shapes the image sent (jpeg_quality only for JPEG)."""
        out = {"width": self.width, "height": self.height, "format": self.format}
        if self.format == "jpeg":
            out["jpeg_quality"] = self.jpeg_quality
        return out


@dataclass(frozen=True)
class _ImageNumbers:
    """The numeric fields of ImageSettings (read with FieldReader.numbers)."""

    width: int = ImageSettings.width
    height: int = ImageSettings.height
    jpeg_quality: int = ImageSettings.jpeg_quality
    upload_threshold_bytes: int = ImageSettings.upload_threshold_bytes


@dataclass(frozen=True)
class HostedConfig:
    path: Path
    models: Mapping[str, HostedModel]
    image: ImageSettings
    client: ClientSettings

    def model(self, name: str) -> HostedModel:
        if name not in self.models:
            raise ConfigError(f"{self.path}: field 'models': no entry for '{name}'; entries: "
                              f"{', '.join(sorted(self.models)) or 'none'}")
        return self.models[name]


def parse_models(path: Path, data: Any) -> HostedConfig:
    """Validate models.yaml; ConfigError names the file and the field."""
    path = Path(path)
    root = FieldReader(path, data)
    root.reject_unknown(("models", "image", "client"))
    rows = root.sub("models")
    if not rows.data:
        raise ConfigError(f"{path}: field 'models': expected at least one model")
    models = {}
    for name in rows.data:
        row = rows.sub(str(name))
        prefix = f"models.{name}"
        row.reject_unknown(("replicate", "image_field", "prompt_field", "negative_prompt_field", "seed_field",
                            "inputs"))
        slug = row.text("replicate")
        if not _SLUG.match(slug):
            raise ConfigError(f"{path}: field '{prefix}.replicate': expected an official model as 'owner/name', "
                              f"got {slug!r}")
        image_field, prompt_field = row.text("image_field"), row.text("prompt_field")
        inputs = row.sub("inputs")
        for key, value in inputs.data.items():
            if not (value is None or isinstance(value, (str, bool, int, float))):
                raise ConfigError(f"{path}: field '{prefix}.inputs.{key}': expected a string, number or boolean, "
                                  f"got {value!r}")
        model = HostedModel(name=str(name), replicate=slug, image_field=image_field, prompt_field=prompt_field,
                            negative_prompt_field=row.text("negative_prompt_field", None),
                            seed_field=row.text("seed_field", None), inputs=dict(inputs.data))
        wired = [f for f in (model.image_field, model.prompt_field, model.negative_prompt_field, model.seed_field) if f]
        if len(set(wired)) != len(wired):
            raise ConfigError(f"{path}: field '{prefix}': two of image_field, prompt_field, negative_prompt_field and "
                              f"seed_field name the same input: {wired}")
        for f in wired:
            if f in inputs.data:
                raise ConfigError(f"{path}: field '{prefix}.inputs.{f}': this input is filled per example; remove "
                                  "it from inputs")
        models[model.name] = model
    image_reader = root.sub("image", {})
    image_format = image_reader.str("format", "png", choices=tuple(IMAGE_FORMATS))
    numbers = FieldReader(path, {k: v for k, v in image_reader.data.items() if k != "format"}, "image.")
    image = numbers.numbers(_ImageNumbers, {"width": 16, "height": 16, "jpeg_quality": 1, "upload_threshold_bytes": 0})
    image = ImageSettings(**asdict(image), format=image_format)
    if image.jpeg_quality > 100:
        raise ConfigError(f"{path}: field 'image.jpeg_quality': must lie in [1, 100], got {image.jpeg_quality}")
    client = root.sub("client", {}).numbers(ClientSettings, {
        "request_timeout_s": 0.001, "wait_s": 1, "poll_interval_s": 0.0, "poll_max_interval_s": 0.0,
        "max_retries": 0, "example_timeout_s": 0.001, "max_output_bytes": 1})
    if client.wait_s > 60:
        raise ConfigError(f"{path}: field 'client.wait_s': Replicate holds a request at most 60 s, got {client.wait_s}")
    return HostedConfig(path=path, models=models, image=image, client=client)


def load_hosted_config(extra_dirs=()) -> HostedConfig:
    """models.yaml from the packaged configs or the last ``extra_dirs`` that has one."""
    path = config_file(MODELS_FILE, extra_dirs)
    return parse_models(path, read_config_yaml(path))


# -- the first frame --------------------------------------------------------------------------------


def encode_first_frame(image: np.ndarray, settings: ImageSettings) -> bytes:
    """(H,W,3) uint8 -> PNG (lossless; or JPEG with ``settings.format`` "jpeg") bytes at settings.width x
    settings.height (Lanczos)."""
    from PIL import Image

    pil = Image.fromarray(np.ascontiguousarray(image[..., :3]).astype(np.uint8, copy=False))
    if pil.size != (settings.width, settings.height):
        pil = pil.resize((settings.width, settings.height), Image.Resampling.LANCZOS)
    out = io.BytesIO()
    if settings.format == "jpeg":
        pil.save(out, format="JPEG", quality=settings.jpeg_quality)
    else:
        pil.save(out, format="PNG")
    return out.getvalue()


def data_uri(data: bytes, mime: str = "image/png") -> str:
    return f"data:{mime};base64," + base64.b64encode(data).decode("ascii")


# -- per-example state (resume) ------------------------------------------------------------------------


def _save_state(path: Path, doc: dict) -> None:
    """A prediction's resume state, fsynced before the rename and the rename fsynced too: it is what keeps
    a rerun from paying twice."""
    write_json(path, doc, durable=True, sort_keys=True)
    try:
        fd = os.open(path.parent, os.O_RDONLY)
    except OSError:  # pragma: no cover - platforms without directory handles
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover
        pass
    finally:
        os.close(fd)


def _read_state(path: Path) -> dict | None:
    """The example's state: a prediction id, or an intent to create one; None when there is neither."""
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        log.warning("%s: unreadable (%s); the example starts a new prediction", path, exc)
        return None
    if not isinstance(doc, dict):
        return None
    if isinstance(doc.get("prediction_id"), str) or isinstance(doc.get("intent"), dict):
        return doc
    return None


def input_hash(inputs: Mapping[str, Any], without: str | None = None) -> str:
    """SHA-256 of the input as sent (canonical JSON), optionally leaving out the field ``without``."""
    body = {k: v for k, v in inputs.items() if k != without}
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def _parse_time(value: Any) -> float | None:
    """Unix seconds of an ISO 8601 time such as Replicate's ``created_at`` ("2025-01-02T03:04:05.678Z")."""
    if not isinstance(value, str) or not value:
        return None
    try:
        when = datetime.fromisoformat(value.replace("Z", "+00:00"))
    except ValueError:
        return None
    if when.tzinfo is None:
        when = when.replace(tzinfo=timezone.utc)
    return when.timestamp()


def _claimed_ids(state_dir: Path, but: str) -> set[str]:
    """Prediction ids that other examples' states in ``state_dir`` hold (never adopted for another example)."""
    ids = set()
    for path in state_dir.glob("*.json"):
        if path.name != but and (state := _read_state(path)) and isinstance(state.get("prediction_id"), str):
            ids.add(state["prediction_id"])
    return ids


class _RecentPredictions:
    """The account's predictions listed newest first, fetched page by page only as far back as a caller
    needs and kept for the run (several interrupted examples cost one listing)."""

    MAX_PAGES = 20  # Replicate lists 100 per page

    def __init__(self, client: ReplicateClient):
        self.client = client
        self.items: list[dict] = []
        self._pages = None
        self.pages = 0
        self.exhausted = False
        self.lock = threading.Lock()

    def _oldest(self) -> float | None:
        times = [t for t in (_parse_time(p.get("created_at")) for p in self.items) if t is not None]
        return min(times) if times else None

    def since(self, cutoff: float, deadline: Deadline, stats: CallStats) -> list[dict]:
        """Every listed prediction created at ``cutoff`` (unix seconds) or later. A PredictionError when
        ``MAX_PAGES`` pages do not reach back that far: then nobody can tell whether one was created."""
        with self.lock:
            while not self.exhausted:
                oldest = self._oldest()
                if oldest is not None and oldest < cutoff:
                    break  # listed far enough back
                if self.pages >= self.MAX_PAGES:
                    raise PredictionError(f"{self.pages} pages of recent predictions did not reach back to the "
                                          "interrupted creation")
                if self._pages is None:
                    self._pages = self.client.list_predictions(deadline, stats)
                try:
                    page = next(self._pages)
                except StopIteration:
                    self.exhausted = True
                    break
                except BaseException:
                    self._pages, self.items, self.pages = None, [], 0  # start over next time
                    raise
                self.pages += 1
                self.items.extend(page)
            return [p for p in self.items if (_parse_time(p.get("created_at")) or 0.0) >= cutoff]


# -- the predictor --------------------------------------------------------------------------------------


class HostedPredictor(Predictor):
    """A hosted video model on Replicate, configured by its row of models.yaml (found by registry name);
    its options: ``options.HostedOptions`` (concurrency, repay_expired)."""

    paid = True
    options_type = HostedOptions

    def __init__(self, info: PredictorInfo):
        super().__init__(info)
        self._lock = threading.Lock()
        self._adopting = threading.Lock()
        self._configs: dict[tuple, HostedConfig] = {}
        self._client: ReplicateClient | None = None
        self._state_dirs: set[Path] = set()
        self._stop = threading.Event()
        self._recent: _RecentPredictions | None = None

    # -- configuration ---------------------------------------------------------------------------

    def config(self, ctx: PredictContext) -> HostedConfig:
        key = tuple(str(d) for d in ctx.run.config_dirs)
        with self._lock:
            if key not in self._configs:
                self._configs[key] = load_hosted_config(ctx.run.config_dirs)
            return self._configs[key]

    def model(self, ctx: PredictContext) -> HostedModel:
        return self.config(ctx).model(self.info.name)

    def concurrency(self, ctx: PredictContext) -> int:
        return self.options(ctx).concurrency  # an int >= 1 (default 8)

    def settings(self, ctx: PredictContext) -> dict[str, Any]:
        """What makes the videos differ: the model, its fixed inputs, the image as sent and the seed (None:
        the model is sent none, see the module docstring)."""
        cfg, model = self.config(ctx), self.model(ctx)
        return {"model": model.replicate, "inputs": dict(model.inputs),
                "fields": {"image": model.image_field, "prompt": model.prompt_field,
                           "negative_prompt": model.negative_prompt_field, "seed": model.seed_field},
                "image": cfg.image.record(),
                "seed": ctx.seed if model.seed_field else None}

    def generation_info(self, ctx: PredictContext) -> dict[str, Any]:
        cfg, model = self.config(ctx), self.model(ctx)
        return {
            "provider": "replicate", "api": public_url(base_url_from_env()), "model": model.replicate,
            "revision": "the official model's current version on Replicate (each example records its 'version')",
            "inputs": dict(model.inputs),
            "fields": {"image": model.image_field, "prompt": model.prompt_field,
                       "negative_prompt": model.negative_prompt_field, "seed": model.seed_field},
            "negative_prompt_sent": model.negative_prompt_field is not None,
            "seed": (f"each example's seed ({SEED_RULE}, base --seed {ctx.seed}) sent as '{model.seed_field}'"
                     if model.seed_field else
                     "none sent: the paper's inputs for this model have no seed, so generations are not reproducible"),
            "image": {**asdict(cfg.image), "resize": "Lanczos",
                      "sent_as": f"data URI under {cfg.image.upload_threshold_bytes:,} bytes, else POST /v1/files"},
            "client": cfg.client.as_dict(), "concurrency": self.concurrency(ctx), "config": str(cfg.path),
        }

    # -- the request --------------------------------------------------------------------------------

    def _inputs(self, model: HostedModel, inputs, image_ref: str, ctx: PredictContext) -> dict[str, Any]:
        body = {model.image_field: image_ref, model.prompt_field: inputs.prompt}
        if model.negative_prompt_field:
            body[model.negative_prompt_field] = inputs.negative_prompt
        if model.seed_field:
            body[model.seed_field] = int(ctx.seed)
        body.update(model.inputs)
        return body

    def describe(self, sample, ctx: PredictContext) -> dict[str, Any]:
        """The request a run would send (the image elided, the token never)."""
        cfg, model = self.config(ctx), self.model(ctx)
        inputs = model_inputs(sample)
        encoded = encode_first_frame(inputs.image, cfg.image)
        uri_bytes = len(data_uri(encoded, cfg.image.mime))
        how = ("a data URI" if uri_bytes < cfg.image.upload_threshold_bytes
               else "the URL of an upload to POST /v1/files")
        image = (f"<{inputs.image_path.name} as a {cfg.image.width}x{cfg.image.height} {cfg.image.format.upper()} of "
                 f"{len(encoded):,} bytes, sent as {how}; elided>")
        owner, _, name = model.replicate.partition("/")
        out = {"method": "POST", "url": f"{public_url(base_url_from_env())}/v1/models/{owner}/{name}/predictions",
               "headers": {"Authorization": f"Bearer ${TOKEN_ENV}", "Prefer": "wait"},
               "body": {"input": self._inputs(model, inputs, image, ctx)}}
        if ctx.out_dir is not None:
            state = _read_state(PredictionsFolder(ctx.out_dir).hosted_state(ctx.item_of(sample)))
            if state and "prediction_id" in state and state.get("status") not in RESTART_STATUSES:
                out["resumes_prediction"] = state["prediction_id"]
            elif state and "intent" in state:
                out["resolves_interrupted_creation"] = ("an earlier run was stopped while creating this prediction: "
                                                        "the account's recent predictions are checked for it first")
        return out

    # -- running ------------------------------------------------------------------------------------

    def _get_client(self, ctx: PredictContext) -> ReplicateClient:
        """One client (one connection pool) for the whole run; the token is read here, on first use."""
        cfg, workers = self.config(ctx), self.concurrency(ctx)
        with self._lock:
            if self._client is None:
                self._client = ReplicateClient(cfg.client, max_connections=workers + 4)
            return self._client

    def preflight(self, ctx: PredictContext) -> None:
        """Called by the predict stage once before any example: the token and base URL must be usable
        (a UserError, one line, otherwise; never the token itself)."""
        base_url_from_env()
        self.config(ctx)
        token_from_env()

    def request_stop(self) -> None:
        """The run is stopping (SIGTERM, Ctrl-C): create nothing new, stop polling, finish what was paid for."""
        self._stop.set()

    def recover_record(self, out_dir: Path, sample_id: str) -> dict | None:
        """A generation record rebuilt from ``.hosted/<id>.json`` for a video whose record was lost (the run
        was killed between writing the video and its record); None without a stored prediction id."""
        state = _read_state(PredictionsFolder(out_dir).hosted_state(sample_id))
        if not state or not isinstance(state.get("prediction_id"), str):
            return None
        record = dict(state.get("record") or {})
        record.setdefault("prediction_id", state["prediction_id"])
        record.setdefault("prediction_status", state.get("status"))
        record.setdefault("created_at", state.get("created_at"))
        return record

    def _clean_temporaries(self, state_dir: Path, sample_id: str) -> None:
        """Remove what a killed run left of this prediction: partial downloads (``.<item>.<random>.part<ext>``,
        not another sample's ``.<item>.s<k>.<random>.part<ext>``) and unrenamed state files."""
        partial = re.compile(re.escape(f".{sample_id}.") + r"[A-Za-z0-9_]+\.part(\.[A-Za-z0-9]+)?")
        for pattern in (f"{glob.escape(f'.{sample_id}.')}*.part*", f"{glob.escape(f'.{sample_id}.json.')}*.tmp"):
            for stale in state_dir.glob(pattern):
                if pattern.endswith(".part*") and not partial.fullmatch(stale.name):
                    continue
                try:
                    stale.unlink()
                    log.debug("removed %s, left by an interrupted run", stale)
                except OSError:
                    pass

    def predict(self, sample, ctx: PredictContext) -> Prediction:
        cfg, model = self.config(ctx), self.model(ctx)
        client = self._get_client(ctx)
        sample_id = ctx.item_of(sample)  # the prediction's name: its state, download and messages
        if ctx.out_dir is None:
            raise PredictionError(f"example {sample_id}: hosted models need the run's output directory "
                                  "(run them through the predict stage)")
        state_dir = PredictionsFolder(ctx.out_dir).hosted_dir
        with self._lock:
            self._state_dirs.add(state_dir)
        if state_dir.is_dir():
            self._clean_temporaries(state_dir, sample_id)
        state_path = PredictionsFolder(ctx.out_dir).hosted_state(sample_id)
        deadline = Deadline(cfg.client.example_timeout_s, stop=self._stop, stop_grace=cfg.client.stop_grace_s)
        stats = CallStats()
        timings: dict[str, float] = {}
        kept = (f"prediction {{pid}} is kept in {state_path}; a rerun of the same command resumes it without "
                "paying again")

        t0 = time.monotonic()
        inputs = model_inputs(sample)
        encoded = encode_first_frame(inputs.image, cfg.image)
        fingerprint = hashlib.sha256(json.dumps(
            {"model": model.replicate, "input": self._inputs(model, inputs, hashlib.sha256(encoded).hexdigest(), ctx)},
            sort_keys=True).encode()).hexdigest()
        timings["image_s"] = time.monotonic() - t0

        prediction, resumed, adopted, replaced = None, False, False, None
        state = _read_state(state_path)
        same = state is not None and state.get("fingerprint") == fingerprint
        repay = self.options(ctx).repay_expired
        if state and isinstance(state.get("prediction_id"), str):
            if same and state.get("status") not in RESTART_STATUSES:
                prediction = self._resume(client, state["prediction_id"], sample_id, deadline, stats, repay)
                resumed = prediction is not None
            if prediction is None and (same or state.get("status") in RESTART_STATUSES):
                replaced = state["prediction_id"]
        elif state and same:  # an intent without an id: the creation may have reached Replicate
            replaced = state.get("replaces_prediction")
            with self._adopting:  # one adoption at a time: two samples with the same input never take one prediction
                found = self._adopt(client, model, state["intent"], sample_id, state_path, deadline, stats)
                if found is not None:
                    _save_state(state_path, {**state, "prediction_id": found["id"], "status": found.get("status"),
                                             "created_at": found.get("created_at"), "adopted": True})
            if found is not None:
                adopted = True
                prediction = self._resume(client, found["id"], sample_id, deadline, stats, repay)
                resumed = prediction is not None
                if prediction is None:
                    replaced = found["id"]

        sent_as = None
        if prediction is None:
            deadline.check_stop(f"example {sample_id}: creating a prediction")
            t0 = time.monotonic()
            uri = data_uri(encoded, cfg.image.mime)
            if len(uri) < cfg.image.upload_threshold_bytes:
                image_ref, sent_as = uri, "data URI"
            else:
                suffix = "jpg" if cfg.image.format == "jpeg" else "png"
                image_ref = client.upload(encoded, f"{sample_id}.{suffix}", cfg.image.mime, deadline, stats)
                sent_as = "upload"
            timings["upload_s"] = time.monotonic() - t0
            body = self._inputs(model, inputs, image_ref, ctx)
            now = time.time()
            intent = {"model": model.replicate, "input_sha256": input_hash(body),
                      "input_sha256_without_image": input_hash(body, without=model.image_field),
                      "image_field": model.image_field, "at": now,
                      "at_utc": datetime.fromtimestamp(now, timezone.utc).isoformat(timespec="milliseconds")}
            deadline.check_stop(f"example {sample_id}: creating a prediction")
            _save_state(state_path, {"model": model.replicate, "fingerprint": fingerprint, "intent": intent,
                                     **({"replaces_prediction": replaced} if replaced else {})})
            t0 = time.monotonic()
            try:
                prediction = client.create(model.replicate, body, deadline, stats)
            except CreationUncertain as exc:
                raise PredictionError(f"example {sample_id}: {exc}. The attempt is recorded in {state_path}: a rerun "
                                      "of the same command looks for it among the account's recent predictions and "
                                      "adopts it instead of paying again") from None
            timings["create_s"] = time.monotonic() - t0
            _save_state(state_path, {"prediction_id": prediction["id"], "model": model.replicate,
                                     "fingerprint": fingerprint, "status": prediction.get("status"),
                                     "created_at": prediction.get("created_at"), "intent": intent,
                                     **({"replaces_prediction": replaced} if replaced else {})})
        pid = prediction["id"]

        t0 = time.monotonic()
        try:
            prediction = client.wait(prediction, deadline, stats)
        except PredictionError as exc:
            raise PredictionError(f"example {sample_id}: {exc}; {kept.format(pid=pid)}") from None
        finally:
            timings["wait_s"] = time.monotonic() - t0
        status = prediction.get("status")
        if status != "succeeded":
            _save_state(state_path, {**(_read_state(state_path) or {"prediction_id": pid}), "status": status,
                                     "fingerprint": fingerprint})
            error = prediction.get("error") or "no error message"
            raise PredictionError(f"prediction {pid} {status}: {client.scrub(str(error))}")
        url = output_url(prediction.get("output"))
        if url is None:
            raise PredictionError(f"prediction {pid} succeeded without a video URL in its output")
        suffix = Path(url.split("?", 1)[0]).suffix.lower()
        suffix = suffix if suffix in VIDEO_EXTENSIONS else ".mp4"
        t0 = time.monotonic()
        try:
            video, size = client.download(url, state_dir / f"{sample_id}{suffix}", deadline, stats)
        except PredictionError as exc:
            raise PredictionError(f"example {sample_id}: prediction {pid}: {exc}; {kept.format(pid=pid)} and its "
                                  "output fetched again (Replicate keeps outputs for an hour)") from None
        timings["download_s"] = time.monotonic() - t0
        meta = self._metadata(prediction, model, ctx, stats, timings, resumed, replaced, sent_as, size)
        meta["adopted"] = adopted
        meta["output_url"] = client.scrub(public_url(url))
        meta = client.scrub_all(meta)
        _save_state(state_path, {**(_read_state(state_path) or {"prediction_id": pid}), "status": status,
                                 "fingerprint": fingerprint, "downloaded": True, "record": meta})
        return Prediction(video_path=video, metadata=meta)

    def _adopt(self, client: ReplicateClient, model: HostedModel, intent: dict, sample_id: str, state_path: Path,
               deadline: Deadline, stats: CallStats) -> dict | None:
        """The prediction an interrupted creation made, found among the account's recent predictions: the same
        model and exact input, created after the intent (less CLOCK_SKEW_S); None when there is none."""
        at = intent.get("at")
        if not isinstance(at, (int, float)):
            log.warning("example %s: %s holds an intent without a time; creating a new prediction", sample_id,
                        state_path)
            return None
        with self._lock:
            if self._recent is None:
                self._recent = _RecentPredictions(client)
            recent = self._recent
        try:
            listed = recent.since(at - CLOCK_SKEW_S, deadline, stats)
        except PredictionError as exc:
            raise PredictionError(f"example {sample_id}: an earlier run was stopped while creating a prediction "
                                  f"({state_path}) and the account's predictions could not be checked for it ({exc}); "
                                  "not creating another one. Rerun later, or check https://replicate.com/predictions "
                                  f"and delete {state_path} to pay for a new one") from None
        # a prediction another state holds is never adopted: the samples of a model sent no seed share one input
        claimed = _claimed_ids(state_path.parent, state_path.name)
        same_model = [p for p in listed if p.get("model") in (None, intent.get("model")) and p.get("id") not in claimed]
        exact = [p for p in same_model if isinstance(p.get("input"), dict)
                 and input_hash(p["input"]) == intent.get("input_sha256")]
        how = "the same input"
        if not exact:  # Replicate may store an inline image as a URL of its own: compare everything else
            field = intent.get("image_field")
            exact = [p for p in same_model if isinstance(p.get("input"), dict) and field in p["input"]
                     and not str(p["input"][field]).startswith("data:")
                     and input_hash(p["input"], without=field) == intent.get("input_sha256_without_image")]
            how = "the same input apart from the image (which Replicate stores as a URL)"
            if len(exact) > 1:
                raise PredictionError(
                    f"example {sample_id}: an earlier run was stopped while creating a prediction ({state_path}); "
                    f"{len(exact)} recent predictions ({', '.join(p['id'] for p in exact)}) match it apart from the "
                    f"image, so none is adopted and none created. Check https://replicate.com/predictions, then "
                    f"delete {state_path} to pay for a new one")
        if not exact:
            log.info("example %s: the interrupted creation of %s did not reach Replicate; creating it now",
                     sample_id, state_path.name)
            return None
        # the first one created after the intent (an earlier one with the same input is another attempt)
        found = min(exact, key=lambda p: (((_parse_time(p.get("created_at")) or 0.0) < at),
                                          _parse_time(p.get("created_at")) or 0.0))
        log.warning("example %s: adopting prediction %s (%s), created by an interrupted run, instead of paying "
                    "again (%s)", sample_id, found["id"], found.get("status"), how)
        return found

    def _resume(self, client: ReplicateClient, pid: str, sample_id: str, deadline: Deadline,
                stats: CallStats, repay_expired: bool = False) -> dict | None:
        """The stored prediction, to wait for or download again; None when it must be created anew."""
        try:
            prediction = client.get(pid, deadline, stats)
        except ReplicateError as exc:
            if exc.status_code == 404:
                log.warning("example %s: stored prediction %s is unknown to Replicate; creating a new one",
                            sample_id, pid)
                return None
            raise PredictionError(f"example {sample_id}: cannot fetch stored prediction {pid} ({exc}); not creating "
                                  "a new one, rerun later") from None
        status = prediction.get("status")
        if status in RESTART_STATUSES:
            log.info("example %s: stored prediction %s %s; creating a new one", sample_id, pid, status)
            return None
        if status == "succeeded" and (prediction.get("data_removed") or output_url(prediction.get("output")) is None):
            if not repay_expired:  # never pay twice without being asked to
                raise PredictionError(f"example {sample_id}: prediction {pid} succeeded but Replicate has deleted its "
                                      "output (outputs are kept for an hour); rerun with --repay-expired to pay for "
                                      "a new prediction")
            log.warning("example %s: prediction %s succeeded but Replicate has deleted its output; creating a new, "
                        "paid, prediction (--repay-expired)", sample_id, pid)
            return None
        log.info("example %s: resuming prediction %s (%s) without creating a new one", sample_id, pid, status)
        return prediction

    def _metadata(self, prediction: dict, model: HostedModel, ctx: PredictContext, stats: CallStats,
                  timings: dict[str, float], resumed: bool, replaced: str | None, sent_as: str | None,
                  size: int) -> dict[str, Any]:
        # "status" is the stage's own key (it is "succeeded" here): the API's is recorded as prediction_status.
        meta: dict[str, Any] = {
            "prediction_id": prediction["id"], "prediction_status": prediction.get("status"),
            "model": prediction.get("model") or model.replicate, "version": prediction.get("version"),
            "created_at": prediction.get("created_at"), "started_at": prediction.get("started_at"),
            "completed_at": prediction.get("completed_at"), "metrics": prediction.get("metrics") or {},
            "resumed": resumed, "image_sent_as": sent_as, "output_bytes": size,
            "requests": stats.requests, "retries": stats.retries,
            "retried": {"rate_limited": stats.rate_limited, "server_errors": stats.server_errors,
                        "network_errors": stats.network_errors},
            "client_seconds": {k: round(v, 3) for k, v in timings.items()},
            "seed": int(ctx.seed) if model.seed_field else None,
        }
        if model.negative_prompt_field is None:
            meta["negative_prompt"] = None  # not sent to this model
        if replaced:
            meta["replaces_prediction"] = replaced
        for key, value in prediction.items():  # any cost or billing facts the API adds
            if any(word in key.lower() for word in ("cost", "price", "billing")):
                meta[key] = value
        return meta

    def close(self) -> None:
        """Close the connection pool and remove downloads the stage has already copied into place (the video of
        that name, as large, written after the download: not an older video of an example that another process
        sharing the folder is downloading again)."""
        with self._lock:
            client, self._client = self._client, None
            state_dirs = list(self._state_dirs)
        if client is not None:
            client.close()
        for state_dir in state_dirs:
            for video in state_dir.glob("*") if state_dir.is_dir() else []:
                if video.suffix.lower() not in VIDEO_EXTENSIONS or video.name.startswith("."):
                    continue
                final = state_dir.parent / video.name
                try:
                    placed, downloaded = final.stat(), video.stat()
                    if (final.is_file() and placed.st_size == downloaded.st_size
                            and placed.st_mtime_ns >= downloaded.st_mtime_ns):
                        video.unlink()
                except OSError:
                    pass
