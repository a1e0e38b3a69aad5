"""Integration-test fixtures (pytest): torch on one thread, an empty Blender scene, the registry. The helpers the
tests import are in the fixtures package: ``fixtures.blender`` (requires_bpy, rendering examples) and
``fixtures.scenes`` (hand-built specs)."""

from __future__ import annotations

import pytest

from rigidbench.config import Registry, registry as load_registry


@pytest.fixture(scope="module")
def torch_single_thread():
    """torch on one thread for the module (the tiny models' numbers then do not depend on the machine)."""
    torch = pytest.importorskip("torch")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def empty_scene():
    """A factory-empty Blender scene (the asset tests build into it)."""
    bpy = pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed; run `make test`")
    bpy.ops.wm.read_factory_settings(use_empty=True)
    yield bpy.context.scene


@pytest.fixture(scope="session")
def reg() -> Registry:
    return load_registry()
