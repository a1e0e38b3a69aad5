"""Render-time changes to one example that leave its simulation untouched (failure-mode counterfactuals).

``RenderOverrides`` is plain data handed to ``render.render_example``:

- ``materials_from``: actor name -> object id; the actor keeps its own mesh (so masks, depth and
  tracks do not change) but every material slot k takes the donor object's slot k mod n_donor
  (identity swap);
- ``offsets_m``: actor name -> (T, 3) world translation in metres added to the actor's rendered
  pose at sample frame t (its physics body, and so the simulation, is not moved).

Offsets move the rendered model (``render.dress_scene`` parents it to the actor's hidden physics body),
never the rigid body itself, whose pose the rigid-body cache owns.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from .assets import objects as asset_objects


@dataclass(frozen=True)
class RenderOverrides:
    materials_from: Mapping[str, str] = field(default_factory=dict)
    offsets_m: Mapping[str, np.ndarray] = field(default_factory=dict)

    def check(self, actor_names: tuple[str, ...], frames: int, sample_id: str) -> None:
        """Raise ValueError unless every named actor exists and every offset is (>= frames, 3) and finite."""
        unknown = sorted((set(self.materials_from) | set(self.offsets_m)) - set(actor_names))
        if unknown:
            raise ValueError(f"example {sample_id}: render overrides name unknown actors {', '.join(unknown)}; "
                             f"actors are {', '.join(actor_names)}")
        for name, off in self.offsets_m.items():
            off = np.asarray(off)
            if off.ndim != 2 or off.shape[1] != 3 or off.shape[0] < frames or not np.isfinite(off).all():
                raise ValueError(f"example {sample_id}: offset of actor '{name}' must be finite ({frames}, 3) "
                                 f"metres, got shape {off.shape}")

    def apply_dressing(self, dressing: Any, registry: Any) -> None:
        """Give each actor in ``materials_from`` its donor's materials (bpy; after ``dress_scene``)."""
        import bpy

        donors: dict[str, list] = {}
        for name, donor in self.materials_from.items():
            if donor not in donors:
                temp = asset_objects.build_object(registry.object(donor), f"rb_donor_{donor}")
                donors[donor] = list(temp.data.materials)
                mesh = temp.data
                bpy.data.objects.remove(temp, do_unlink=True)
                bpy.data.meshes.remove(mesh)
            mats = donors[donor]
            if not mats:
                raise RuntimeError(f"donor object '{donor}' has no materials to lend to actor '{name}'")
            slots = dressing.render_objects[name].data.materials
            for k in range(len(slots)):
                slots[k] = mats[k % len(mats)]
            if not len(slots):
                slots.append(mats[0])

    def pose(self, physics_objects: Mapping[str, Any], dressing: Any, frame: int) -> None:
        """Place each offset actor's render object at its physics pose translated by offsets_m[name][frame]."""
        from mathutils import Matrix, Vector

        for name, off in self.offsets_m.items():
            phys, shown = physics_objects[name], dressing.render_objects[name]
            shown.matrix_world = Matrix.Translation(Vector(tuple(map(float, off[frame])))) @ phys.matrix_world


__all__ = ["RenderOverrides"]
