"""Probe core on synthetic data: the probes and their shuffled control, INLP and its controls, the
variance-matched alpha, the slot mapping, mask pooling and the targets (paper appendix E)."""

from types import SimpleNamespace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rigidbench.probe.fit import ProbeSettings, fit_cell, r2_score, roc_auc, train_probe  # noqa: E402
from rigidbench.probe.inlp import (inlp, project_out, random_orthonormal, ridge_fit, split_rows,  # noqa: E402
                                   total_variance, variance_matched_alpha, variance_matched_pcs)
from rigidbench.probe.pooling import (max_pool_to_grid, n_slots, pool_actors, pooling_matrix,  # noqa: E402
                                      slot_frames, slot_token_masks)
from rigidbench.probe.targets import slot_targets  # noqa: E402
from rigidbench.stages.probe_bases import fit_bases  # noqa: E402

# the paper's optimiser, with smaller batches so that the few thousand synthetic rows get enough steps
FAST = ProbeSettings(epochs=20, batch_size=128, lr=1e-3, seed=0)


def planted(n=4000, d=32, k=3, noise=0.05, seed=1):
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((n, d)) * rng.uniform(0.1, 10.0, d)  # very different scales per feature
    w = rng.standard_normal((d, k)) / np.sqrt(d)
    y = (x / x.std(axis=0)) @ w
    return x.astype(np.float32), (y + noise * y.std() * rng.standard_normal(y.shape)).astype(np.float32)


def splits(x, y):
    n = len(x)
    a, b = int(0.8 * n), int(0.9 * n)
    return (x[:a], y[:a]), (x[a:b], y[a:b]), (x[b:], y[b:])


def test_linear_probe_recovers_a_planted_signal_and_the_shuffled_control_does_not():
    x, y = planted()
    tr, va, te = splits(x, y)
    trained = fit_cell(tr, va, te, "linear", False, "trained", FAST)
    control = fit_cell(tr, va, te, "linear", False, "shuffled", FAST)
    assert trained["metric"] == "r2" and trained["test"] > 0.9
    assert control["test"] < 0.05
    mlp = fit_cell(tr, va, te, "mlp", False, "trained", FAST)
    assert mlp["test"] > 0.8


def test_probe_recovers_a_planted_binary_target_by_roc_auc():
    x, y = planted(k=1)
    label = (y[:, :1] > 0).astype(np.float32)
    tr, va, te = splits(x, label)
    trained = fit_cell(tr, va, te, "linear", True, "trained", FAST)
    control = fit_cell(tr, va, te, "linear", True, "shuffled", FAST)
    assert trained["metric"] == "roc_auc" and trained["test"] > 0.95
    assert abs(control["test"] - 0.5) < 0.1


def test_scores_edge_cases():
    assert np.isnan(roc_auc(np.ones(5), np.arange(5)))
    assert r2_score(np.arange(5.0), np.arange(5.0)) == pytest.approx(1.0)
    assert r2_score(np.arange(5.0), np.full(5, 2.0)) == pytest.approx(0.0)
    assert np.isnan(r2_score(np.ones((5, 2)), np.zeros((5, 2))))


def release_r2(y, pred):
    """The release's R^2, written out: 1 - sum of squared residuals / sum of squared deviations from
    each column's mean, both summed over rows and columns."""
    y, pred = np.asarray(y, np.float64), np.asarray(pred, np.float64)
    ss_res = sum(float((y[i, j] - pred[i, j]) ** 2) for i in range(len(y)) for j in range(y.shape[1]))
    means = [float(np.mean(y[:, j])) for j in range(y.shape[1])]
    ss_tot = sum(float((y[i, j] - means[j]) ** 2) for i in range(len(y)) for j in range(y.shape[1]))
    return 1.0 - ss_res / ss_tot


def test_r2_is_pooled_over_the_target_dimensions_as_in_the_release():
    rng = np.random.default_rng(4)
    y = rng.standard_normal((200, 3)) * np.array([10.0, 1.0, 0.1])  # dimensions of very different spread
    pred = y + rng.standard_normal(y.shape) * 0.5                   # the same error on every dimension
    pooled = release_r2(y, pred)
    assert r2_score(y, pred) == pytest.approx(pooled, abs=1e-12)
    per_dim = np.mean([1 - np.sum((y[:, j] - pred[:, j]) ** 2) / np.sum((y[:, j] - y[:, j].mean()) ** 2)
                       for j in range(3)])
    assert r2_score(y, pred, "mean") == pytest.approx(per_dim, abs=1e-12)
    assert pooled > 0.99 and per_dim < 0.0  # the two definitions really differ here


def test_linear_probe_is_fit_on_raw_values_and_scored_by_pooled_r2_as_in_the_release():
    rng = np.random.default_rng(5)
    n, d = 1200, 16
    x = (rng.standard_normal((n, d)) + 2.0).astype(np.float32)            # uncentred activations
    y = (x @ rng.standard_normal((d, 3)) * [3.0, 1.0, 0.2] + [5.0, -1.0, 0.5]
         + 0.3 * rng.standard_normal((n, 3))).astype(np.float32)
    tr, va, te = splits(x, y)
    settings = ProbeSettings(epochs=30, batch_size=64, lr=1e-2, seed=0)
    got = fit_cell(tr, va, te, "linear", False, "trained", settings)
    # independent: a linear layer trained on the raw rows (same initial weights and batch order), pooled R^2
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        net = torch.nn.Linear(d, 3)
    gen = torch.Generator().manual_seed(0)
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    xt, yt = torch.as_tensor(tr[0]), torch.as_tensor(tr[1])
    for _ in range(30):
        order = torch.randperm(len(xt), generator=gen)
        for s in range(0, len(xt), 64):
            idx = order[s:s + 64]
            opt.zero_grad()
            torch.nn.functional.mse_loss(net(xt[idx]), yt[idx]).backward()
            opt.step()
    with torch.no_grad():
        pred = net(torch.as_tensor(te[0])).double().numpy()
    assert got["metric"] == "r2"
    assert got["test"] == pytest.approx(release_r2(te[1], pred), abs=1e-5)
    assert got["test"] > 0.5  # it learns (20-30 epochs of Adam on raw values do not fully converge)
    # standardising stays available as an option and gives another fit
    std = fit_cell(tr, va, te, "linear", False, "trained", ProbeSettings(epochs=30, batch_size=64, lr=1e-2,
                                                                         standardize=True))
    assert std["test"] > 0.5 and std["test"] != pytest.approx(got["test"], abs=1e-6)
    probe, _ = train_probe(tr[0], tr[1], "linear", False, ProbeSettings(epochs=1, standardize=False))
    assert np.all(probe.x_stats[0] == 0) and np.all(probe.x_stats[1] == 1)


def release_inlp(x, y, reg=0.05, eps=0.05, max_iters=30, seed=0, tol=1e-6):
    """The release's INLP steps written out directly, but in float64 numpy (the release ran them in float32:
    ``release_inlp_float32``): 80/20 split by torch.randperm,
    ridge without intercept on the projected rows with penalty reg * N, pooled training R^2, projection
    of the rows onto the nullspace of each added regressor, rank of the stacked regressors."""
    perm = torch.randperm(len(x), generator=torch.Generator().manual_seed(seed)).numpy()
    xp = np.asarray(x, np.float64)[perm[: int(0.8 * len(x))]]
    yt = np.asarray(y, np.float64)[perm[: int(0.8 * len(x))]]
    n, d = xp.shape
    history, collected = [], []
    for _ in range(max_iters):
        w = np.linalg.solve(xp.T @ xp + reg * n * np.eye(d), xp.T @ yt).T       # (k, d)
        r2 = release_r2(yt, xp @ w.T)
        history.append(r2)
        if r2 < eps:
            break
        collected.append(w)
        _, s, vh = np.linalg.svd(w, full_matrices=True)
        null = vh[int((s > tol * s.max()).sum()):].T
        xp = (xp @ null) @ null.T
    if not collected:
        return np.zeros((d, 0)), history
    _, s, vh = np.linalg.svd(np.concatenate(collected), full_matrices=True)
    return vh[: int((s > tol * s.max()).sum())].T, history


def redundant_position(n=2500, d=48, seed=0):
    """A 3-d target spread redundantly over many noisy, uncentred features: INLP needs several rounds."""
    rng = np.random.default_rng(seed)
    z = rng.standard_normal((n, 3))
    noise = rng.standard_normal((n, d)) @ (rng.standard_normal((d, d)) * rng.uniform(0.05, 1.0, d)) * 0.5
    x = z @ rng.standard_normal((3, d)) + noise + 2.0  # correlated noise: each regressor leaves some signal
    y = z + np.array([1.0, 0.5, -2.0])
    return x.astype(np.float32), y


def test_inlp_rank_and_r2_path_equal_the_release_steps_in_float64():
    x, y = redundant_position()
    basis_ref, history_ref = release_inlp(x, y)
    res = inlp(x, y, device="cpu")
    assert res.rank == basis_ref.shape[1] and res.rank > 6     # several rounds, not one
    assert res.train_r2 == pytest.approx(history_ref, abs=1e-8)
    assert np.allclose(res.basis @ res.basis.T, basis_ref @ basis_ref.T, atol=1e-8)
    assert res.train_rows == int(0.8 * len(x)) and res.stopped == "r2"
    # float32 Gram and solves land on the same subspace here
    r32 = inlp(x, y, device="cpu", dtype=torch.float32)
    assert r32.rank == res.rank and np.allclose(r32.basis @ r32.basis.T, res.basis @ res.basis.T, atol=1e-3)


def release_inlp_float32(x, y, reg=0.05, eps=0.05, max_iters=30, seed=0, tol=1e-6):
    """The release's INLP as it ran (``probe/inlp.py``: ``fit_cell`` and ``fit_inlp``), written out in torch:
    float32 rows in the permutation's order, each ridge solved in float64 from the float32 projected rows and
    cast back to float32, R^2 in float32, the rows re-projected in float32 onto each regressor's null space
    (full SVD, 1e-6 rule), then the null space of the stacked regressors, its float32 projector, and the
    null space of that projector as the basis. Returns (basis (D, r), R^2 history, regressors added)."""
    def null(m):
        _, s, vh = torch.linalg.svd(m, full_matrices=True)
        keep = int((s > tol * float(s.max())).sum()) if float(s.max()) > 0 else 0
        return vh[keep:].T

    perm = torch.randperm(len(x), generator=torch.Generator().manual_seed(seed))
    tr = perm[: int(0.8 * len(x))]
    x_tr = torch.as_tensor(x, dtype=torch.float32)[tr]
    y_tr = torch.as_tensor(np.asarray(y), dtype=torch.float32)[tr]
    x_proj, collected, history = x_tr.clone(), [], []
    for _ in range(max_iters):
        xd, yd = x_proj.double(), y_tr.double()
        n, d = xd.shape
        w = torch.linalg.solve(xd.T @ xd + reg * n * torch.eye(d, dtype=torch.float64), xd.T @ yd).T.to(torch.float32)
        pred = x_proj @ w.T
        r2 = 1.0 - ((y_tr - pred) ** 2).sum().item() / ((y_tr - y_tr.mean(0)) ** 2).sum().item()
        history.append(r2)
        if r2 < eps:
            break
        collected.append(w)
        b = null(w)
        x_proj = (x_proj @ b) @ b.T
    if not collected:
        return np.zeros((x.shape[1], 0)), history, 0
    joint = null(torch.cat(collected, dim=0))
    return null(joint @ joint.T).double().numpy(), history, len(collected)


def test_the_release_inlp_procedure_is_the_release_float32_computation_and_parts_from_the_stable_one():
    x, y = redundant_position(n=4000, d=128)
    basis, history, rounds = release_inlp_float32(x, y)
    got = inlp(x, y, device="cpu", procedure="release")
    assert got.procedure == "release" and got.rounds == rounds and len(history) > 10
    assert got.train_r2 == pytest.approx(history, abs=1e-6)
    assert got.rank == basis.shape[1]
    assert np.allclose(got.basis @ got.basis.T, basis @ basis.T, atol=1e-5)
    # the stable procedure equals the release's steps computed in float64 on these rows (which drift by
    # 1e-8 over 14 rounds already; at 10x the scale they part too) ...
    stable = inlp(x, y, device="cpu")
    ref_basis, ref_history = release_inlp(x, y)
    assert stable.train_r2 == pytest.approx(ref_history, abs=1e-6) and stable.rank == ref_basis.shape[1]
    assert stable.rank == 3 * stable.rounds
    # ... and the float32 steps part from it after some rounds: each re-projection leaves a little of the
    # removed regressors, which the next, weakly penalised ridge fits again
    common = min(len(got.train_r2), len(stable.train_r2))
    diffs = np.abs(np.subtract(got.train_r2[:common], stable.train_r2[:common]))
    assert diffs[:8].max() < 1e-3 and diffs.max() > 0.05
    assert got.rank != stable.rank
    with pytest.raises(ValueError, match="unknown INLP procedure"):
        inlp(x[:50], y[:50], procedure="float16")


def test_fit_bases_controls_come_from_the_inlp_training_rows():
    x, y = redundant_position(n=1500, d=24, seed=2)
    cell = fit_bases(x, y, device="cpu")
    tr, _ = split_rows(len(x))
    xt = x[tr].astype(np.float64)
    cov = np.cov(xt.T)
    b = cell["position"]
    assert cell["removed_variance"] == pytest.approx(np.trace(b.T @ cov @ b), rel=1e-8)
    assert cell["total_variance"] == pytest.approx(np.trace(cov), rel=1e-8)
    pc = variance_matched_pcs(xt, b)
    assert cell["k_pc"] == pc.k and cell["alpha_pc"] == pytest.approx(pc.alpha, rel=1e-8)
    g = torch.randn(x.shape[1], cell["rank"], generator=torch.Generator().manual_seed(1), dtype=torch.float32)
    q = np.linalg.qr(g.double().numpy())[0]  # the release's random control: seed + 1, float32 draws, QR
    assert np.allclose(np.abs(cell["random"].T @ q), np.eye(cell["rank"]), atol=1e-8)


def test_inlp_removes_a_planted_low_rank_subspace():
    rng = np.random.default_rng(0)
    n, d = 3000, 40
    x = rng.standard_normal((n, d))
    m = rng.standard_normal((3, 2))
    y = x[:, :3] @ m  # a 2-d target read from a planted 2-d subspace (columns of m in the first 3 axes)
    res = inlp(x, y)
    b = res.basis
    assert res.stopped == "r2"
    assert b.shape[0] == d and res.rank == 2 * (len(res.train_r2) - 1)
    assert np.allclose(b.T @ b, np.eye(res.rank), atol=1e-8)
    xr = project_out(x, b)
    w = ridge_fit(xr[:2400], y[:2400], 0.05)
    assert r2_score(y[2400:], xr[2400:] @ w) < 0.05
    assert r2_score(y[:2400], xr[:2400] @ w) < 0.05
    # the planted directions lie in the removed subspace (up to the ridge's shrinkage, 0.05 per row, acting
    # on the sample covariance's spread)
    planted_dirs = np.eye(d)[:, :3] @ m
    assert np.linalg.norm(project_out(planted_dirs.T, b)) < 1e-2 * np.linalg.norm(planted_dirs)
    rnd = random_orthonormal(d, res.rank, seed=0)
    assert rnd.shape == b.shape and np.allclose(rnd.T @ rnd, np.eye(res.rank), atol=1e-10)


def test_variance_matched_alpha_removes_exactly_the_target_variance():
    rng = np.random.default_rng(3)
    d = 12
    a = rng.standard_normal((d, d)) * rng.uniform(0.1, 3.0, d)
    x = rng.standard_normal((500, d)) @ a
    basis = random_orthonormal(d, 3, seed=5)
    pc = variance_matched_pcs(x, basis)
    removed = total_variance(x) - total_variance(project_out(x, pc.basis, pc.alpha))
    assert removed == pytest.approx(pc.target_variance, abs=1e-6, rel=0)
    assert pc.top_variance >= pc.target_variance
    assert removed == pytest.approx(total_variance(x) - total_variance(project_out(x, basis)), abs=1e-6, rel=0)
    lam = np.sort(np.linalg.eigvalsh(np.cov(x.T)))[::-1]
    assert pc.k == 1 or lam[:pc.k - 1].sum() < pc.target_variance
    alpha, k, top = variance_matched_alpha(lam[0] * 0.75, lam)
    assert k == 1 and alpha * (2 - alpha) * top == pytest.approx(lam[0] * 0.75, abs=1e-9)


def test_slot_mapping_of_the_4n_plus_1_vae():
    assert slot_frames(0) == [0]
    assert slot_frames(1) == [1, 2, 3, 4]
    assert slot_frames(12) == [45, 46, 47, 48]
    assert n_slots(49) == 13 and n_slots(9) == 3


def test_mask_pooling_on_a_hand_built_clip():
    # 9 frames (3 slots) of 8x16 pixels, token grid 2x4 (4x4-pixel cells); two actors
    masks = np.zeros((9, 2, 8, 16), dtype=bool)
    masks[0, 0, 0, 0] = True               # actor 0 in frame 0: one pixel of token (0, 0)
    masks[2, 0, 5, 5] = True               # actor 0 in frame 2 -> slot 1, token (1, 1)
    masks[4, 0, 0, 15] = True              # ... frame 4 -> slot 1, token (0, 3)
    masks[5:9, 1, 4:8, 8:16] = True        # actor 1 in slot 2: tokens (1, 2) and (1, 3)
    tm = slot_token_masks(masks, 3, (2, 4))
    assert tm.shape == (3, 2, 2, 4)
    assert tm[0, 0].sum() == 1 and tm[0, 0, 0, 0]
    assert tm[1, 0].sum() == 2 and tm[1, 0, 1, 1] and tm[1, 0, 0, 3]
    assert tm[2, 1].sum() == 2 and tm[2, 1, 1, 2] and tm[2, 1, 1, 3]
    assert not tm[0, 1].any() and not tm[2, 0].any() and not tm[1, 1].any()
    w, index = pooling_matrix(tm)
    assert index.tolist() == [[0, 0], [1, 0], [2, 1]]  # uncovered (slot, actor) pairs have no row
    tokens = np.arange(24 * 2, dtype=np.float32).reshape(24, 2)  # token t = slot*8 + row*4 + col
    rows, _ = pool_actors(tokens, tm)
    assert np.allclose(rows[0], tokens[0])
    assert np.allclose(rows[1], (tokens[8 + 5] + tokens[8 + 3]) / 2)
    assert np.allclose(rows[2], (tokens[16 + 6] + tokens[16 + 7]) / 2)
    trows, _ = pool_actors(torch.as_tensor(tokens), tm)
    assert np.allclose(trows.numpy(), rows)
    # a non-integer cell size (a 144x256 render onto a 2x4 grid) covers the boundary rows in both cells
    m = np.zeros((3, 5), dtype=bool)
    m[1, 0] = True
    assert max_pool_to_grid(m, (2, 2))[:, 0].tolist() == [True, True]


def test_slot_targets_on_a_hand_built_trajectory():
    t = 9
    pos = np.zeros((2, t, 3))
    pos[0, :, 0] = np.arange(t)               # actor 0 moves 1 m per frame along x
    quat = np.tile([1.0, 0, 0, 0], (2, t, 1))
    quat[1] *= -1                              # sign-flipped quaternion is the same orientation
    vel = np.gradient(pos, 1 / 10, axis=1)
    contacts = [SimpleNamespace(frame=3, a="b", b="a", normals=((1.0, 0, 0),))]
    out = slot_targets(pos, quat, vel, np.zeros_like(vel), 10.0, contacts, ("a", "b"), 3, 9)
    assert out["position"][1, 0, 0] == pytest.approx(2.5) and out["position"][2, 0, 0] == pytest.approx(6.5)
    assert np.allclose(out["orientation"][:, 1], [1, 0, 0, 0])
    assert out["linear_velocity"][1, 0, 0] == pytest.approx(10.0)
    assert np.allclose(out["acceleration"], 0.0)
    assert out["contact"][:, :, 0].tolist() == [[0, 0], [1, 1], [0, 0]]
    assert np.allclose(out["contact_normal"][1, 1], [1, 0, 0]) and np.allclose(out["contact_normal"][1, 0], [-1, 0, 0])
