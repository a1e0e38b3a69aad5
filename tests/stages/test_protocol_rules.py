"""`rigidbench-v1` follows the published evaluator's edge rules and decoder; `paper-rules` and `lossless` ours.

Each published rule is re-implemented here, independently, the way the authors' release computes it
(github swarnim-j/RigidBench, commit f0b8f29: eval/score/track.py, trajectory.py, depth.py, identity.py,
background.py, eval/prepare.py): plain loops, its clamped bilinear sampling, its K-dict unprojection,
its Weiszfeld stop rule, its ``int(round(x))`` patch placement, its ``np.average`` weighting. The
metrics under ``rigidbench-v1``'s edge rules must give the same numbers on the edge cases of
docs/metrics.md, NaN with the reason where the release raises, and ``paper-rules`` must differ there.
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest

from rigidbench.driver import RunOptions
from rigidbench.evaluation.protocol import PROTOCOLS, get_protocol
from rigidbench.metrics import MetricInputs
from rigidbench.metrics.background import bgdrift
from rigidbench.metrics.depth import ate3d, fit_disparity_alignment
from rigidbench.metrics.identity import IMAGENET_MEAN, IMAGENET_STD, iddrift
from rigidbench.metrics.tracks import ate, score_ate

cv2 = pytest.importorskip("cv2")
torch = pytest.importorskip("torch")

V1, OURS = "published", "paper"  # the edge rules of rigidbench-v1 and of paper-rules (checked below)


def same(a: float, b: float, rel: float = 1e-9) -> bool:
    """Equal, both NaN, or both the same infinity."""
    if math.isnan(a) or math.isnan(b):
        return math.isnan(a) and math.isnan(b)
    return a == b if math.isinf(a) or math.isinf(b) else math.isclose(a, b, rel_tol=rel, abs_tol=1e-15)


def test_the_protocols_are_typed_values_naming_their_rules():
    v1, paper, lossless = (get_protocol(n) for n in ("rigidbench-v1", "paper-rules", "lossless"))
    assert get_protocol(None) is v1 and PROTOCOLS["rigidbench-v1"].edge_rules == V1
    assert (v1.edge_rules, v1.decoder, v1.jpeg_quality) == ("published", "opencv", 95)
    assert (paper.edge_rules, paper.decoder, paper.jpeg_quality) == ("paper", "pyav", 95)
    assert (lossless.edge_rules, lossless.decoder, lossless.jpeg_quality) == ("paper", "pyav", None)
    assert {"edge_rules", "decoder", "jpeg_quality"} <= set(v1.facts())
    assert len({p.key() for p in (v1, paper, lossless)}) == 3  # each rule is part of the input key
    with pytest.raises(ValueError, match="edge_rules"):
        type(v1)("x", "", "lenient", "opencv", None)
    with pytest.raises(ValueError, match="unknown edge rules"):
        ate(np.zeros((1, 1, 2)), np.zeros((1, 1, 2)), np.ones((1, 1), bool), np.ones((1, 1), bool), 10,
            rules="lenient")


# ------------------------------------------------------------------------------------------------ ATE


def release_ate(gt, pred, vis, height):
    """eval/score/track.py: the mean over visible (k, t) pairs of the plain distance / H, and per frame."""
    errors = np.linalg.norm(gt - pred, axis=-1)
    value = float(errors[vis].mean() / height) if vis.any() else float("nan")
    per_frame = np.full(gt.shape[1], np.nan)
    for t in range(gt.shape[1]):
        if vis[:, t].any():
            per_frame[t] = errors[vis[:, t], t].mean() / height
    return value, per_frame


@pytest.mark.parametrize("bad", [[np.nan, 1.0], [np.inf, 0.0], [-np.inf, np.nan]])
def test_ate_non_finite_track_flagged_visible(bad):
    ref = np.zeros((3, 2, 2))
    gen = np.array([[[3.0, 4.0], [3.0, 4.0]], [[6.0, 8.0], [0.0, 0.0]], [[0.0, 0.0], [1.0, 0.0]]])
    gen[1, 1] = bad
    vis = np.ones((3, 2), bool)
    vis[2, 0] = False
    want, want_pf = release_ate(ref, gen, vis, 100)
    with np.errstate(invalid="ignore"):
        got = ate(ref, gen, vis, vis.copy(), 100, rules=V1)
    assert not math.isfinite(want) and same(got.value, want)
    assert all(same(a, b) for a, b in zip(got.per_frame, want_pf))
    assert got.per_frame[0] == pytest.approx(7.5 / 100)  # frame 0 has no bad point
    ours = ate(ref, gen, vis, vis.copy(), 100, rules=OURS)
    assert ours.value == pytest.approx((5 + 5 + 10 + 1) / 4 / 100)  # the bad point-frame left out


def test_the_registry_adapter_reads_the_rules_from_the_inputs():
    gen = np.array([[[0.0, 0.0], [np.nan, 0.0]]])
    x = MetricInputs(ref_rgb=np.zeros((2, 10, 10, 3), np.uint8), gen_rgb=np.zeros((2, 10, 10, 3), np.uint8),
                     ref_masks=np.zeros((2, 1, 10, 10), bool), gen_masks=np.zeros((2, 1, 10, 10), bool),
                     ref_tracks=np.zeros((1, 2, 2)), gen_tracks=gen, ref_visibility=np.ones((1, 2), bool),
                     gen_visibility=np.ones((1, 2), bool), track_actor=np.zeros(1, int),
                     ref_depth_m=np.ones((2, 10, 10)), gen_disparity=np.ones((2, 10, 10)), K=np.eye(3),
                     camera_to_world=np.eye(4), actor_positions_m=np.zeros((1, 2, 3)),
                     ref_points_m=np.zeros((1, 2, 3)), bg_tracks=np.zeros((0, 2, 2)), bg_confidence=np.zeros((0, 2)),
                     edge_rules=V1)
    assert math.isnan(score_ate(x).value)
    x.edge_rules = OURS
    assert score_ate(x).value == 0.0
    with pytest.raises(ValueError, match="unknown edge rules"):
        MetricInputs(**{**x.__dict__, "edge_rules": "other"})


# --------------------------------------------------------------------------------------------- ATE-3D
# A 10 x 8 image, focal 10 px, principal point (4.5, 3.5), camera at the origin looking down -Z
# (Blender). Reference depth 2 + 0.1 j m in column j; predicted disparity exactly 1 / depth.

SH, SW, FOCAL = 8, 10, 10.0
SK = np.array([[FOCAL, 0.0, 4.5], [0.0, FOCAL, 3.5], [0.0, 0.0, 1.0]])
K_DICT = {"fx": FOCAL, "fy": FOCAL, "cx": 4.5, "cy": 3.5}


def world(u, v, z):
    return np.array([z * (u - 4.5) / FOCAL, -z * (v - 3.5) / FOCAL, -z])


A0, A1 = world(3, 4, 2.3), world(6, 4, 2.6)
OFFSET = np.array([0.1, 0.0, 0.0])


def release_bilinear(img, uv):
    h, w = img.shape
    u = np.clip(uv[..., 0], 0, w - 1.0001)
    v = np.clip(uv[..., 1], 0, h - 1.0001)
    u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
    du, dv = u - u0, v - v0
    return (img[v0, u0] * (1 - du) * (1 - dv) + img[v0, np.minimum(u0 + 1, w - 1)] * du * (1 - dv)
            + img[np.minimum(v0 + 1, h - 1), u0] * (1 - du) * dv
            + img[np.minimum(v0 + 1, h - 1), np.minimum(u0 + 1, w - 1)] * du * dv)


def release_median(x, eps=1e-5, max_iter=100):
    if len(x) == 1:
        return x[0]
    y = x.mean(axis=0)
    for _ in range(max_iter):
        w = 1.0 / np.maximum(np.linalg.norm(x - y, axis=1, keepdims=True), eps)
        y_new = (x * w).sum(axis=0) / w.sum()
        if np.linalg.norm(y_new - y) < eps:
            break
        y = y_new
    return y


def release_aligned_depth(disp, depth):
    """eval/score/depth.py affine_align_disparity: lstsq over valid pixels, positive aligned -> 1 / it."""
    valid = np.isfinite(depth) & np.isfinite(disp) & (depth > 0) & (depth < 100.0)
    a = np.column_stack([disp[valid], np.ones(valid.sum())])
    (s, c), *_ = np.linalg.lstsq(a, 1.0 / np.clip(depth[valid], 1e-3, None), rcond=None)
    aligned = s * disp + c
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(aligned > 0, 1.0 / aligned, np.nan), (s, c)


def release_ate3d(tracks, vis, disp, depth, positions):
    """eval/score/trajectory.py: reconstruct_centroids (one actor) then compute_ate3d, R = I, camera at 0."""
    pred_depth, _ = release_aligned_depth(disp, depth)
    recon = np.full((tracks.shape[1], 3), np.nan)
    for t in range(tracks.shape[1]):
        if vis[:, t].sum() < 1:
            continue
        uv = tracks[vis[:, t], t]
        z = release_bilinear(pred_depth[t], uv)  # a NaN coordinate raises IndexError here
        ok = np.isfinite(z) & (z > 0)
        if ok.sum() < 1:
            continue
        with np.errstate(invalid="ignore", over="ignore"):
            x = (uv[ok, 0] - K_DICT["cx"]) * z[ok] / K_DICT["fx"]
            y = (uv[ok, 1] - K_DICT["cy"]) * z[ok] / K_DICT["fy"]
            pts = np.stack([x, y, z[ok]], axis=-1) * np.array([1, -1, -1]) @ np.eye(3).T + np.zeros(3)
            recon[t] = release_median(pts)
    disp_m = np.linalg.norm(positions[-1] - positions[0])
    errors = [np.linalg.norm(recon[t] - positions[t]) for t in range(len(positions)) if np.isfinite(recon[t]).all()]
    if not errors:
        return float("nan")
    scale = float(disp_m) if disp_m > 0.01 else 1.0
    return float(np.sqrt(np.mean(np.square(errors)))) / scale


def scene(p1_frame1, positions=None, disparity=None, depth=None):
    tracks = np.array([[[3.0, 4.0], [6.0, 4.0]], [[5.0, 4.0], p1_frame1]])
    vis = np.array([[True, True], [False, True]])
    if depth is None:
        depth = np.broadcast_to(2.0 + 0.1 * np.arange(SW), (2, SH, SW)).copy()
    if disparity is None:
        disparity = 1.0 / depth
    if positions is None:
        positions = np.stack([A0 + OFFSET, A1 + OFFSET])
    return tracks, vis, disparity, depth, positions


def our_ate3d(tracks, vis, disparity, depth, positions, rules):
    return ate3d(tracks, vis, vis.copy(), np.zeros(2, int), disparity, depth, SK, np.eye(3), np.zeros(3),
                 positions[None], rules=rules)


@pytest.mark.parametrize("outside", [[12.0, 4.0], [9.6, 4.0], [5.0, -3.0], [-40.0, 30.0]])
def test_ate3d_generated_point_outside_the_image_takes_the_border_depth(outside):
    case = scene(outside)
    want = release_ate3d(*case)
    got = our_ate3d(*case, rules=V1)
    assert got.value == pytest.approx(want, rel=1e-9)
    ours = our_ate3d(*case, rules=OURS)
    assert ours.value == pytest.approx(0.1 / np.linalg.norm(A1 - A0), rel=1e-9)  # the point left out
    assert abs(got.value - ours.value) > 1e-3


@pytest.mark.parametrize("move_m", [0.0, 0.005, 0.0099])
def test_ate3d_without_a_moving_actor_is_the_raw_rmse(move_m):
    case = scene([6.0, 4.0], positions=np.stack([A0, A0 + [move_m, 0.0, 0.0]]))
    want = release_ate3d(*case)
    got = our_ate3d(*case, rules=V1)
    assert math.isfinite(want) and got.value == pytest.approx(want, rel=1e-9)
    assert np.isfinite(got.per_frame).all()
    assert math.isnan(our_ate3d(*case, rules=OURS).value)


@pytest.mark.parametrize("bad", [[np.nan, 4.0], [3.0, np.nan]])
def test_ate3d_nan_track_flagged_visible_is_nan_with_the_reason(bad):
    case = scene(bad)
    with pytest.raises(IndexError), np.errstate(invalid="ignore"):
        release_ate3d(*case)
    got = our_ate3d(*case, rules=V1)
    assert math.isnan(got.value) and np.isnan(got.per_frame).all()
    assert "IndexError" in got.note and "point 1, frame 1" in got.note
    ours = our_ate3d(*case, rules=OURS)
    assert ours.value == pytest.approx(0.1 / np.linalg.norm(A1 - A0), rel=1e-9) and ours.note == ""


@pytest.mark.parametrize("bad", [[np.inf, 4.0], [3.0, -np.inf]])
def test_ate3d_infinite_track_loses_its_actor_frame(bad):
    case = scene(bad)
    want = release_ate3d(*case)
    got = our_ate3d(*case, rules=V1)
    # frame 1's reconstruction is not finite, so only frame 0 (0.1 m off) is in V3
    assert got.value == pytest.approx(want, rel=1e-9) and want == pytest.approx(0.1 / np.linalg.norm(A1 - A0))
    assert math.isnan(got.per_frame[1])


def test_ate3d_neighbour_without_depth_drops_the_point_even_at_zero_weight():
    # Pixel (4, 4) has no valid reference depth (sky) and a negative predicted disparity, so it has no
    # aligned depth; the point at (3, 4) reads it with weight 0, the one at (5, 4) too.
    tracks, vis, disparity, depth, positions = scene([5.0, 4.0])
    depth[:, 4, 4] = 150.0
    disparity[:, 4, 4] = -1.0
    case = (tracks, vis, disparity, depth, positions)
    want = release_ate3d(*case)
    got = our_ate3d(*case, rules=V1)
    assert got.value == pytest.approx(want, rel=1e-9)
    # frame 0 has no usable point (its only one, (3, 4), neighbours (4, 4)); ours keeps it
    assert math.isnan(got.per_frame[0]) and np.isfinite(our_ate3d(*case, rules=OURS).per_frame).all()


def test_constant_disparity_gets_the_minimum_norm_fit():
    depth = np.broadcast_to(2.0 + 0.1 * np.arange(SW), (2, SH, SW)).copy()
    disparity = np.full_like(depth, 0.4)
    _, (s, c) = release_aligned_depth(disparity, depth)
    got = fit_disparity_alignment(disparity, depth, rules=V1)
    assert (got.scale, got.shift) == (pytest.approx(s, rel=1e-9), pytest.approx(c, rel=1e-9))
    assert fit_disparity_alignment(disparity, depth, rules=OURS).scale == 0.0


# --------------------------------------------------------------------------------------------- IdDrift

H, W = 160, 320


def release_iddrift(gt_frames, pred_frames, gt_tracks, pred_tracks, vis, offsets):
    """eval/score/identity.py with a mean-colour 'network' on ImageNet-normalised 224 x 224 patches."""
    def patch(frame, center):
        x, y = int(round(center[0])), int(round(center[1]))  # raises on NaN / inf
        x0, x1, y0, y1 = max(0, x - 32), min(W, x + 32), max(0, y - 32), min(H, y + 32)
        if x1 - x0 < 32 or y1 - y0 < 32:
            return None
        return cv2.resize(frame[y0:y1, x0:x1], (224, 224))

    def feature(p):
        f = (p.reshape(-1, 3).mean(axis=0) / 255.0 - IMAGENET_MEAN) / IMAGENET_STD
        return f / np.linalg.norm(f)

    sims, actors = [], []
    for ai in range(len(offsets) - 1):
        for pi in range(offsets[ai], offsets[ai + 1]):
            for t in range(1, len(gt_frames)):
                if not vis[pi, t]:
                    continue
                g, p = patch(gt_frames[t], gt_tracks[pi, t]), patch(pred_frames[t], pred_tracks[pi, t])
                if g is not None and p is not None:
                    sims.append(feature(g) @ feature(p))
                    actors.append(ai)
    if not sims:
        return float("nan")
    sims, actors = np.array(sims), np.array(actors)
    return 1.0 - float(np.mean([sims[actors == a].mean() for a in np.unique(actors)]))


def identity_case(bad, where):
    ref = np.full((3, H, W, 3), 128, np.uint8)
    gen = ref.copy()
    gen[:, :, : W // 2] = (200, 40, 40)
    gen[:, :, W // 2:] = (40, 40, 200)
    tracks = np.array([[[80.0, 80.0]] * 3, [[240.0, 80.0]] * 3])
    gen_tracks = tracks.copy()
    gen_tracks[where] = bad
    return ref, gen, tracks, gen_tracks, np.ones((2, 3), bool)


def our_iddrift(ref, gen, tracks, gen_tracks, vis, rules):
    return iddrift(ref, gen, tracks, gen_tracks, vis, vis.copy(), np.array([0, 1]), lambda x: x.mean(dim=(2, 3)),
                   rules=rules)


@pytest.mark.parametrize("bad,error", [([np.nan, 80.0], ValueError), ([80.0, np.inf], OverflowError)])
def test_iddrift_non_finite_track_flagged_visible_is_nan_with_the_reason(bad, error):
    case = identity_case(bad, (0, 1))
    with pytest.raises(error):
        release_iddrift(*case, [0, 1, 2])
    got = our_iddrift(*case, rules=V1)
    assert math.isnan(got.value) and "extract_patch" in got.note and "point 0" in got.note
    assert math.isfinite(our_iddrift(*case, rules=OURS).value)
    # a NaN reference position stops it the same way
    ref, gen, tracks, gen_tracks, vis = identity_case([80.0, 80.0], (0, 1))
    tracks[1, 2] = bad
    assert math.isnan(our_iddrift(ref, gen, tracks, gen_tracks, vis, rules=V1).value)


@pytest.mark.parametrize("where,visible", [((0, 0), True), ((1, 2), False)])
def test_iddrift_non_finite_track_the_release_never_reads(where, visible):
    # at frame 0 (never scored), or not visible: the release goes on, and so does rigidbench-v1
    ref, gen, tracks, gen_tracks, vis = identity_case([np.nan, 80.0], where)
    vis[where] = visible
    want = release_iddrift(ref, gen, tracks, gen_tracks, vis, [0, 1, 2])
    got = our_iddrift(ref, gen, tracks, gen_tracks, vis, rules=V1)
    assert math.isfinite(want) and got.value == pytest.approx(want, abs=1e-5) and got.note == ""


# --------------------------------------------------------------------------------------------- BGDrift


def release_bgdrift(tracks, confidence, height):
    """eval/score/background.py compute_bgdrift."""
    residuals, weights = [], []
    for t in range(1, tracks.shape[1]):
        conf_t = confidence[:, t] * confidence[:, 0]
        valid = conf_t > 0
        if valid.sum() < 4:
            continue
        src, dst = tracks[valid, 0].astype(np.float32), tracks[valid, t].astype(np.float32)
        m, _ = cv2.estimateAffinePartial2D(src, dst, method=cv2.RANSAC)
        disp = np.linalg.norm(dst - src, axis=1) if m is None else np.linalg.norm(dst - ((m[:, :2] @ src.T).T
                                                                                          + m[:, 2]), axis=1)
        residuals.append(float(np.average(disp, weights=conf_t[valid])))
        weights.append(float(conf_t[valid].sum()))
    return float(np.average(residuals, weights=weights) / height) if residuals else float("nan")


def corner_case():
    x0 = np.array([[100.0, 100.0], [300.0, 120.0], [180.0, 400.0], [500.0, 350.0], [250.0, 250.0], [420.0, 60.0]])
    x1 = x0 + [10.0, 0.0]
    x1[4] += [0.0, 30.0]
    x2 = x0 + [4.0, -3.0]
    x2[5] += [7.0, 0.0]
    conf = np.ones((6, 3))
    conf[4, 0] = 0.5
    return np.stack([x0, x1, x2], axis=1), conf


@pytest.mark.parametrize("change", ["none", "nan position", "inf position", "nan confidence", "inf confidence",
                                    "negative confidences"])
def test_bgdrift_corner_rules(change):
    tracks, conf = corner_case()
    if change == "nan position":
        tracks[1, 2, 0] = np.nan
    elif change == "inf position":
        tracks[2, 0, 1] = np.inf
    elif change == "nan confidence":
        conf[3, 2] = np.nan
    elif change == "inf confidence":
        conf[0, 1] = np.inf
    elif change == "negative confidences":
        conf[5, 0] = conf[5, 2] = -1.0
    with np.errstate(invalid="ignore", over="ignore"):
        want = release_bgdrift(tracks, conf, 100)
        got = bgdrift(tracks, conf, 100, rules=V1).value
    assert same(got, want, rel=1e-6), (got, want)
    ours = bgdrift(tracks, conf, 100, rules=OURS).value
    assert math.isfinite(ours)
    if change in ("nan position", "inf position", "inf confidence"):
        assert not math.isfinite(got)


# --------------------------------------------------------------------------------------------- decoding


def write_clip(path, frames, bt709: bool):
    """H.264 yuv420p written with PyAV; ``bt709``: converted with and tagged as BT.709 (what hosted models
    return), else untagged (decoders assume BT.601)."""
    av = pytest.importorskip("av")
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=Fraction(24))
        stream.width, stream.height, stream.pix_fmt = frames.shape[2], frames.shape[1], "yuv420p"
        stream.options = {"crf": "12"}
        if bt709:
            cc = stream.codec_context
            cc.colorspace = cc.color_primaries = cc.color_trc = 1  # BT.709
            cc.color_range = 1  # limited ("tv")
        for frame in frames:
            vf = av.VideoFrame.from_ndarray(frame, format="rgb24")
            if bt709:
                vf = vf.reformat(format="yuv420p", dst_colorspace=1)
                vf.colorspace, vf.color_range = 1, 1
            container.mux(stream.encode(vf))
        container.mux(stream.encode(None))


def opencv_frames(path):
    """eval/prepare.py extract_frames: cv2.VideoCapture, BGR -> RGB, every frame."""
    capture = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
    capture.release()
    return np.stack(frames)


def test_v1_decodes_tagged_and_untagged_clips_as_opencv(tmp_path):
    rows, cols = np.mgrid[0:48, 0:64]
    source = np.stack([np.stack([(cols * 4 + 9 * t) % 256, rows * 5, 220 - (rows + cols) % 150], -1)
                       for t in range(5)]).astype(np.uint8)
    v1, lossless = get_protocol("rigidbench-v1"), get_protocol("lossless")
    for bt709 in (True, False):
        path = tmp_path / f"clip-{bt709}.mp4"
        write_clip(path, source, bt709)
        reference = opencv_frames(path)
        got = v1.decode(path)
        np.testing.assert_array_equal(got.frames, reference)
        np.testing.assert_allclose(got.times_s, np.arange(5) / 24)
        honoured = lossless.decode(path).frames
        if bt709:
            gap = np.abs(honoured.astype(int) - reference).mean()
            assert gap > 2  # the matrices differ by several grey levels on saturated colours
            # PyAV honours the tag, so it is the closer of the two to the source
            assert np.abs(honoured.astype(int) - source).mean() < np.abs(reference.astype(int) - source).mean()
        else:
            np.testing.assert_array_equal(honoured, reference)
    assert v1.decode(tmp_path / "clip-True.mp4", until_s=2 / 24).n_frames == 3


# --------------------------------------------------------------------------------- the evaluate stage


@pytest.fixture(scope="module")
def reference_set(tmp_path_factory):
    """The synthetic published set (three examples, no Blender) and the `reference` predictor's clips."""

    from fixtures import published_set as ps

    from rigidbench.config import registry
    from rigidbench.stages.import_set import import_published
    from rigidbench.stages.predict import predict
    from rigidbench.predictors import PredictContext

    root = tmp_path_factory.mktemp("protocol")
    published = ps.write_set(root / "published" / "rigidbench-eval-v1.1")
    import_published(published.parent, root / "data", registry=registry(), run=RunOptions(progress=False))
    predict("reference", root / "data" / "eval", root / "reference", PredictContext(), run=RunOptions(progress=False))
    return root / "data", root / "reference"


@pytest.mark.parametrize("name", ["rigidbench-v1", "paper-rules"])
def test_evaluate_threads_the_protocol_and_records_why_a_value_is_undefined(reference_set, tmp_path, monkeypatch,
                                                                              name):
    from rigidbench.stages.evaluate import evaluate
    from rigidbench.evaluation import protocol
    from rigidbench.stages import evaluate as runner
    from rigidbench.metrics.common import MetricResult
    from rigidbench.perception.features import FeatureNets

    decoders, rules = [], []
    real_read, real_score = protocol.read_video, runner.score_inputs

    def read_video(path, **kw):
        decoders.append(kw["decoder"])
        return real_read(path, **kw)

    def score_inputs(inputs, metrics=None, **options):
        rules.append(inputs.edge_rules)
        scores = real_score(inputs, metrics, **options)
        if inputs.ref_tracks.shape[0] and len(rules) == 1:  # the first example: a value its rules leave undefined
            scores["ate"] = MetricResult(float("nan"), None, "why it is undefined")
        return scores

    monkeypatch.setattr(protocol, "read_video", read_video)
    monkeypatch.setattr(runner, "score_inputs", score_inputs)
    data, preds = reference_set
    summary = evaluate(preds, data, tmp_path / "run", nets=FeatureNets(), protocol=name, run=RunOptions(progress=False))
    chosen = get_protocol(name)
    n = len(summary.ran)
    assert n >= 1 and decoders == [chosen.decoder] * n and rules == [chosen.edge_rules] * n
    facts = summary.facts.results["protocol"]
    assert (facts["name"], facts["edge_rules"], facts["decoder"]) == (name, chosen.edge_rules, chosen.decoder)
    first = summary.ran[0]
    record = __import__("json").loads((tmp_path / "run" / "examples" / f"{first}.json").read_text())
    assert record["protocol"] == name and record["notes"] == {"ate": "why it is undefined"}
    assert record["metrics"]["ate"] is None
    assert summary.facts.results["notes"] == {first: {"ate": "why it is undefined"}}


def test_the_report_names_each_runs_protocol(tmp_path):
    import json
    from types import SimpleNamespace

    from rigidbench.metrics import METRICS
    from rigidbench.report import report_notes
    from rigidbench.report.html import header, runs_table
    from rigidbench.report.load import load_runs

    dirs = []
    for model, name in (("a", "rigidbench-v1"), ("b", "paper-rules")):
        run = tmp_path / model
        (run / "examples").mkdir(parents=True)
        record = {"id": "00000", "task": "bounce", "partition": "in_distribution",
                  "metrics": {m: 0.5 for m in METRICS}, "skipped": {}}
        (run / "examples" / "00000.json").write_text(json.dumps(record))
        (run / "results.json").write_text(json.dumps({"model": model, "official": False, "failed": {},
                                                      "protocol": {"name": name}}))
        dirs.append(run)
    table = load_runs(dirs)
    assert [r.protocol for r in table.runs] == ["rigidbench-v1", "paper-rules"]
    assert any("different evaluation protocols" in n and "b: paper-rules" in n for n in table.notes)
    data = SimpleNamespace(table=table, resamples=10, seed=0, baseline=0, samples=None)
    assert "protocol paper-rules / rigidbench-v1" in "".join(header(data, report_notes(data)))
    assert "<td>paper-rules</td>" in runs_table(data, {})
    assert not any("protocols" in n for n in load_runs(dirs[:1]).notes)


def test_an_undecodable_prediction_is_one_clear_error_under_either_decoder(tmp_path):
    from rigidbench.errors import VideoError

    bad = tmp_path / "00000.mp4"
    bad.write_bytes(b"not a video" * 100)
    for name in ("rigidbench-v1", "lossless"):
        with pytest.raises(VideoError, match="00000.mp4"):
            get_protocol(name).decode(bad)
