"""Named evaluation protocols: the rules, beyond the metrics' formulas, that move scores.

The paper's numbers come from the authors' released evaluator. Protocol ``rigidbench-v1`` (the
default) follows it on every rule we know to move scores: predictions decoded with OpenCV (which
ignores the colour-matrix tag and converts with BT.601; frame k at k / the header's frame rate),
resized to the reference size with PIL's Lanczos when the size differs, stored as JPEG (quality 95,
4:4:4 chroma) that perception and every metric then read, and the release's edge rules in the
metrics (``metrics.common.EDGE_RULES``: e.g. a generated point outside the image takes the border
pixel's depth in ATE-3D; where the release stops with an exception the value is NaN with that reason).
``paper-rules`` keeps the same JPEG round trip but decodes with PyAV, honouring the colour tag, and
applies our edge rules (the paper's wording), so that comparing it with ``rigidbench-v1`` isolates the
rules; ``lossless`` is ``paper-rules`` without the JPEG round trip. The protocol is part of every
example's input key and is written, with the reference set's identity, into each record,
``results.json`` and ``run.json``; ``docs/metrics.md`` gives the measured effect of each difference.
"""

from __future__ import annotations

import io
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from ..errors import UserError
from ..executors import usable_cores
from ..metrics.common import EDGE_RULES, EdgeRules
from ..video import DECODERS, Video, read_video

Decoder = Literal["pyav", "opencv"]


@dataclass(frozen=True)
class Protocol:
    """name; edge_rules: the metrics' edge-case rules ("published": the released evaluator's, "paper": ours);
    decoder: how predictions are decoded ("opencv": as the released evaluator, "pyav": honouring the colour
    tag); jpeg_quality: JPEG round trip of every generated frame after resizing (None: none)."""

    name: str
    description: str
    edge_rules: EdgeRules
    decoder: Decoder
    jpeg_quality: int | None

    def __post_init__(self) -> None:
        if self.edge_rules not in EDGE_RULES or self.decoder not in DECODERS:
            raise ValueError(f"protocol {self.name}: edge_rules must be one of {EDGE_RULES} and decoder one of "
                             f"{DECODERS}; got {self.edge_rules!r}, {self.decoder!r}")

    def facts(self) -> dict:
        return asdict(self)

    def key(self) -> str:
        """The rules that decide scores, as one string for the input key (the description is left out)."""
        return f"{self.name}:rules={self.edge_rules}:decoder={self.decoder}:jpeg={self.jpeg_quality}"

    def decode(self, path: str | Path, until_s: float | None = None) -> Video:
        """The prediction at ``path`` decoded with this protocol's decoder (``video.read_video``)."""
        return read_video(path, until_s=until_s, decoder=self.decoder)

    def prepare(self, frames: np.ndarray, in_place: bool = False) -> np.ndarray:
        """frames (T,H,W,3) uint8 at the reference size -> the frames perception and metrics see; ``in_place``:
        written over ``frames`` (the evaluator's own decoded copy: no second clip-sized array)."""
        if self.jpeg_quality is None:
            return frames
        return jpeg_roundtrip(frames, self.jpeg_quality, out=frames if in_place and frames.flags.writeable else None)


PROTOCOLS = {p.name: p for p in (
    Protocol("rigidbench-v1", "the published evaluator's rules (paper): predictions decoded with OpenCV (colour tag "
             "ignored), resized to the reference size with Lanczos, stored as JPEG q95 4:4:4 before perception "
             "and metrics, and the released evaluator's edge rules in the metrics", "published", "opencv", 95),
    Protocol("paper-rules", "as rigidbench-v1 (JPEG q95 4:4:4 round trip) but decoded with PyAV honouring the colour "
             "tag, and our edge rules (the paper's wording, docs/metrics.md)", "paper", "pyav", 95),
    Protocol("lossless", "our edge rules, PyAV decoding honouring the colour tag, generated frames resized with "
             "Lanczos and used as decoded (no JPEG round trip)", "paper", "pyav", None),
)}
DEFAULT_PROTOCOL = "rigidbench-v1"


def get_protocol(name: str | None) -> Protocol:
    """The protocol called ``name`` (default ``rigidbench-v1``); UserError naming the known ones."""
    name = name or DEFAULT_PROTOCOL
    try:
        return PROTOCOLS[name]
    except KeyError:
        raise UserError(f"unknown protocol '{name}'; known: {', '.join(PROTOCOLS)}") from None


def jpeg_roundtrip(frames: np.ndarray, quality: int = 95, out: np.ndarray | None = None) -> np.ndarray:
    """frames (T,H,W,3) or (H,W,3) uint8 -> the same frames after a JPEG encode/decode at ``quality``
    with 4:4:4 chroma (PIL, as the released evaluator saved its prepared frames); written into ``out`` (of
    frames' shape; ``frames`` itself is allowed: each frame is encoded before its place is written) when given."""
    from PIL import Image

    single = frames.ndim == 3
    batch = frames[None] if single else frames
    if out is None:
        out = np.empty_like(frames)
    elif out.shape != frames.shape or out.dtype != np.uint8:
        raise ValueError(f"out must be uint8 {frames.shape}, got {out.dtype} {out.shape}")
    result, out = out, (out[None] if single else out)

    def roundtrip(t: int) -> None:
        buffer = io.BytesIO()
        Image.fromarray(np.ascontiguousarray(batch[t])).save(buffer, format="JPEG", quality=quality, subsampling=0)
        buffer.seek(0)
        with Image.open(buffer) as im:
            out[t] = np.asarray(im if im.mode == "RGB" else im.convert("RGB"))

    # Frames are independent and PIL releases the GIL while it encodes and decodes: a few threads share them.
    with ThreadPoolExecutor(max_workers=usable_cores(min(4, max(len(batch), 1)))) as pool:
        list(pool.map(roundtrip, range(len(batch))))
    return result


__all__ = ["Protocol", "PROTOCOLS", "DEFAULT_PROTOCOL", "Decoder", "get_protocol", "jpeg_roundtrip"]
