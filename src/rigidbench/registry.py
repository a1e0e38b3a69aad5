"""One registry idiom for everything that is looked up by name: metrics, perception backends,
predictors.

An entry is a small frozen record with a ``name``, a ``target`` (``"package.module:attr"``,
imported only when the entry is loaded, so registering costs nothing and ``--help`` stays
instant), optional ``aliases`` and whatever metadata its kind needs (a metric's display name and
direction, a predictor's kind). Looking up an unknown name raises ``UnknownNameError`` listing the
nearest known names. A registry reads like a mapping from canonical name to entry, in
registration order::

    METRICS.add(MetricInfo("iou", "rigidbench.metrics.masks:score_iou", ...))
    METRICS["IoU"]          # by alias, case-insensitive
    METRICS.load("iou")     # imports rigidbench.metrics.masks and returns score_iou
"""

from __future__ import annotations

import contextlib
import difflib
import importlib
from collections.abc import Iterator, Mapping
from typing import Any, Generic, Protocol, TypeVar

from .errors import RigidBenchError, UnknownNameError
from .extras import explain


class Entry(Protocol):
    name: str
    target: str
    aliases: tuple[str, ...]


E = TypeVar("E", bound=Entry)


def load_target(target: str, what: str = "object") -> Any:
    """Import ``"package.module:attr"`` and return the attribute; a missing package or attribute is a
    RigidBenchError naming the target and what to install or fix."""
    module_name, sep, attr = target.partition(":")
    if not sep or not module_name or not attr:
        raise RigidBenchError(f"{what} '{target}': expected 'package.module:attr'")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name and module_name.startswith(exc.name) and not exc.name.startswith("rigidbench"):
            raise RigidBenchError(f"{what} '{target}': no module named '{exc.name}' (is it on PYTHONPATH?)") from None
        if exc.name and exc.name.startswith("rigidbench"):
            raise
        line = explain(exc, f"{what} '{target}'")
        raise RigidBenchError(line or f"{what} '{target}' needs the package '{exc.name}', which is not installed: "
                                      "install it with pip") from None
    try:
        obj = module
        for part in attr.split("."):
            obj = getattr(obj, part)
    except AttributeError:
        raise RigidBenchError(f"{what} '{target}': module '{module_name}' has no attribute '{attr}'") from None
    return obj


class LazyRegistry(Mapping, Generic[E]):
    """Canonical name -> entry, in registration order; ``kind`` names the things held ("metric")."""

    def __init__(self, kind: str, entries: tuple[E, ...] | list[E] = ()):
        self.kind = kind
        self._entries: dict[str, E] = {}
        self._keys: dict[str, str] = {}  # lower-case name or alias -> canonical name
        for entry in entries:
            self.add(entry)

    # -- registration ------------------------------------------------------------------------------

    def add(self, entry: E) -> E:
        """Register ``entry``; a name or alias already taken is an error (registries never shadow)."""
        keys = [entry.name, *entry.aliases]
        taken = [k for k in keys if k.lower() in self._keys and self._keys[k.lower()] != entry.name]
        if entry.name in self._entries or taken:
            raise ValueError(f"{self.kind} '{entry.name}': name or alias already registered "
                             f"({', '.join(taken or [entry.name])})")
        self._entries[entry.name] = entry
        for key in keys:
            self._keys[key.lower()] = entry.name
        return entry

    def remove(self, name: str) -> E:
        """Unregister and return the entry called ``name`` (or one of its aliases)."""
        entry = self[name]
        del self._entries[entry.name]
        self._keys = {k: v for k, v in self._keys.items() if v != entry.name}
        return entry

    @contextlib.contextmanager
    def added(self, entry: E) -> Iterator[E]:
        """Register ``entry`` for the duration of a ``with`` block (plug-ins in tests and scripts)."""
        self.add(entry)
        try:
            yield entry
        finally:
            self.remove(entry.name)

    # -- lookup ------------------------------------------------------------------------------------

    def __getitem__(self, name: str) -> E:
        canonical = self._keys.get(str(name).lower())
        if canonical is None:
            raise UnknownNameError(self.unknown_message(str(name)))
        return self._entries[canonical]

    def __iter__(self) -> Iterator[str]:
        return iter(self._entries)

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, name: object) -> bool:
        return isinstance(name, str) and name.lower() in self._keys

    def names(self) -> tuple[str, ...]:
        return tuple(self._entries)

    def nearest(self, name: str, n: int = 3) -> list[str]:
        """Up to ``n`` canonical names closest to ``name`` (by name or alias)."""
        close = difflib.get_close_matches(name.lower(), list(self._keys), n=n * 2, cutoff=0.5)
        out: list[str] = []
        for key in close:
            if self._keys[key] not in out:
                out.append(self._keys[key])
        return out[:n]

    def unknown_message(self, name: str) -> str:
        near = self.nearest(name)
        hint = f" Did you mean {' or '.join(repr(n) for n in near)}?" if near else ""
        return f"unknown {self.kind} '{name}'.{hint} Known {self.kind}s: {', '.join(self._entries)}"

    def load(self, name: str) -> Any:
        """Import and return the target of the entry called ``name``."""
        entry = self[name]
        return load_target(entry.target, f"{self.kind} '{entry.name}'")
