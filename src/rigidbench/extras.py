"""Optional packages: which extra of pyproject.toml installs each one, and the one-line error a missing one gives.

A plain ``pip install rigidbench`` holds numpy, scipy, PyYAML, pymunk, Pillow and tqdm: enough for ``--help``,
``manifest`` and ``inputs``. The rest comes with an extra, one per kind of user (docs/install.md)::

    score    download, import, validate, evaluate (gt and neural perception), readouts, weights, report
             (= eval + report + neural + httpx)
    sim      simulate, render, show: Blender as a Python module
    models   predict and audit with the video models (includes score)
    train    preprocess, train, probe (includes models)
    guardrail, ray, dev

Optional packages are imported inside the functions that need them. ``require`` imports one and raises
``MissingExtra`` naming the extra; a bare import that fails elsewhere raises ModuleNotFoundError, which
``explain`` turns into the same line (the command line and ``registry.load_target`` use it).
"""

from __future__ import annotations

import importlib
import importlib.util
from types import ModuleType, TracebackType

from .errors import MissingExtra

#: optional top-level module -> (the distribution that installs it, the extra to name when it is missing)
OPTIONAL: dict[str, tuple[str, str]] = {
    "bpy": ("bpy", "sim"), "mathutils": ("bpy", "sim"), "bmesh": ("bpy", "sim"), "addon_utils": ("bpy", "sim"),
    "bpy_extras": ("bpy", "sim"), "OpenEXR": ("OpenEXR", "sim"),
    "torch": ("torch", "score"), "cv2": ("opencv-python-headless", "score"), "av": ("av", "score"),
    "pytorch_msssim": ("pytorch-msssim", "score"), "matplotlib": ("matplotlib", "score"),
    "transformers": ("transformers", "score"), "tokenizers": ("tokenizers", "score"),
    "safetensors": ("safetensors", "score"), "huggingface_hub": ("huggingface_hub", "score"),
    "httpx": ("httpx", "score"), "httpcore": ("httpcore", "score"),
    "diffusers": ("diffusers", "models"), "accelerate": ("accelerate", "models"), "peft": ("peft", "models"),
    "ftfy": ("ftfy", "models"),
    "cosmos_guardrail": ("cosmos-guardrail", "guardrail"),
    "sklearn": ("scikit-learn", "train"),
    "ray": ("ray", "ray"),
}

#: the extras each extra includes (pyproject.toml's self-references, followed through)
INCLUDES: dict[str, frozenset[str]] = {
    "score": frozenset({"eval", "report", "neural"}),
    "models": frozenset({"score", "eval", "report", "neural"}),
    "train": frozenset({"models", "score", "eval", "report", "neural"}),
}

#: our packages whose users install a larger extra: a package they import is named with that extra
OWNERS: tuple[tuple[str, str], ...] = tuple((package, "train") for package in (
    "rigidbench.train", "rigidbench.probe", "rigidbench.stages.preprocess", "rigidbench.stages.probe_extract",
    "rigidbench.stages.probe_bases", "rigidbench.stages.probe_intervene", "rigidbench.commands.training",
    "rigidbench.commands.probing"))


def install_command(extra: str) -> str:
    """What to type; works from any install of rigidbench (pip reads the extra from the installed metadata)."""
    return f"pip install 'rigidbench[{extra}]'"


def extra_for(module: str, importer: str | None = None) -> str:
    """The extra to install for the optional ``module`` (a dotted name is fine), when imported by our module
    ``importer``: its owner's extra where that includes the module's (``OWNERS``), else the module's own."""
    own = OPTIONAL[module.partition(".")[0]][1]
    for prefix, extra in OWNERS:
        if importer and (importer == prefix or importer.startswith(prefix + ".")) and (
                own == extra or own in INCLUDES.get(extra, ())):
            return extra
    return own


def message(module: str, purpose: str, extra: str | None = None, importer: str | None = None) -> str:
    """One line: ``purpose`` needs the package, which is not installed, and the pip command that installs it."""
    top = module.partition(".")[0]
    dist = OPTIONAL[top][0]
    what = dist if dist.lower() == top.lower() else f"{dist} ({top})"
    return (f"{purpose} needs {what}, which is not installed: "
            f"{install_command(extra or extra_for(top, importer))}")


def missing(module: str, purpose: str, extra: str | None = None) -> MissingExtra:
    """The ``MissingExtra`` for ``module`` (to raise)."""
    return MissingExtra(message(module, purpose, extra), name=module.partition(".")[0])


def require(module: str, purpose: str, extra: str | None = None) -> ModuleType:
    """Import and return ``module`` (an optional package, or a submodule of one); raises ``MissingExtra`` naming
    ``purpose`` and the extra when it, or an optional package it needs, is not installed."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        top = (exc.name or "").partition(".")[0]
        if top not in OPTIONAL:
            raise
        raise missing(top, purpose, extra) from None


def available(module: str) -> bool:
    """Whether ``module`` can be imported, without importing it."""
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


def _importer(tb: TracebackType | None) -> str | None:
    """The innermost module of ours in a traceback (the one whose import failed)."""
    found = None
    while tb is not None:
        name = tb.tb_frame.f_globals.get("__name__", "")
        if name == "rigidbench" or name.startswith("rigidbench."):
            found = name
        tb = tb.tb_next
    return found


def explain(exc: ModuleNotFoundError, purpose: str) -> str | None:
    """The one line for a failed import of an optional package (``MissingExtra``'s own message), or None when
    the missing module is not one of ours to name (a bug, or a plug-in's own package)."""
    if isinstance(exc, MissingExtra):
        return str(exc)
    top = (exc.name or "").partition(".")[0]
    if top not in OPTIONAL:
        return None
    return message(top, purpose, importer=_importer(exc.__traceback__))
