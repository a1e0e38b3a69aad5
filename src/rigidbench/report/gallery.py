"""The docs gallery's pure parts: which examples, which frames, and how a sheet is drawn.

``scripts/make_gallery.py`` renders the chosen examples at the ``paper`` preset (data passes for
every frame, RGB only at the event frames) and calls these to lay the sheets out:

- ``pick_examples``: one eval example per scene and one per task, all different;
- ``event_frames``: release, first new contact, rebound apex and rest, from the simulated
  trajectory and contacts;
- ``example_sheet``: a clean RGB row, then the same frames with the actor mask outlines and a few
  small hollow ground-truth track markers, then the disparity; ``objects_sheet`` tiles the
  object close-ups; ``encode_under`` saves a sheet as JPEG under a byte budget.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from ..groundtruth import contact_sheet
from ..groundtruth.trajectory import Contact, Trajectory

REST_SPEED_M_S = 0.03  # an actor moving slower than this (and turning slower than REST_SPIN) is at rest
REST_SPIN_RAD_S = 0.5
APEX_MIN_RISE_M = 0.02  # a rebound must rise this much above its contact height to show as an apex
BOUNCE_FALL_M_S = 0.5  # a rebound counts when the actor fell at least this fast into it ...
BOUNCE_RISE_M = 0.002  # ... and rises at least this much in the next frame
MARKERS_PER_ACTOR = 8
TRAIL_FRAMES = 6
LABEL_H = 28  # pixels of caption strip above each sheet row


@dataclass(frozen=True)
class Event:
    frame: int
    label: str


def pick_examples(rows: Sequence, tasks: Sequence[str], scenes: Sequence[str]) -> tuple[dict, dict]:
    """rows: eval ManifestRows. Returns ({task: row}, {scene: row}), every row a different example.

    Scene sheets come first and rotate through the tasks (scene i prefers task i mod n); each task
    sheet then takes the first unused row of its task in a scene no other task sheet shows, if any."""
    used: set[str] = set()
    by_scene: dict = {}
    for i, scene in enumerate(scenes):
        candidates = [r for r in rows if r.scene == scene]
        if not candidates:
            raise ValueError(f"no eval row uses scene '{scene}'; check configs/splits.yaml")
        order = [*tasks[i % len(tasks):], *tasks[:i % len(tasks)]]
        row = next(r for t in order for r in candidates if r.task == t)
        by_scene[scene] = row
        used.add(row.sample_id)
    by_task: dict = {}
    for task in tasks:
        candidates = [r for r in rows if r.task == task and r.sample_id not in used]
        if not candidates:
            raise ValueError(f"no unused eval row of task '{task}' is left for its gallery sheet")
        shown = {r.scene for r in by_task.values()}
        row = next((r for r in candidates if r.scene not in shown), candidates[0])
        by_task[task] = row
        used.add(row.sample_id)
    return by_task, by_scene


def _pairs_at(contacts: Sequence[Contact], frame: int) -> set[frozenset]:
    return {frozenset((c.a, c.b)) for c in contacts if c.frame == frame}


def _between_actors(trajectory: Trajectory, contacts: Sequence[Contact], frame: int | None) -> bool:
    actors = set(trajectory.names)
    return frame is not None and any(c.frame == frame and c.a in actors and c.b in actors for c in contacts)


def first_new_contact(trajectory: Trajectory, contacts: Sequence[Contact], n_frames: int) -> int | None:
    """First frame at which an active actor starts touching something it did not touch at frame 0;
    a contact between two actors is preferred to one with the support or floor."""
    active = {n for n, r in zip(trajectory.names, trajectory.roles) if r == "active"}
    actors = set(trajectory.names)
    initial = _pairs_at(contacts, 0)
    new = [c for c in sorted(contacts, key=lambda c: c.frame)
           if 0 < c.frame < n_frames and (c.a in active or c.b in active) and frozenset((c.a, c.b)) not in initial]
    between_actors = [c for c in new if c.a in actors and c.b in actors]
    chosen = between_actors or new
    return chosen[0].frame if chosen else None


def first_bounce(trajectory: Trajectory, n_frames: int) -> int | None:
    """First frame at which an active actor that was falling faster than BOUNCE_FALL_M_S (in one of
    the two frame steps before) is at the bottom of a rebound (its height is a local minimum and rises at least BOUNCE_RISE_M in the next
    frame). At 24 fps the impact itself often falls between two frames, a few millimetres above the
    support, where the contact test (mesh proximity) does not see it."""
    best = None
    for k, role in enumerate(trajectory.roles):
        if role != "active":
            continue
        z = trajectory.positions_m[k, :n_frames, 2]
        vz = np.diff(z) * trajectory.fps
        for f in range(1, len(z) - 1):
            if vz[max(f - 2, 0):f].min() < -BOUNCE_FALL_M_S and z[f + 1] - z[f] >= BOUNCE_RISE_M:
                best = f if best is None else min(best, f)
                break
    return best


def rest_frame(trajectory: Trajectory, n_frames: int) -> int | None:
    """First frame from which every active actor stays below REST_SPEED_M_S and REST_SPIN_RAD_S to
    the end of the clip; None if they are still moving in the last frame."""
    active = [k for k, r in enumerate(trajectory.roles) if r == "active"] or list(range(len(trajectory.names)))
    speed = np.linalg.norm(trajectory.linear_velocity_m_s[active, :n_frames], axis=-1).max(0)
    spin = np.linalg.norm(trajectory.angular_velocity_rad_s[active, :n_frames], axis=-1).max(0)
    moving = np.flatnonzero((speed >= REST_SPEED_M_S) | (spin >= REST_SPIN_RAD_S))
    if len(moving) == 0:
        return 0
    return None if moving[-1] >= n_frames - 1 else int(moving[-1] + 1)


def apex_frame(trajectory: Trajectory, after: int, before: int) -> int | None:
    """Highest point of the first rebound of an active actor between frames ``after`` and ``before``
    (a local maximum of its height that rises at least APEX_MIN_RISE_M above the height at ``after``)."""
    active = [k for k, r in enumerate(trajectory.roles) if r == "active"]
    best: tuple[float, int] | None = None
    for k in active:
        z = trajectory.positions_m[k, after:before + 1, 2]
        for i in range(1, len(z) - 1):
            if z[i] >= z[i - 1] and z[i] > z[i + 1] and z[i] - z[0] >= APEX_MIN_RISE_M:
                if best is None or i < best[1]:
                    best = (z[i] - z[0], i)
                break
    return None if best is None else after + best[1]


def event_frames(trajectory: Trajectory, contacts: Sequence[Contact], n_frames: int) -> list[Event]:
    """Release (frame 0), first contact (the first new contact, or an earlier bounce the contact test
    missed, unless the contact is between two actors), the first rebound's apex and rest (or the
    last frame, if the actors never settle), in order and without repeats; a clip without a contact
    shows its midpoint instead."""
    rest = rest_frame(trajectory, n_frames)
    end = n_frames - 1 if rest is None else rest
    events = [Event(0, "release")]
    contact = first_new_contact(trajectory, contacts, n_frames)
    bounce = first_bounce(trajectory, n_frames)
    if bounce is not None and (contact is None or bounce < contact) and not _between_actors(trajectory, contacts,
                                                                                              contact):
        contact = bounce
    if contact is None:
        events.append(Event(max(1, end // 2), "in motion"))
    else:
        events.append(Event(contact, "first contact"))
        apex = apex_frame(trajectory, contact, end if end > contact else n_frames - 1)
        if apex is not None:
            events.append(Event(apex, "rebound apex"))
    if end > events[-1].frame:
        events.append(Event(end, "at rest" if rest is not None else "last frame"))
    elif events[-1].frame < n_frames - 1:
        events.append(Event(n_frames - 1, "last frame"))
    out: list[Event] = []
    for e in events:
        if not out or e.frame > out[-1].frame:
            out.append(e)
    return out


# -- drawing ------------------------------------------------------------------------------------------


def actor_colours(n: int) -> np.ndarray:
    """(n,3) uint8 colours, distinct per actor (the contact sheet's)."""
    return (contact_sheet.actor_colours(n) * 255).round().astype(np.uint8)


def marker_subset(actor_index: np.ndarray, per_actor: int = MARKERS_PER_ACTOR) -> np.ndarray:
    """Indices of at most ``per_actor`` tracks per actor, evenly spread through its list."""
    keep = []
    for a in np.unique(actor_index):
        idx = np.flatnonzero(actor_index == a)
        take = np.unique(np.linspace(0, len(idx) - 1, min(per_actor, len(idx))).round().astype(int))
        keep.extend(idx[take])
    return np.array(sorted(keep), dtype=np.int64)


def outline(mask: np.ndarray) -> np.ndarray:
    """Boundary pixels of a boolean mask (4-neighbourhood), thickened to 2 px."""
    m = np.asarray(mask, bool)
    inner = m.copy()
    inner[1:] &= m[:-1]
    inner[:-1] &= m[1:]
    inner[:, 1:] &= m[:, :-1]
    inner[:, :-1] &= m[:, 1:]
    edge = m & ~inner
    thick = edge.copy()
    thick[1:] |= edge[:-1]
    thick[:, 1:] |= edge[:, :-1]
    return thick


def disparity_rgb(depth_m: np.ndarray, near_m: float, far_m: float) -> np.ndarray:
    """(H,W) depth -> (H,W,3) uint8: the contact sheet's disparity colours (near red, no surface black)."""
    return (contact_sheet.depth_colours(depth_m, near_m, far_m) * 255).round().astype(np.uint8)


def font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1
        return ImageFont.load_default()


def _resize(rgb: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.fromarray(rgb).resize(size, Image.Resampling.LANCZOS))


def _resize_mask(mask: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.fromarray(mask.astype(np.uint8) * 255).resize(size, Image.Resampling.BILINEAR)) >= 128


def annotate(rgb: np.ndarray, masks: np.ndarray, tracks_px: np.ndarray, visibility: np.ndarray,
             actor_index: np.ndarray, t: int, size: tuple[int, int]):
    """One frame, scaled to ``size``, with actor mask outlines and hollow markers on the chosen tracks
    (``tracks_px`` (P,T,2) at full resolution); a short trail leads to each visible marker and an
    occluded point is a small cross. Returns a PIL image."""
    from PIL import Image, ImageDraw

    H, W = rgb.shape[:2]
    sx, sy = size[0] / W, size[1] / H
    out = _resize(rgb, size).copy()
    colours = actor_colours(len(masks))
    for m, c in zip(masks, colours):
        out[outline(_resize_mask(m, size))] = c
    img = Image.fromarray(out)
    draw = ImageDraw.Draw(img)
    r = max(3.0, size[0] / 200)
    for p in range(len(tracks_px)):
        c = tuple(int(v) for v in colours[actor_index[p]])
        x, y = tracks_px[p, t, 0] * sx, tracks_px[p, t, 1] * sy
        start = max(0, t - TRAIL_FRAMES)
        seen = visibility[p, start:t + 1]
        if visibility[p, t]:
            trail = [(float(u * sx), float(v * sy)) for (u, v), s in zip(tracks_px[p, start:t + 1], seen) if s]
            if len(trail) > 1:
                draw.line(trail, fill=c, width=1)
            draw.ellipse((x - r, y - r, x + r, y + r), outline=(255, 255, 255), width=3)
            draw.ellipse((x - r, y - r, x + r, y + r), outline=c, width=2)
        elif 0 <= x < size[0] and 0 <= y < size[1]:
            k = r * 0.7
            draw.line((x - k, y - k, x + k, y + k), fill=c, width=2)
            draw.line((x - k, y + k, x + k, y - k), fill=c, width=2)
    return img


def example_sheet(frames: Mapping[int, np.ndarray], events: Sequence[Event],
                  masks: Mapping[int, np.ndarray] | np.ndarray, depth_m: Mapping[int, np.ndarray] | np.ndarray,
                  tracks_px: np.ndarray, visibility: np.ndarray, actor_index: np.ndarray, fps: float, title: str,
                  legend: Sequence[str], cell_width: int = 640):
    """A gallery sheet: rows clean RGB, RGB with outlines and markers, disparity; one column per event.

    ``frames`` maps frame -> (H,W,3) uint8 at full resolution; ``masks`` ((N,H,W) per frame) and
    ``depth_m`` ((H,W) per frame) are indexed by frame number: arrays over all T frames or dicts
    holding the event frames only; ``tracks_px``/``visibility``/``actor_index`` the chosen tracks.
    Returns a PIL image."""
    from PIL import Image, ImageDraw

    H, W = next(iter(frames.values())).shape[:2]
    size = (cell_width, int(round(cell_width * H / W)))
    finite = np.stack([np.asarray(depth_m[e.frame]) for e in events])
    finite = finite[np.isfinite(finite) & (finite > 0)]
    near, far = (np.percentile(finite, [0.5, 99.5]) if finite.size else (1.0, 2.0))
    cols = len(events)
    gap = 6
    header = 2 * LABEL_H + 8
    sheet = Image.new("RGB", (cols * size[0] + (cols - 1) * gap, header + 3 * (size[1] + LABEL_H)), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    draw.text((8, 6), title, fill=(0, 0, 0), font=font(20))
    colours = actor_colours(len(legend))
    x = 8
    for name, c in zip(legend, colours):
        draw.rectangle((x, LABEL_H + 12, x + 14, LABEL_H + 26), fill=tuple(int(v) for v in c))
        draw.text((x + 20, LABEL_H + 10), name, fill=(40, 40, 40), font=font(16))
        x += 30 + int(draw.textlength(name, font=font(16)))
    rows = ("RGB", "mask outlines and ground-truth tracks (o visible, x occluded)", "disparity (near = red)")
    for j, e in enumerate(events):
        x0 = j * (size[0] + gap)
        cells = (Image.fromarray(_resize(frames[e.frame], size)),
                 annotate(frames[e.frame], masks[e.frame], tracks_px, visibility, actor_index, e.frame, size),
                 Image.fromarray(_resize(disparity_rgb(depth_m[e.frame], float(near), float(far)), size)))
        for i, cell in enumerate(cells):
            y0 = header + i * (size[1] + LABEL_H)
            caption = f"{e.label}, frame {e.frame} (t = {e.frame / fps:.2f} s)" if i == 0 else (rows[i] if j == 0 else "")
            draw.text((x0 + 2, y0 + 4), caption, fill=(0, 0, 0), font=font(16))
            sheet.paste(cell, (x0, y0 + LABEL_H))
    return sheet


def objects_sheet(tiles: Sequence[tuple[str, np.ndarray, bool]], cols: int = 6, title: str = ""):
    """Tile object close-ups: (label, (h,w,3) uint8, held out). Held-out objects get an orange frame
    and '(held out)' in their label. Returns a PIL image."""
    from PIL import Image, ImageDraw

    h, w = tiles[0][1].shape[:2]
    rows = -(-len(tiles) // cols)
    pad, top = 6, (40 if title else 0)
    sheet = Image.new("RGB", (cols * (w + pad) + pad, top + rows * (h + LABEL_H + pad) + pad), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    if title:
        draw.text((pad, 10), title, fill=(0, 0, 0), font=font(20))
    for k, (label, img, held_out) in enumerate(tiles):
        r, c = divmod(k, cols)
        x0, y0 = pad + c * (w + pad), top + pad + r * (h + LABEL_H + pad)
        draw.text((x0 + 2, y0 + 4), label + (" (held out)" if held_out else ""),
                  fill=(200, 90, 0) if held_out else (0, 0, 0), font=font(16))
        sheet.paste(Image.fromarray(img), (x0, y0 + LABEL_H))
        if held_out:
            draw.rectangle((x0, y0 + LABEL_H, x0 + w - 1, y0 + LABEL_H + h - 1), outline=(230, 110, 0), width=4)
    return sheet


def encode_under(image, max_bytes: int, qualities: Sequence[int] = (92, 88, 84, 80, 75, 70, 60)) -> bytes:
    """JPEG bytes of ``image`` at the best quality in ``qualities`` that fits ``max_bytes``, scaling the
    image down by 15% steps if even the lowest does not. Raises ValueError if nothing fits."""
    img = image.convert("RGB")
    for _ in range(6):
        for q in qualities:
            buf = io.BytesIO()
            img.save(buf, format="JPEG", quality=q, optimize=True, progressive=True, subsampling=0 if q >= 88 else 2)
            if buf.tell() <= max_bytes:
                return buf.getvalue()
        img = img.resize((int(img.width * 0.85), int(img.height * 0.85)))
    raise ValueError(f"cannot encode a {image.width}x{image.height} sheet under {max_bytes} bytes")


__all__ = ["Event", "pick_examples", "first_new_contact", "first_bounce", "rest_frame", "apex_frame", "event_frames",
           "font", "actor_colours", "marker_subset", "outline", "disparity_rgb", "annotate", "example_sheet",
           "objects_sheet", "encode_under"]
