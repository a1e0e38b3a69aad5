"""One registry idiom: lookups by name or alias, did-you-mean on typos, lazy loading, plug-ins."""

from dataclasses import dataclass

import pytest

from rigidbench.errors import RigidBenchError, UnknownNameError, UserError
from rigidbench.metrics import METRICS, MetricInfo
from rigidbench.perception.base import BACKENDS
from rigidbench.predictors import PREDICTORS, Kind, Predictor, PredictorInfo, predictor_info
from rigidbench.registry import LazyRegistry, load_target


@dataclass(frozen=True)
class Thing:
    name: str
    target: str
    aliases: tuple[str, ...] = ()


def test_lookup_by_name_and_alias_is_case_insensitive():
    reg = LazyRegistry("thing", [Thing("alpha", "math:sqrt", ("A",)), Thing("beta", "math:floor")])
    assert reg["ALPHA"].name == "alpha" and reg["a"].name == "alpha"
    assert list(reg) == ["alpha", "beta"] and len(reg) == 2 and "Beta" in reg and "gamma" not in reg
    assert reg.load("alpha")(9.0) == 3.0


def test_a_typo_names_the_nearest_entries():
    with pytest.raises(UnknownNameError) as err:
        PREDICTORS["gravty"]
    assert "Did you mean 'gravity'?" in str(err.value)
    with pytest.raises(KeyError, match="Did you mean 'ate3d'"):  # still a KeyError for mapping callers
        METRICS["ate-3"]
    assert "background-wobble" in PREDICTORS.nearest("backgroundwobble")
    with pytest.raises(UnknownNameError, match="Did you mean 'neural'"):
        BACKENDS["nueral"]


def test_names_and_aliases_cannot_be_registered_twice():
    reg = LazyRegistry("thing", [Thing("alpha", "math:sqrt", ("A",))])
    with pytest.raises(ValueError, match="already registered"):
        reg.add(Thing("a", "math:floor"))
    with reg.added(Thing("gamma", "math:floor")):
        assert "gamma" in reg
    assert "gamma" not in reg


def test_display_names_are_aliases_of_metrics():
    assert METRICS["IoU"].name == "iou" and METRICS["ATE-3D"].name == "ate3d" and METRICS["Cham."].name == "chamfer"


@pytest.mark.parametrize("name", list(METRICS))
def test_every_metric_entry_loads_a_compute_function(name):
    assert callable(METRICS[name].load())


@pytest.mark.parametrize("name", list(PREDICTORS))
def test_every_predictor_entry_loads(name):
    predictor = PREDICTORS[name].create()
    assert isinstance(predictor, Predictor) and predictor.name == name


@pytest.mark.parametrize("name", list(BACKENDS))
def test_every_perception_backend_entry_loads(name):
    assert isinstance(BACKENDS.load(name), type)


def test_load_target_errors_name_the_target():
    with pytest.raises(RigidBenchError, match="expected 'package.module:attr'"):
        load_target("no_colon")
    with pytest.raises(RigidBenchError, match="no module named 'surely_absent_pkg'"):
        load_target("surely_absent_pkg.mod:thing")
    with pytest.raises(RigidBenchError, match="has no attribute 'nope'"):
        load_target("math:nope")


def test_a_plugin_path_is_a_predictor_without_registration():
    info = predictor_info("rigidbench.predictors.image_space:static")
    assert info.kind == Kind.PLUGIN and info.name == "static" and not info.writes_state
    with pytest.raises(RigidBenchError, match="Did you mean 'static'"):
        predictor_info("statik")


def test_metric_entries_carry_everything_the_outputs_need():
    for info in METRICS.values():
        assert info.group in ("motion", "appearance") and info.display_name and info.curve_modes
        assert all(mode in PREDICTORS for mode in info.curve_modes + info.control_modes)
    assert [i.group for i in METRICS.values()] == ["motion"] * 6 + ["appearance"] * 4  # the paper's two blocks
    assert METRICS["bgdrift"].display_scale == 1e3 and METRICS["ssim"].higher_is_better


def test_registering_a_metric_makes_it_loadable():
    info = MetricInfo("toy", "math:fsum", "Toy", True, "appearance", "a toy")
    with METRICS.added(info):
        assert METRICS.load("toy") is __import__("math").fsum and list(METRICS)[-1] == "toy"
    assert "toy" not in METRICS


def test_predictor_info_create_rejects_a_non_callable_target():
    info = PredictorInfo("pi", "math:pi", "not a predictor", Kind.PLUGIN)
    with pytest.raises(UserError, match="neither a Predictor class nor a function"):
        info.create()


def test_installed_packages_register_predictors_through_entry_points(tmp_path, monkeypatch):
    dist = tmp_path / "still_model-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: still-model\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[rigidbench.predictors]\nstill = still_model:StillModel\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    try:
        info = predictor_info("still")  # not registered yet: entry points are read, nothing is imported
        assert info.target == "still_model:StillModel" and info.kind == Kind.PLUGIN and "still-model" in info.description
    finally:
        if "still" in PREDICTORS:
            PREDICTORS.remove("still")
