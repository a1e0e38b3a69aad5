"""Render device choice (issue: OptiX, else CUDA, else CPU, chosen automatically and recorded), on a
stand-in for Cycles' add-on preferences, so the GPU branches run on a machine without a GPU."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from rigidbench.blender.render import RenderDevice, pick_device


@dataclass
class FakeDevice:
    name: str
    type: str
    use: bool = True


class FakePrefs:
    """The parts of ``CyclesPreferences`` that ``pick_device`` touches. ``backends`` maps a backend to the
    devices it lists (Cycles lists the CPU under every GPU backend); a missing backend raises as Blender
    builds without it do."""

    def __init__(self, backends: dict[str, list[FakeDevice]]):
        self.backends = backends
        self.devices = [d for ds in backends.values() for d in ds]
        self.compute_device_type = "NONE"
        self.refreshed = 0

    def refresh_devices(self):
        self.refreshed += 1

    def get_devices_for_type(self, kind):
        if kind not in self.backends:
            raise TypeError(f"enum '{kind}' not found")
        return self.backends[kind]


def cpu():
    return FakeDevice("EPYC", "CPU")


def test_optix_is_preferred_and_only_its_devices_are_used():
    optix, cuda, host = FakeDevice("H100", "OPTIX"), FakeDevice("H100", "CUDA"), cpu()
    prefs = FakePrefs({"OPTIX": [optix, host], "CUDA": [cuda]})
    chosen = pick_device(prefs, "auto")
    assert chosen == RenderDevice("OPTIX", ("H100",)) and chosen.is_gpu
    assert prefs.refreshed == 1 and prefs.compute_device_type == "OPTIX"
    assert optix.use and not cuda.use and not host.use
    assert chosen.describe() == "OPTIX: H100"


def test_cuda_when_optix_is_missing_or_empty():
    for backends in ({"CUDA": [FakeDevice("A100", "CUDA"), cpu()]},
                     {"OPTIX": [cpu()], "CUDA": [FakeDevice("A100", "CUDA"), cpu()]}):
        prefs = FakePrefs(backends)
        assert pick_device(prefs, "gpu") == RenderDevice("CUDA", ("A100",))
        assert prefs.compute_device_type == "CUDA"


def test_cpu_fallback_for_auto_error_for_gpu_and_no_probe_for_cpu():
    prefs = FakePrefs({"OPTIX": [cpu()], "CUDA": [cpu()]})
    auto = pick_device(prefs, "auto")
    assert auto.kind == "CPU" and not auto.is_gpu and auto.describe().startswith("CPU: ")
    assert prefs.compute_device_type == "NONE"
    with pytest.raises(RuntimeError, match="--device cpu or auto"):
        pick_device(prefs, "gpu")
    assert pick_device(None, "cpu").kind == "CPU"  # never touches the preferences
