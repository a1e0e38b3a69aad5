"""A PNG contact sheet of one bundle: first, middle and last frame as RGB with the ground-truth
tracks, the actor masks overlaid in colour, and the colour-mapped depth."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .bundle import Sample

TRAIL_FRAMES = 8  # frames of track history drawn behind each point


def sheet_frames(n_frames: int) -> list[int]:
    """Indices of the first, middle and last frame (deduplicated for very short clips)."""
    return sorted({0, (n_frames - 1) // 2, n_frames - 1})


def actor_colours(n: int) -> np.ndarray:
    """(n,3) float RGB in [0,1], distinct per actor."""
    import matplotlib

    cmap = matplotlib.colormaps["tab10"]
    return np.array([cmap(k % 10)[:3] for k in range(n)])


def mask_overlay(rgb: np.ndarray, masks: np.ndarray, colours: np.ndarray, alpha: float = 0.6) -> np.ndarray:
    """rgb (H,W,3) uint8, masks (N,H,W) bool, colours (N,3) in [0,1]. Returns (H,W,3) float in [0,1]:
    the frame dimmed, each actor's pixels tinted with its colour."""
    out = rgb.astype(np.float64) / 255.0 * 0.45
    for m, c in zip(masks, colours):
        out[m] = (1 - alpha) * out[m] + alpha * c
    return np.clip(out, 0.0, 1.0)


def depth_colours(depth_m: np.ndarray, near_m: float, far_m: float) -> np.ndarray:
    """depth_m (H,W) m -> (H,W,3) float RGB: disparity 1/depth between 1/far_m and 1/near_m on the
    turbo map (near = red), so the actors keep their contrast against a distant background; no
    surface (inf) is black."""
    import matplotlib

    finite = np.isfinite(depth_m) & (depth_m > 0)
    disparity = np.where(finite, 1.0 / np.where(finite, depth_m, 1.0), 0.0)
    lo, hi = 1.0 / far_m, 1.0 / near_m
    x = np.clip((disparity - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    rgb = matplotlib.colormaps["turbo"](x)[..., :3]
    rgb[~finite] = 0.0
    return rgb


def contact_sheet_figure(sample: Sample):
    """A matplotlib Figure: rows RGB + tracks, masks, depth; columns first, middle, last frame."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    ts = sheet_frames(sample.n_frames)
    W, H = sample.resolution
    names, roles = sample.actor_names, sample.roles
    colours = actor_colours(len(names))
    masks, depth = sample.masks, sample.depth
    finite = depth[np.isfinite(depth)]
    lo, hi = (np.percentile(finite, [0.5, 99.5]) if finite.size else (1.0, 2.0))
    tracks = sample.tracks
    cols = len(ts)
    fig, axes = plt.subplots(3, cols, figsize=(3.6 * cols, 3.6 * 3 * H / W + 1.4), squeeze=False,
                             layout="constrained")
    for j, t in enumerate(ts):
        rgb = sample.frame(t)
        ax = axes[0, j]
        ax.imshow(rgb)
        for p in range(tracks.n_points):
            c = colours[tracks.actor_index[p]]
            start = max(0, t - TRAIL_FRAMES)
            trail = tracks.tracks_px[p, start:t + 1]
            vis = tracks.visibility[p, start:t + 1]
            if vis.sum() > 1:
                ax.plot(trail[vis, 0], trail[vis, 1], "-", color=c, lw=0.8, alpha=0.7)
            x, y = tracks.tracks_px[p, t]
            if tracks.visibility[p, t]:
                ax.plot(x, y, "o", ms=3, mfc=c, mec="white", mew=0.4)
            elif 0 <= x < W and 0 <= y < H:
                ax.plot(x, y, "x", ms=3, color=c, mew=0.8)
        ax.set_title(f"frame {t}: RGB + tracks", fontsize=8)
        axes[1, j].imshow(mask_overlay(rgb, masks[t], colours))
        axes[1, j].set_title(f"frame {t}: masks", fontsize=8)
        axes[2, j].imshow(depth_colours(depth[t], float(lo), float(hi)))
        axes[2, j].set_title(f"frame {t}: disparity, depth {lo:.2f}-{hi:.2f} m", fontsize=8)
    for ax in axes.ravel():
        ax.set_xlim(-0.5, W - 0.5)
        ax.set_ylim(H - 0.5, -0.5)
        ax.set_xticks([])
        ax.set_yticks([])
    handles = [plt.Line2D([], [], marker="s", ls="", color=c, label=f"{n} ({r})")
               for n, r, c in zip(names, roles, colours)]
    fig.legend(handles=handles, loc="outside lower center", ncol=min(len(names), 5), fontsize=7, frameon=False)
    meta = sample.metadata
    fig.suptitle(f"{sample.sample_id} {meta['task']} / {meta['scene']} / {meta['partition']}: {sample.prompt}\n"
                 f"{tracks.n_points} ground-truth points: o visible, x occluded",
                 fontsize=9)
    return fig


def write_contact_sheet(sample: Sample, out_path: str | Path, dpi: int = 150) -> Path:
    """Render ``contact_sheet_figure`` to a PNG at ``out_path``; returns the path."""
    import matplotlib.pyplot as plt

    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    fig = contact_sheet_figure(sample)
    try:
        fig.savefig(out_path, dpi=dpi)
    finally:
        plt.close(fig)
    return out_path


__all__ = ["sheet_frames", "actor_colours", "mask_overlay", "depth_colours", "contact_sheet_figure",
           "write_contact_sheet"]
