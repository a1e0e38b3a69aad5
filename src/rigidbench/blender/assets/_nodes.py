"""A thin builder over Blender shader node trees, plus numpy-painted images and material caching.

Materials are cached by name in ``bpy.data`` (a rebuilt scene after ``read_factory_settings``
simply recreates them), and painted images are computed once per process (``functools.cache``
on the numpy painter) and packed into the .blend so a saved file renders the same.
"""

from __future__ import annotations

import logging
from typing import Any, Callable

import numpy as np

log = logging.getLogger(__name__)

# ShaderNodeMix exposes one socket per data type under the same name; pick the colour/float ones.
_MIX_IDS = {"Factor": "Factor_Float", "A": "A_Color", "B": "B_Color"}
_MIX_FLOAT_IDS = {"Factor": "Factor_Float", "A": "A_Float", "B": "B_Float"}


class Graph:
    """Add nodes by type with inputs given by name; a socket value links, anything else is set."""

    def __init__(self, tree):
        self.tree = tree
        self.nodes = tree.nodes
        self.links = tree.links

    def add(self, node_type: str, props: dict[str, Any] | None = None, **inputs: Any):
        node = self.nodes.new(node_type)
        for key, value in (props or {}).items():
            setattr(node, key, value)
        ids = {}
        if node_type == "ShaderNodeMix":
            ids = _MIX_FLOAT_IDS if node.data_type == "FLOAT" else _MIX_IDS
        for key, value in inputs.items():
            name = key.replace("_", " ")
            sock = _input(node, ids.get(name, name))
            self.set(sock, value)
        return node

    def set(self, sock, value: Any) -> None:
        """Link ``value`` into ``sock`` if it is a socket (or node: first output), else assign it."""
        import bpy

        if isinstance(value, bpy.types.Node):
            value = value.outputs[0]
        if isinstance(value, bpy.types.NodeSocket):
            self.links.new(value, sock)
            return
        if isinstance(value, (tuple, list)) and len(value) == 3 and sock.type == "RGBA":
            value = (*value, 1.0)
        sock.default_value = value

    # -- common patterns --------------------------------------------------------------------

    def coords(self, kind: str = "Object"):
        """Texture coordinates: 'Object' (model frame, metres), 'UV' or 'Generated'."""
        return self.add("ShaderNodeTexCoord").outputs[kind]

    def noise(self, vector, scale: float, detail: float = 2.0, roughness: float = 0.5, distortion: float = 0.0,
              dims: str = "3D", w: float = 0.0):
        return self.add("ShaderNodeTexNoise", {"noise_dimensions": dims}, Vector=vector, Scale=scale,
                        Detail=detail, Roughness=roughness, Distortion=distortion, W=w)

    def voronoi(self, vector, scale: float, feature: str = "F1", randomness: float = 1.0):
        return self.add("ShaderNodeTexVoronoi", {"feature": feature}, Vector=vector, Scale=scale,
                        Randomness=randomness)

    def ramp(self, factor, stops: list[tuple[float, tuple[float, ...]]], interpolation: str = "LINEAR"):
        """Colour ramp with ``stops`` [(position, rgb or rgba)]; returns the node (outputs Color, Alpha)."""
        node = self.add("ShaderNodeValToRGB", Fac=factor)
        cr = node.color_ramp
        cr.interpolation = interpolation
        while len(cr.elements) < len(stops):
            cr.elements.new(0.5)
        for el, (pos, col) in zip(cr.elements, stops):
            el.position = pos
            el.color = (*col, 1.0) if len(col) == 3 else col
        return node

    def mix(self, a, b, factor, blend: str = "MIX"):
        """Colour mix (outputs Result)."""
        node = self.add("ShaderNodeMix", {"data_type": "RGBA", "blend_type": blend}, Factor=factor, A=a, B=b)
        return _output(node, "Result_Color")

    def mixf(self, a, b, factor):
        node = self.add("ShaderNodeMix", {"data_type": "FLOAT"}, Factor=factor, A=a, B=b)
        return _output(node, "Result_Float")

    def math(self, op: str, a, b=0.0, c=None, clamp: bool = False):
        """Scalar math node; ``c`` is the third operand (MULTIPLY_ADD: a * b + c)."""
        node = self.add("ShaderNodeMath", {"operation": op, "use_clamp": clamp})
        self.set(node.inputs[0], a)
        self.set(node.inputs[1], b)
        if c is not None:
            self.set(node.inputs[2], c)
        return node.outputs[0]

    def vmath(self, op: str, a, b=(0.0, 0.0, 0.0)):
        node = self.add("ShaderNodeVectorMath", {"operation": op})
        self.set(node.inputs[0], a)
        self.set(node.inputs[1], b)
        return node.outputs[1] if op in ("LENGTH", "DOT_PRODUCT", "DISTANCE") else node.outputs[0]

    def mapping(self, vector, scale=(1.0, 1.0, 1.0), rotation=(0.0, 0.0, 0.0), location=(0.0, 0.0, 0.0)):
        return self.add("ShaderNodeMapping", Vector=vector, Scale=scale, Rotation=rotation,
                        Location=location).outputs[0]

    def separate(self, vector):
        return self.add("ShaderNodeSeparateXYZ", Vector=vector).outputs

    def image(self, img, vector=None, interpolation: str = "Linear", extension: str = "REPEAT"):
        node = self.add("ShaderNodeTexImage", {"image": img, "interpolation": interpolation, "extension": extension})
        if vector is not None:
            self.set(node.inputs["Vector"], vector)
        return node

    def bump(self, height, strength: float = 0.3, distance: float = 0.001, normal=None):
        node = self.add("ShaderNodeBump", Height=height, Strength=strength, Distance=distance)
        if normal is not None:
            self.set(node.inputs["Normal"], normal)
        return node.outputs["Normal"]

    def principled(self, **inputs):
        return self.add("ShaderNodeBsdfPrincipled", **inputs)

    def output(self, shader) -> None:
        out = self.add("ShaderNodeOutputMaterial")
        self.set(out.inputs["Surface"], shader)


def _input(node, name: str):
    for sock in node.inputs:
        if sock.identifier == name:
            return sock
    for sock in node.inputs:
        if sock.name == name and sock.enabled:
            return sock
    raise KeyError(f"shader node {node.bl_idname} has no input '{name}'; inputs: "
                   f"{', '.join(s.identifier for s in node.inputs)}")


def _output(node, identifier: str):
    for sock in node.outputs:
        if sock.identifier == identifier:
            return sock
    raise KeyError(f"shader node {node.bl_idname} has no output '{identifier}'")


def cached_material(name: str, build: Callable[[Graph], None]):
    """The material ``name`` from ``bpy.data``, built with ``build(graph)`` the first time."""
    import bpy

    mat = bpy.data.materials.get(name)
    if mat is not None:
        return mat
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    mat.node_tree.nodes.clear()
    build(Graph(mat.node_tree))
    return mat


def srgb_to_linear(rgb) -> tuple[float, float, float]:
    """rgb: 3 floats in display sRGB [0, 1]. Returns linear values for node colour sockets."""
    c = np.asarray(rgb, float)
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    return tuple(float(x) for x in lin)


def painted_image(name: str, painter: Callable[[], np.ndarray], colorspace: str = "sRGB"):
    """An image in ``bpy.data`` holding ``painter()`` ((H,W,3|4) float in [0,1], row 0 at the top).

    Colour images are sRGB; pass colorspace 'Non-Color' for data such as bump heights.
    """
    import bpy

    img = bpy.data.images.get(name)
    if img is not None:
        return img
    pixels = np.asarray(painter(), np.float32)
    h, w = pixels.shape[:2]
    if pixels.shape[2] == 3:
        pixels = np.concatenate([pixels, np.ones((h, w, 1), np.float32)], 2)
    img = bpy.data.images.new(name, w, h, alpha=False)
    img.colorspace_settings.name = colorspace
    img.pixels.foreach_set(np.ascontiguousarray(np.clip(pixels[::-1], 0.0, 1.0)).reshape(-1))
    img.pack()
    return img
