"""The reference side of one example: what scoring a sample needs of the reference and not of the sample.

Every sample (generation) of an example is scored against the same reference bundle. ``ReferenceSide`` holds
that bundle's reader (``groundtruth.bundle.Sample``: its frames, masks, depth, tracks, trajectory, contacts and
scene spec, each decoded on first use and kept) and a cache of the quantities derived from the reference
alone (the active actors' masks and the tracked points' world positions cut to the compared frames; the
metrics' and readouts' own reference quantities through ``MetricInputs.reference_shared``). The evaluate
worker keeps the side of the last example it scored; items come example by example, so the samples of one
example after the first pay for none of it again. The values are those computed per sample without it,
bit for bit: only where they are computed changes.

``prefetch`` starts reading the large reference files on a background thread while the sample's video is
decoded (PNG and zlib decoding release the GIL), so even one sample overlaps the two.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..errors import EXAMPLE_ERRORS
from ..groundtruth.bundle import Sample
from ..video import reference_times
from .scoring import tracked_points_world


class ReferenceSide:
    """One reference example's reader and the reference-only quantities its samples share. ``ref_hash``: the
    content hash of the bundle it was read from (``evaluation.keys.reference_hash``), so that a worker reuses
    it only for the same bundle (``serves``); ``samples``: how many samples of the example are to be scored
    against it (a quantity that costs much memory, SSIM's filtered reference, is kept only for more than one)."""

    def __init__(self, sample: Sample, ref_hash: str | None = None, samples: int = 1):
        self.sample = sample
        self.ref_hash = ref_hash
        self.samples = samples
        #: reference-only quantities by name (and compared length): ``shared`` and ``MetricInputs.reference_shared``
        self.cache: dict[str, Any] = {}
        self._prefetch: threading.Thread | None = None

    @classmethod
    def read(cls, path: str | Path, ref_hash: str | None = None, samples: int = 1) -> "ReferenceSide":
        """The side of the bundle at ``path`` (nothing is decoded yet)."""
        return cls(Sample(path), ref_hash, samples)

    def serves(self, path: str | Path, ref_hash: str | None) -> bool:
        """Whether this side is the one of the bundle at ``path`` with content hash ``ref_hash`` (None: unknown,
        never reused)."""
        return ref_hash is not None and self.ref_hash == ref_hash and self.sample.path == Path(path)

    def prefetch(self) -> None:
        """Start decoding the reference's frames, masks, depth, tracks and trajectory on a background thread
        (once). A file that cannot be read is left to the first use, which raises its BundleError there."""
        if self._prefetch is not None:
            return

        def load() -> None:
            for name in ("masks", "tracks", "trajectory", "depth", "frames"):
                try:
                    getattr(self.sample, name)
                except EXAMPLE_ERRORS:  # read again, and reported, where the scoring needs it
                    return

        self._prefetch = threading.Thread(target=load, name=f"reference {self.sample.path.name}", daemon=True)
        self._prefetch.start()

    def wait(self) -> None:
        """Until the prefetch (if any) has finished; the large arrays it read are then read-only (the samples
        share them: a measurement that wrote into one would change the next sample's scores)."""
        if self._prefetch is not None:
            self._prefetch.join()
        loaded = self.sample.__dict__  # where functools.cached_property keeps what was read
        for array in (loaded.get("frames"), loaded.get("depth"), (loaded.get("_masks") or {}).get("masks")):
            if isinstance(array, np.ndarray):
                array.flags.writeable = False

    def shared(self, key: str, compute: Callable[[], Any]) -> Any:
        """``compute()`` once per reference example, whichever sample asks first (an array comes back
        read-only)."""
        if key not in self.cache:
            value = compute()
            if isinstance(value, np.ndarray):
                value.flags.writeable = False
            self.cache[key] = value
        return self.cache[key]

    @property
    def times_s(self) -> np.ndarray:
        """(T,) s: the reference frame times k / fps."""
        return self.shared("times_s", lambda: reference_times(self.sample.n_frames, self.sample.fps))

    @property
    def first_frame(self) -> np.ndarray:
        """(H,W,3) uint8: frame 0 (from the decoded frames when they are there, else its PNG alone)."""
        if "frames" in self.sample.__dict__:  # functools.cached_property keeps the decoded frames there
            return self.sample.frames[0]
        return self.shared("first_frame", lambda: self.sample.frame(0))

    def active_masks(self, n: int) -> np.ndarray:
        """(n,A,H,W) bool: the masks of the active actors over the first n frames."""
        return self.shared(f"active_masks:{n}", lambda: self.sample.masks[:n][:, self.sample.active_indices])

    def tracked_points(self, n: int) -> np.ndarray:
        """(P,n,3) m: the world positions of the ground-truth query points (``scoring.tracked_points_world``)."""
        return self.shared(f"tracked_points:{n}", lambda: tracked_points_world(self.sample, n))
