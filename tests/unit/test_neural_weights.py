"""Weights registry, `rigidbench weights`, missing-weight messages and the loading rules (env / cache)."""

import json
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("transformers")

from fixtures import tiny_perception  # noqa: E402

from rigidbench.cli import build_parser  # noqa: E402
from rigidbench.commands.scoring import cmd_weights  # noqa: E402
from rigidbench.errors import UserError  # noqa: E402
from rigidbench.perception import weights  # noqa: E402
from rigidbench.perception.features import WeightsUnavailable  # noqa: E402


@pytest.fixture(autouse=True)
def empty_caches(tmp_path, monkeypatch):
    """Point the Hugging Face and torch hub caches at empty folders and clear every override variable."""
    import huggingface_hub.constants

    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(tmp_path / "hf"))
    monkeypatch.setattr(torch.hub, "_hub_dir", str(tmp_path / "torch_hub"))
    for w in weights.WEIGHTS.values():
        if w.env:
            monkeypatch.delenv(w.env, raising=False)
    return tmp_path


def run_cmd(argv, capsys):
    code = cmd_weights(build_parser().parse_args(["weights", *argv]))
    out = capsys.readouterr()
    return code, out.out, out.err


def test_list_names_every_weight_with_source_override_and_status(capsys):
    code, out, _ = run_cmd(["--list"], capsys)
    assert code == 0
    for w in weights.WEIGHTS.values():
        assert w.name in out and w.source in out
        if w.env:
            assert f"${w.env}" in out
    lines = {line.split()[0]: line for line in out.splitlines() if line and not line.startswith(" ")}
    assert "MISSING" in lines["sam2"] and "MISSING" in lines["dinov2"] and "MISSING" in lines["alexnet"]
    assert "present" in lines["lpips-lin"]  # shipped inside the lpips package


def test_list_json_reports_env_override_path_and_size(tmp_path, monkeypatch, capsys):
    ckpt = tmp_path / "my_vda.pth"
    ckpt.write_bytes(b"x" * 1234)
    monkeypatch.setenv("RIGIDBENCH_VDA", str(ckpt))
    code, out, _ = run_cmd(["--list", "--json"], capsys)
    rows = {r["name"]: r for r in json.loads(out)}
    assert code == 0 and rows["vda"]["present"] and rows["vda"]["path"] == str(ckpt)
    assert rows["vda"]["size_bytes"] == 1234
    assert not rows["sam2"]["present"] and rows["sam2"]["size_bytes"] is None


def test_cache_lookup_finds_a_torch_hub_checkpoint(empty_caches):
    dst = empty_caches / "torch_hub" / "checkpoints" / "alexnet-owt-7be5be79.pth"
    dst.parent.mkdir(parents=True)
    dst.write_bytes(b"weights")
    assert weights.locate("alexnet") == dst and weights.status("alexnet")["size_bytes"] == 7


def test_missing_message_is_one_paragraph_naming_model_places_and_fix(empty_caches):
    msg = weights.missing_message("sam2")
    assert "\n" not in msg
    assert "SAM 2.1 Hiera Large" in msg and "facebook/sam2.1-hiera-large" in msg
    assert "$RIGIDBENCH_SAM2 (unset)" in msg and str(empty_caches / "hf") in msg
    assert "rigidbench weights --download sam2" in msg


def test_env_pointing_nowhere_is_reported_not_replaced(tmp_path, monkeypatch):
    monkeypatch.setenv("RIGIDBENCH_DINOV2", str(tmp_path / "nowhere"))
    assert weights.locate("dinov2") is None
    assert f"$RIGIDBENCH_DINOV2={tmp_path / 'nowhere'} (does not exist)" in weights.missing_message("dinov2")


def test_unknown_name_suggests_the_closest(capsys):
    with pytest.raises(UserError, match="--download: .*did you mean sam2"):  # the command line: one line, exit 2
        run_cmd(["--download", "sam3"], capsys)
    with pytest.raises(KeyError, match="did you mean dinov2"):
        weights.spec("dinov")


def test_download_fetches_into_the_standard_caches(monkeypatch, capsys, empty_caches):
    import huggingface_hub

    calls = []

    def fake_snapshot(repo_id, allow_patterns=None):
        calls.append(("snapshot", repo_id))
        return str(empty_caches / repo_id.replace("/", "_"))

    def fake_file(repo_id, filename):
        calls.append(("file", repo_id, filename))
        return str(empty_caches / filename)

    def fake_url(url, dst, progress=True):
        calls.append(("url", url, dst))
        Path(dst).write_bytes(b"ok")

    monkeypatch.setattr(huggingface_hub, "snapshot_download", fake_snapshot)
    monkeypatch.setattr(huggingface_hub, "hf_hub_download", fake_file)
    monkeypatch.setattr(torch.hub, "download_url_to_file", fake_url)
    code, out, err = run_cmd(["--download", "sam2", "vda", "alexnet"], capsys)
    assert code == 0, err
    assert calls[0] == ("snapshot", "facebook/sam2.1-hiera-large")
    assert calls[1] == ("file", "depth-anything/Video-Depth-Anything-Large", "video_depth_anything_vitl.pth")
    assert calls[2][1] == "https://download.pytorch.org/models/alexnet-owt-7be5be79.pth"
    assert weights.locate("alexnet") == empty_caches / "torch_hub" / "checkpoints" / "alexnet-owt-7be5be79.pth"
    assert "alexnet: downloaded to" in out


def test_bare_download_fetches_the_defaults_and_a_failure_is_one_line(monkeypatch, capsys):
    fetched = []

    def fake_download(name):
        fetched.append(name)
        if name == "dinov2":
            raise WeightsUnavailable("could not download DINOv2: no network")
        return Path("/cache") / name

    monkeypatch.setattr(weights, "download", fake_download)
    code, out, err = run_cmd(["--download"], capsys)
    assert code == 1
    assert fetched == ["sam2", "cotracker", "cotracker-code", "vda", "dinov2", "alexnet"]  # not the dav2 fallback
    assert err.strip() == "dinov2: could not download DINOv2: no network" and "Traceback" not in err
    assert "lpips-lin: present at" in out


def test_failed_network_download_becomes_weights_unavailable(monkeypatch):
    import huggingface_hub

    def offline(*args, **kwargs):
        raise ConnectionError("Name or service not known")

    monkeypatch.setattr(huggingface_hub, "snapshot_download", offline)
    with pytest.raises(WeightsUnavailable, match="could not download SAM 2.1 Hiera Large .* not known"):
        weights.download("sam2")


# -- the loaders follow the rules: explicit path, then env, then cache; missing -> the message


def test_sam2_loads_from_env_directory_and_says_where_it_looked_when_missing(tmp_path, monkeypatch):
    from rigidbench.perception.sam2 import load_sam2

    with pytest.raises(WeightsUnavailable) as err:
        load_sam2()
    assert str(err.value) == weights.missing_message("sam2")
    tiny = tiny_perception.tiny_sam2(seed=3)
    tiny.save_pretrained(tmp_path / "sam2")
    monkeypatch.setenv("RIGIDBENCH_SAM2", str(tmp_path / "sam2"))
    loaded = load_sam2()
    assert loaded.dtype == torch.float32 and not loaded.training
    torch.testing.assert_close(loaded.mask_downsample.weight, tiny.mask_downsample.weight)


def test_dinov2_identity_features_from_env_directory(tmp_path, monkeypatch):
    from rigidbench.perception.features import load_identity_features

    tiny = tiny_perception.tiny_dinov2()
    tiny.save_pretrained(tmp_path / "dino")
    monkeypatch.setenv("RIGIDBENCH_DINOV2", str(tmp_path / "dino"))
    f = load_identity_features(device="cpu")
    x = torch.randn(3, 3, 224, 224)
    out = f(x)
    assert out.shape == (3, 32) and out.dtype == torch.float32
    torch.testing.assert_close(out, tiny(pixel_values=x).pooler_output)


def test_cotracker_needs_its_checkpoint_unless_random(tmp_path, monkeypatch):
    from rigidbench.perception.cotracker import load_cotracker

    with pytest.raises(WeightsUnavailable, match="CoTracker torch-hub repository"):
        load_cotracker()
    monkeypatch.setenv("RIGIDBENCH_COTRACKER", str(tiny_perception.HUB_DIR))
    with pytest.raises(WeightsUnavailable, match="scaled_offline.pth"):
        load_cotracker()
    # A checkpoint named by the env variable is loaded into the hub entry's model.
    reference = load_cotracker(pretrained=False)
    state = {k: torch.full_like(v, 0.25) for k, v in reference.state_dict().items()}
    torch.save(state, tmp_path / "ckpt.pth")
    monkeypatch.setenv("RIGIDBENCH_COTRACKER_CKPT", str(tmp_path / "ckpt.pth"))
    loaded = load_cotracker()
    assert all(torch.equal(v, state[k]) for k, v in loaded.state_dict().items())


def test_feature_nets_load_from_overrides_or_are_skipped_with_the_message(tmp_path, monkeypatch):
    from rigidbench.perception.features import load_feature_nets
    from rigidbench.metrics.lpips_net import alexnet_features

    nets = load_feature_nets(device="cpu")
    assert nets.lpips is None and nets.identity is None
    assert nets.skipped["lpips"] == weights.missing_message("alexnet")
    assert "DINOv2 ViT-L/14" in nets.skipped["iddrift"]
    torch.save({f"features.{k}": v for k, v in alexnet_features().state_dict().items()}, tmp_path / "alex.pth")
    tiny_perception.tiny_dinov2().save_pretrained(tmp_path / "dino")
    monkeypatch.setenv("RIGIDBENCH_ALEXNET", str(tmp_path / "alex.pth"))
    monkeypatch.setenv("RIGIDBENCH_DINOV2", str(tmp_path / "dino"))
    nets = load_feature_nets(device="cpu")
    assert not nets.skipped and nets.key == "lpips=yes,iddrift=yes"
    x = torch.rand(2, 3, 64, 64) * 2 - 1
    assert torch.allclose(nets.lpips(x, x), torch.zeros(2)) and bool((nets.lpips(x, -x) > 0).all())


def test_evaluate_stops_before_any_example_when_neural_weights_are_missing(tmp_path, monkeypatch):
    from rigidbench.errors import EvaluationError
    from rigidbench.stages.evaluate import evaluate

    ckpt = tmp_path / "vda.pth"
    ckpt.write_bytes(b"present")
    monkeypatch.setenv("RIGIDBENCH_VDA", str(ckpt))  # one weight present: not reported
    (tmp_path / "preds").mkdir()
    (tmp_path / "preds" / "00000.mp4").write_bytes(b"not read")  # an example to score: the check runs
    (tmp_path / "data" / "00000").mkdir(parents=True)
    (tmp_path / "data" / "00000" / "metadata.json").write_text("{}")  # a bundle that is never read
    with pytest.raises(EvaluationError) as err:
        evaluate(tmp_path / "preds", tmp_path / "data", tmp_path / "run", perception="neural",
                 perception_options={"device": "cpu"})
    text = str(err.value)
    for name in ("sam2", "cotracker", "cotracker-code"):
        assert f"rigidbench weights --download {name}`" in text
    assert "download vda" not in text
    assert not (tmp_path / "run" / "examples").exists()  # stopped before writing anything
