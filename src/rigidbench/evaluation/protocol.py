"""Named evaluation protocols: the rules, beyond the metrics themselves, that move scores.

The paper's numbers come from the authors' released evaluator (protocol ``rigidbench-v1``). Its
preparation step decodes every generated frame, resizes it to the reference size with PIL's
Lanczos when the size differs, and stores it as a JPEG (quality 95, 4:4:4 chroma) that
perception and every metric then read. ``rigidbench-v1`` reproduces that round trip; ``lossless``
skips it (our earlier rule: the decoded frames go straight to perception and the metrics). The
protocol is part of every example's input key and is written, with the reference set's identity,
into ``results.json`` and ``run.json``; ``docs/metrics.md`` gives the measured effect of each
difference.
"""

from __future__ import annotations

import io
from dataclasses import asdict, dataclass

import numpy as np

from ..errors import UserError


@dataclass(frozen=True)
class Protocol:
    """name; jpeg_quality: JPEG round trip of every generated frame after resizing (None: none)."""

    name: str
    description: str
    jpeg_quality: int | None

    def facts(self) -> dict:
        return asdict(self)

    def prepare(self, frames: np.ndarray) -> np.ndarray:
        """frames (T,H,W,3) uint8 at the reference size -> the frames perception and metrics see."""
        if self.jpeg_quality is None:
            return frames
        return jpeg_roundtrip(frames, self.jpeg_quality)


PROTOCOLS = {
    "rigidbench-v1": Protocol("rigidbench-v1", "the published evaluator's rules (paper): generated frames resized to "
                              "the reference size with Lanczos, then stored as JPEG q95 4:4:4 before perception and "
                              "metrics", 95),
    "lossless": Protocol("lossless", "generated frames resized with Lanczos and used as decoded (no JPEG round trip)",
                         None),
}
DEFAULT_PROTOCOL = "rigidbench-v1"


def get_protocol(name: str | None) -> Protocol:
    """The protocol called ``name`` (default ``rigidbench-v1``); UserError naming the known ones."""
    name = name or DEFAULT_PROTOCOL
    try:
        return PROTOCOLS[name]
    except KeyError:
        raise UserError(f"unknown protocol '{name}'; known: {', '.join(PROTOCOLS)}") from None


def jpeg_roundtrip(frames: np.ndarray, quality: int = 95) -> np.ndarray:
    """frames (T,H,W,3) or (H,W,3) uint8 -> the same frames after a JPEG encode/decode at ``quality``
    with 4:4:4 chroma (PIL, as the released evaluator saved its prepared frames)."""
    from PIL import Image

    single = frames.ndim == 3
    batch = frames[None] if single else frames
    out = np.empty_like(batch)
    for t, frame in enumerate(batch):
        buffer = io.BytesIO()
        Image.fromarray(np.ascontiguousarray(frame)).save(buffer, format="JPEG", quality=quality, subsampling=0)
        buffer.seek(0)
        with Image.open(buffer) as im:
            out[t] = np.asarray(im.convert("RGB"))
    return out[0] if single else out


__all__ = ["Protocol", "PROTOCOLS", "DEFAULT_PROTOCOL", "get_protocol", "jpeg_roundtrip"]
