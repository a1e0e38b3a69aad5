import shutil
from pathlib import Path

import pytest

from rigidbench.config import PACKAGE_CONFIG_DIR, ConfigError, load_registry


@pytest.fixture
def config_copy(tmp_path, monkeypatch):
    """A full copy of the packaged configs that a test may break; used as the only source."""
    root = tmp_path / "configs"
    shutil.copytree(PACKAGE_CONFIG_DIR, root)
    monkeypatch.setattr("rigidbench.config.PACKAGE_CONFIG_DIR", root)
    monkeypatch.delenv("RIGIDBENCH_CONFIG_PATH", raising=False)
    return root


def test_registry_counts_and_partitions():
    reg = load_registry()
    assert len(reg.objects) == 24 and len(reg.scenes) == 12 and len(reg.tasks) == 5
    assert sorted(reg.materials) == ["dark_wood", "light_wood", "polished_white_marble", "rough_grey_concrete"]
    assert set(reg.presets) == {"paper", "preview", "demo", "test"}
    demo, preview = reg.presets["demo"], reg.presets["preview"]  # the demo's preset: preview at half the samples
    assert demo.samples == 4 and demo.denoise and (demo.resolution, demo.frames) == (preview.resolution, preview.frames)
    assert reg.presets["paper"].resolution == (1280, 704) and reg.presets["paper"].samples == 32
    assert reg.presets["paper"].adaptive_threshold == 0.05 and reg.presets["paper"].frames == 49
    assert reg.presets["preview"].resolution == (320, 176) and reg.presets["preview"].samples == 8
    assert (reg.presets["paper"].light_transport, reg.presets["paper"].denoise_quality) == ("full", "high")
    assert (reg.presets["preview"].light_transport, reg.presets["preview"].denoise_quality) == ("fast", "fast")
    assert len(reg.objects_in("train")) == 16 and len(reg.objects_in("held_out")) == 8
    assert reg.scenes_in("held_out") == ("beach_gazebo", "butterfly_mural_room", "cozy_living_room",
                                         "modern_warm_kitchen")
    assert reg.object("bouncy_ball").physics.restitution == 0.85
    assert reg.task("bounce").support_override.restitution == 0.6
    assert reg.task("bounce").support_override.friction == 0.3
    sim = reg.sim
    assert (sim.fps, sim.frames, sim.substeps, sim.solver_iterations) == (24, 49, 30, 20)
    assert (sim.linear_damping, sim.angular_damping, sim.active_margin_m, sim.passive_margin_m) == (0.1, 0.5, 0.001, 0.0001)


def test_bouncy_tag_resolution_matches_reference():
    reg = load_registry()
    bouncy = sorted(o.id for o in reg.objects.values() if "bouncy" in o.tags)
    assert bouncy == ["baseball", "bouncy_ball", "cricket_ball", "tennis_ball"]


def test_unknown_tag_names_file_field_and_known_values(config_copy):
    path = config_copy / "objects" / "apple.yaml"
    path.write_text(path.read_text().replace("tags: [all, rolling, stackable]", "tags: [all, roling, stackable]"))
    with pytest.raises(ConfigError) as exc:
        load_registry()
    msg = str(exc.value)
    assert str(path) in msg and "'tags'" in msg and "roling" in msg
    assert "did you mean 'rolling'" in msg and "known values: all, bouncy, rolling, stackable" in msg


def test_unknown_material_and_step_reference(config_copy):
    path = config_copy / "tasks" / "ball_chain.yaml"
    path.write_text(path.read_text().replace("ramp: ramp,", "ramp: rampp,"))
    with pytest.raises(ConfigError) as exc:
        load_registry()
    assert str(path) in str(exc.value) and "steps[1].ramp" in str(exc.value) and "known values: ramp" in str(exc.value)


def test_invalid_yaml_reports_line(config_copy):
    path = config_copy / "scenes" / "modern_loft.yaml"
    path.write_text("id: modern_loft\nsupports: [\n")
    with pytest.raises(ConfigError) as exc:
        load_registry()
    assert str(path) in str(exc.value) and "not valid YAML" in str(exc.value) and "line" in str(exc.value)


def test_missing_and_wrong_typed_fields(config_copy):
    path = config_copy / "objects" / "kiwi.yaml"
    path.write_text(path.read_text().replace("mass_kg: 0.08", "mass_kg: heavy"))
    with pytest.raises(ConfigError, match=r"kiwi.yaml: field 'physics.mass_kg': expected a number"):
        load_registry()


def test_unknown_field_is_rejected_with_suggestion(config_copy):
    path = config_copy / "objects" / "kiwi.yaml"
    path.write_text(path.read_text() + "partiton: train\n")
    with pytest.raises(ConfigError, match=r"field 'partiton': unknown field \(did you mean 'partition'\?\)"):
        load_registry()


def test_task_counts_must_name_known_tasks(config_copy):
    path = config_copy / "splits.yaml"
    path.write_text(path.read_text().replace("free_fall: 1047", "freefall: 1047"))
    with pytest.raises(ConfigError, match=r"train.task_counts.freefall': unknown task 'freefall' \(did you mean 'free_fall'\?\)"):
        load_registry()


def test_extra_config_dir_adds_an_object(tmp_path, monkeypatch):
    extra = tmp_path / "extra" / "objects"
    extra.mkdir(parents=True)
    src = (PACKAGE_CONFIG_DIR / "objects" / "apple.yaml").read_text()
    (extra / "green_apple.yaml").write_text(src.replace("id: apple", "id: green_apple").replace("name: Apple", "name: Green apple"))
    reg = load_registry([tmp_path / "extra"])
    assert reg.object("green_apple").name == "Green apple" and len(reg.objects) == 25


def test_unknown_lookup_suggests():
    reg = load_registry()
    with pytest.raises(ConfigError, match="did you mean 'tennis_ball'"):
        reg.object("tenis_ball")


def test_user_mesh_must_exist(config_copy):
    path = config_copy / "objects" / "kiwi.yaml"
    path.write_text(path.read_text() + "mesh: meshes/kiwi.glb\n")
    with pytest.raises(ConfigError, match=r"kiwi.yaml: field 'mesh': mesh file .*kiwi.glb does not exist"):
        load_registry()
    Path(config_copy / "objects" / "meshes").mkdir()
    (config_copy / "objects" / "meshes" / "kiwi.glb").write_bytes(b"glTF")
    assert load_registry().object("kiwi").mesh_path.endswith("kiwi.glb")


def test_preset_transport_keys_default_to_the_paper_and_reject_unknown_values(config_copy):
    path = config_copy / "render.yaml"
    text = path.read_text()
    custom = ("  quick:\n    resolution: [160, 88]\n    frames: 6\n    samples: 3\n    denoise: true\n"
              "    max_bounces: 2\n    diffuse_bounces: 1\n    glossy_bounces: 1\n    transmission_bounces: 1\n"
              "    persistent_data: true\n")
    path.write_text(text.rstrip("\n") + "\n" + custom)
    quick = load_registry().preset("quick")
    assert (quick.light_transport, quick.denoise_quality, quick.samples) == ("full", "high", 3)
    path.write_text(text.rstrip("\n") + "\n" + custom + "    light_transport: quick\n")
    with pytest.raises(ConfigError) as exc:
        load_registry()
    msg = str(exc.value)
    assert str(path) in msg and "presets.quick.light_transport" in msg and "'quick'" in msg and "fast" in msg


def test_cli_config_and_environment_become_the_run_context(tmp_path, monkeypatch, capsys):
    # The CLI alone reads $RIGIDBENCH_CONFIG_PATH and --config; stages get the directories in the run context.
    from rigidbench.cli import build_context, build_parser, main
    from rigidbench.config import registry

    monkeypatch.delenv("RIGIDBENCH_CONFIG_PATH", raising=False)
    extra = tmp_path / "cfg"
    extra.mkdir()
    text = (PACKAGE_CONFIG_DIR / "render.yaml").read_text()
    (extra / "render.yaml").write_text(text.rstrip("\n") + "\n  quick:\n    resolution: [160, 88]\n    frames: 6\n"
                                       "    samples: 3\n    denoise: false\n    max_bounces: 2\n"
                                       "    diffuse_bounces: 1\n    glossy_bounces: 1\n"
                                       "    transmission_bounces: 1\n    persistent_data: true\n")
    with pytest.raises(ConfigError, match="unknown render preset 'quick'"):
        registry().preset("quick")
    assert main(["--config", str(extra), "manifest", "--split", "eval", "--out", str(tmp_path / "m.jsonl")]) == 0
    with pytest.raises(ConfigError, match="unknown render preset 'quick'"):
        registry().preset("quick")  # main changed no process-wide state
    ctx = build_context(build_parser().parse_args(["--config", str(extra), "manifest", "--split", "eval"]))
    assert ctx.config_dirs == (extra.resolve(),) and ctx.registry.preset("quick").samples == 3
    env_dir = tmp_path / "env"
    env_dir.mkdir()
    monkeypatch.setenv("RIGIDBENCH_CONFIG_PATH", str(env_dir))
    ctx = build_context(build_parser().parse_args(["--config", str(extra), "manifest", "--split", "eval"]))
    assert ctx.config_dirs == (env_dir.resolve(), extra.resolve())  # the environment first, then --config
    assert ctx.job()["config_dirs"] == [str(env_dir.resolve()), str(extra.resolve())]  # what render workers get
    monkeypatch.delenv("RIGIDBENCH_CONFIG_PATH")
    assert main(["--config", str(tmp_path / "missing"), "manifest", "--split", "eval"]) == 2
    assert str(tmp_path / "missing") in capsys.readouterr().err
