"""Scene specification: manifest row -> SceneSpec (pure Python)."""

from .types import Body, BodyPhysics, CameraSpec, RampShape, SceneSpec, SimSpec, SupportSpec

__all__ = ["Body", "BodyPhysics", "CameraSpec", "RampShape", "SceneSpec", "SimSpec", "SupportSpec"]
