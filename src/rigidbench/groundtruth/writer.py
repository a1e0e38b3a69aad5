"""Bundle files from one rendered example: masks, depth, trajectories, contacts, point tracks, prompt,
scene spec, video and metadata (the artifact table of the paper), written into a temporary bundle
directory whose frames are already there. Independent of Blender: it reads the arrays of a
``blender.render.ExampleRender``.
"""

from __future__ import annotations

import dataclasses
import logging
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .. import __version__
from ..config import RenderPreset
from ..jsonio import write_json
from ..rotations import quat_to_matrix
from ..video import write_video
from . import bundle as B
from .camera_model import camera_pose, intrinsics, project
from .tracks import DEPTH_TOLERANCE, POINTS_PER_ACTOR, RENDER_TRACK_RULE, TRACK_RULES, ground_truth_tracks
from .trajectory import save_contacts

log = logging.getLogger(__name__)


def image_sides(names: Sequence[str], positions_m: np.ndarray, K: np.ndarray, R_c: np.ndarray,
                t_c: np.ndarray) -> dict[str, Any]:
    """Which side of the image each actor starts on, from the camera's point of view: actor centres at
    frame 0 (``positions_m`` (N,3)) are projected and compared with the mean projected x of all
    actors; "left" means a smaller image column (x) than that mean. Actor names themselves are neutral
    (e.g. ramp_a / ramp_b in ramp_collision) because the camera may view the task from either side."""
    uv, _ = project(np.asarray(positions_m, float), K, R_c, t_c)
    x = uv[:, 0]
    mid = float(x.mean())
    return {"convention": "camera view at frame 0: left = projected actor centre has a smaller image x "
                          "(column) than the mean over actors (within 0.5 px: centre)",
            "actors": {n: ("left" if xi < mid - 0.5 else "right" if xi > mid + 0.5 else "centre")
                       for n, xi in zip(names, map(float, x))},
            "image_x_px": {n: round(float(xi), 2) for n, xi in zip(names, x)}}


def write_bundle(tmp: Path, result: Any, preset: RenderPreset, total_s: float) -> None:
    """Turn a ``blender.render.ExampleRender`` into the bundle files inside ``tmp`` (frames already there)."""
    from PIL import Image

    spec = result.spec
    T = result.index.shape[0]
    names = tuple(b.name for b in spec.bodies)
    roles = tuple(b.role for b in spec.bodies)
    traj = B.slice_trajectory(result.simulation.trajectory, T)
    if traj.names != names:
        raise B.BundleError(f"example {spec.sample_id}: simulated actors {traj.names} differ from the spec's {names}")
    masks = B.masks_from_index(result.index, len(names))
    cam = spec.camera
    R_c, t_c = camera_pose(cam.target_m, cam.azimuth_deg, cam.elevation_deg, cam.distance_m)
    K = intrinsics(spec.camera.lens_mm, spec.camera.sensor_width_mm, *preset.resolution)
    tracks = ground_truth_tracks(masks, result.depth_m, K, R_c, t_c, quat_to_matrix(traj.quat_wxyz), traj.positions_m,
                                 np.array([r == "active" for r in roles]), seed=spec.seed,
                                 rule=TRACK_RULES[RENDER_TRACK_RULE])
    if tracks.n_points and not tracks.visibility[:, 0].all():
        log.warning("example %s: %d ground-truth points are not visible at frame 0", spec.sample_id,
                    int((~tracks.visibility[:, 0]).sum()))
    B.write_masks(tmp / B.MASKS_FILE, masks, names, roles)
    B.write_depth(tmp / B.DEPTH_FILE, result.depth_m)
    traj.save(tmp / B.TRAJECTORIES_FILE)
    save_contacts(tmp / B.CONTACTS_FILE, [c for c in result.simulation.contacts if c.frame < T], frames=T,
                  tolerance_m=result.simulation.tolerance_m)
    tracks.save(tmp / B.TRACKS_FILE)
    (tmp / B.PROMPT_FILE).write_text(spec.prompt + "\n")
    (tmp / B.SPEC_FILE).write_text(spec.to_json())
    frames = np.stack([np.asarray(Image.open(tmp / B.FRAMES_DIR / B.frame_name(k)).convert("RGB")) for k in range(T)])
    write_video(tmp / B.VIDEO_FILE, frames, fps=float(spec.sim.fps))
    render_facts = {"engine": "CYCLES", "device": result.device.describe(), "device_kind": result.device.kind,
                    **{k: v for k, v in dataclasses.asdict(preset).items() if k not in ("name", "resolution", "frames")},
                    "motion_blur": False, "depth_of_field": False,
                    "seed": spec.seed, "data_passes": "1 sample at pixel centres (filter width 0.01 px)",
                    "color_management": result.color_management, "procedural_assets": True}
    software = {**result.software, "rigidbench": __version__, "python": sys.version.split()[0],
                "numpy": np.__version__}
    seconds = {**{k: round(v, 3) for k, v in result.seconds.items()}, "total": round(total_s, 3)}
    track_facts = {"points_per_actor": POINTS_PER_ACTOR, "depth_tolerance": DEPTH_TOLERANCE,
                   **TRACK_RULES[RENDER_TRACK_RULE].facts(), "sampled": [int(n) for n in tracks.points_per_actor]}
    meta = B.make_metadata(spec, resolution=preset.resolution, frames=T, simulated_frames=result.simulation.frames,
                           fps=float(spec.sim.fps), render=render_facts, software=software, seconds=seconds,
                           tracks=track_facts)
    meta["image_sides"] = image_sides(names, traj.positions_m[:, 0], K, R_c, t_c)
    write_json(tmp / B.METADATA_FILE, meta, allow_nan=False)


__all__ = ["image_sides", "write_bundle"]
