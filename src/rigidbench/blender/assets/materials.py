"""Procedural Cycles materials: ramp materials, object skins and the environment library.

Environment and ramp materials read metric UVs (1 UV unit = 1 m, see ``_mesh.box``), so a
texture keeps its real-world scale on any box. Object skins combine a numpy-painted UV image
(large-scale pattern) with object-space noise (fine detail and bump) so points on an object stay
trackable as it moves. Materials are cached by name in ``bpy.data``.
"""

from __future__ import annotations

from typing import Callable

from ...config import MaterialConfig
from ._nodes import Graph, cached_material, painted_image, srgb_to_linear

RAMP_PATTERNS = ("wood", "marble", "concrete", "plain")


def _scaled(rgb, k: float) -> tuple[float, float, float]:
    return tuple(min(1.0, max(0.0, c * k)) for c in rgb)


def _lin(rgb) -> tuple[float, float, float]:
    return srgb_to_linear(rgb)


# ---------------------------------------------------------------------------------------------
# Ramp materials (and the wood/marble/concrete used by supports and furniture)


def ramp_material(material: MaterialConfig):
    """bpy Material for a ramp: params.pattern (wood, marble, concrete, plain), base_colour (sRGB), roughness."""
    params = material.params
    pattern = params.get("pattern", "plain")
    colour = tuple(params.get("base_colour", (0.6, 0.6, 0.6)))
    roughness = float(params.get("roughness", 0.5))
    if pattern not in RAMP_PATTERNS or len(colour) != 3:
        raise ValueError(f"{material.source or material.id}: field 'params': pattern must be one of "
                         f"{', '.join(RAMP_PATTERNS)} and base_colour three numbers; got {pattern!r}, {colour!r}")
    name = f"rb_ramp_{material.id}"
    if pattern == "wood":
        return wood(name, colour, roughness, planks=False)
    if pattern == "marble":
        return marble(name, colour, roughness)
    if pattern == "concrete":
        return concrete(name, colour, roughness)
    return painted(name, colour, roughness)


def wood(name: str, colour, roughness: float, planks: bool = False, plank_m: tuple[float, float] = (1.2, 0.14),
         grain: float = 1.0, coat: float = 0.0, contrast: float = 1.0):
    """Wood with grain along UV u (x): long streaks, fine fibres and, with ``planks``, boards with seams."""
    def build(g: Graph) -> None:
        uv = g.coords("UV")
        streaks = g.noise(g.mapping(uv, scale=(1.2, 22.0 * grain, 1.2)), scale=1.0, detail=6.0, roughness=0.6,
                          distortion=0.4)
        fibre = g.noise(g.mapping(uv, scale=(3.0, 140.0, 3.0)), scale=1.0, detail=5.0, roughness=0.65)
        fac = g.math("MULTIPLY_ADD", streaks.outputs["Fac"], 0.65, g.math("MULTIPLY", fibre, 0.35))
        dark, light = 1 - 0.3 * contrast, 1 + 0.14 * contrast
        col = g.ramp(fac, [(0.3, _lin(_scaled(colour, dark))), (0.5, _lin(colour)),
                           (0.7, _lin(_scaled(colour, light)))]).outputs["Color"]
        height = fibre
        if planks:
            brick = g.add("ShaderNodeTexBrick", {"offset": 0.37, "offset_frequency": 1}, Vector=uv, Scale=1.0,
                          Color1=(0.8, 0.8, 0.8, 1.0), Color2=(1.08, 1.05, 1.0, 1.0), Mortar=(0.25, 0.25, 0.25, 1.0),
                          Mortar_Size=0.0012, Mortar_Smooth=0.3, Bias=0.0, Brick_Width=plank_m[0],
                          Row_Height=plank_m[1])
            col = g.mix(col, brick.outputs["Color"], 1.0, blend="MULTIPLY")
            height = g.math("SUBTRACT", fibre, g.math("MULTIPLY", brick.outputs["Fac"], 2.0))
        rough = g.math("MULTIPLY_ADD", fibre, 0.2, roughness - 0.1)
        bsdf = g.principled(Base_Color=col, Roughness=rough, Coat_Weight=coat, Coat_Roughness=0.15,
                            Normal=g.bump(height, strength=0.12, distance=0.002))
        g.output(bsdf)
    return cached_material(name, build)


def marble(name: str, colour, roughness: float, vein=(0.35, 0.35, 0.38), vein_scale: float = 2.0):
    """Polished stone with thin dark veins (two noise layers) and a glossy coat. The two layers are 3D noise
    at different offsets (off the lattice plane z = 0 of the flat UVs): half the cost of 4D noise, which
    made marble the most expensive surface in the kitchens."""
    def build(g: Graph) -> None:
        uv = g.coords("UV")
        n1 = g.noise(g.mapping(uv, location=(13.7, 5.1, 0.37)), scale=vein_scale, detail=8.0, roughness=0.6,
                     distortion=1.2)
        n2 = g.noise(g.mapping(uv, location=(3.3, 9.9, 0.71)), scale=vein_scale * 2.6, detail=6.0, roughness=0.55,
                     distortion=0.8)
        v1 = g.math("ABSOLUTE", g.math("SUBTRACT", n1.outputs["Fac"], 0.5))
        v2 = g.math("ABSOLUTE", g.math("SUBTRACT", n2.outputs["Fac"], 0.5))
        veins = g.ramp(v1, [(0.0, (0.0,) * 3), (0.012, (0.55,) * 3), (0.05, (1.0,) * 3)]).outputs["Color"]
        fine = g.ramp(v2, [(0.0, (0.45,) * 3), (0.008, (0.85,) * 3), (0.03, (1.0,) * 3)]).outputs["Color"]
        mask = g.mix(veins, fine, 1.0, blend="MULTIPLY")
        cloud = g.noise(uv, scale=3.0, detail=4.0)
        base = g.mix(_lin(colour), _lin(_scaled(colour, 0.93)), cloud.outputs["Fac"])
        col = g.mix(_lin(vein), base, g.math("POWER", g.add("ShaderNodeRGBToBW", Color=mask).outputs[0], 1.5))
        bsdf = g.principled(Base_Color=col, Roughness=roughness, Coat_Weight=0.4, Coat_Roughness=0.03,
                            Normal=g.bump(mask, strength=0.02, distance=0.001))
        g.output(bsdf)
    return cached_material(name, build)


def concrete(name: str, colour, roughness: float):
    """Rough cement: blotchy tone, aggregate speckles and pitted bump."""
    def build(g: Graph) -> None:
        uv = g.coords("UV")
        blotch = g.noise(uv, scale=3.0, detail=8.0, roughness=0.6)
        grain = g.noise(uv, scale=90.0, detail=6.0, roughness=0.7)
        pits = g.voronoi(uv, scale=160.0)
        tone = g.ramp(blotch.outputs["Fac"], [(0.3, _lin(_scaled(colour, 0.82))), (0.7, _lin(_scaled(colour, 1.1)))])
        col = g.mix(tone.outputs["Color"], _lin(_scaled(colour, 0.6)),
                    g.math("LESS_THAN", pits.outputs["Distance"], 0.08))
        col = g.mix(col, _lin(_scaled(colour, 1.2)), g.math("GREATER_THAN", grain.outputs["Fac"], 0.68))
        height = g.math("ADD", grain.outputs["Fac"], g.math("MULTIPLY", pits.outputs["Distance"], 0.8))
        bsdf = g.principled(Base_Color=col, Roughness=roughness, Normal=g.bump(height, strength=0.35, distance=0.002))
        g.output(bsdf)
    return cached_material(name, build)


def painted(name: str, colour, roughness: float = 0.7, variation: float = 0.05, bump: float = 0.03,
            metallic: float = 0.0, coat: float = 0.0, scale: float = 4.0):
    """A painted or plain surface with a faint tone variation and micro bump."""
    def build(g: Graph) -> None:
        uv = g.coords("UV")
        n = g.noise(uv, scale=scale, detail=4.0)
        col = g.mix(_lin(_scaled(colour, 1 - variation)), _lin(_scaled(colour, 1 + variation)), n.outputs["Fac"])
        micro = g.noise(uv, scale=400.0, detail=2.0)
        bsdf = g.principled(Base_Color=col, Roughness=roughness, Metallic=metallic, Coat_Weight=coat,
                            Normal=g.bump(micro, strength=bump, distance=0.001))
        g.output(bsdf)
    return cached_material(name, build)


def metal(name: str, colour, roughness: float = 0.3):
    """Brushed metal (brass, steel, black iron)."""
    def build(g: Graph) -> None:
        uv = g.coords("UV")
        brush = g.noise(g.mapping(uv, scale=(2.0, 300.0, 2.0)), scale=1.0, detail=3.0)
        rough = g.math("MULTIPLY_ADD", brush, 0.15, roughness - 0.05)
        g.output(g.principled(Base_Color=_lin(colour), Metallic=1.0, Roughness=rough))
    return cached_material(name, build)


def fabric(name: str, colour, weave_m: float = 0.003, sheen: float = 0.6, pattern: str = "plain",
           second=(0.9, 0.9, 0.9), stripe_m: float = 0.12):
    """Woven textile with sheen; pattern 'plain', 'stripes' (along v) or 'check'."""
    def build(g: Graph) -> None:
        uv = g.coords("UV")
        sep = g.separate(uv)
        wx = g.math("SINE", g.math("MULTIPLY", sep[0], 6.283 / weave_m))
        wy = g.math("SINE", g.math("MULTIPLY", sep[1], 6.283 / weave_m))
        weave = g.math("MULTIPLY", g.math("ADD", wx, wy), 0.25)
        tone = g.noise(uv, scale=8.0, detail=3.0)
        base = g.mix(_lin(_scaled(colour, 0.9)), _lin(_scaled(colour, 1.08)), tone.outputs["Fac"])
        if pattern in ("stripes", "check"):
            s1 = g.math("GREATER_THAN", g.math("SINE", g.math("MULTIPLY", sep[1], 6.283 / stripe_m)), 0.3)
            mask = s1
            if pattern == "check":
                s2 = g.math("GREATER_THAN", g.math("SINE", g.math("MULTIPLY", sep[0], 6.283 / stripe_m)), 0.3)
                mask = g.math("MAXIMUM", s1, s2)
            base = g.mix(base, _lin(second), mask)
        col = g.mix(base, (0.0, 0.0, 0.0, 1.0), g.math("MULTIPLY", g.math("ADD", weave, 0.5), 0.25))
        bsdf = g.principled(Base_Color=col, Roughness=0.9, Sheen_Weight=sheen, Sheen_Roughness=0.4,
                            Normal=g.bump(weave, strength=0.25, distance=0.001))
        g.output(bsdf)
    return cached_material(name, build)


def tiles(name: str, colour, grout=(0.85, 0.85, 0.82), tile_m: tuple[float, float] = (0.15, 0.075),
          offset: float = 0.5, roughness: float = 0.15, variation: float = 0.08, grout_m: float = 0.003):
    """Glazed tiles in a (running or stack) bond with recessed grout."""
    def build(g: Graph) -> None:
        uv = g.coords("UV")
        brick = g.add("ShaderNodeTexBrick", {"offset": offset, "offset_frequency": 2}, Vector=uv, Scale=1.0,
                      Color1=(*_lin(_scaled(colour, 1 - variation)), 1.0),
                      Color2=(*_lin(_scaled(colour, 1 + variation)), 1.0),
                      Mortar=(*_lin(grout), 1.0), Mortar_Size=grout_m, Mortar_Smooth=0.3, Bias=0.0,
                      Brick_Width=tile_m[0], Row_Height=tile_m[1])
        glaze = g.noise(uv, scale=30.0, detail=3.0)
        rough = g.mixf(roughness, 0.85, brick.outputs["Fac"])
        height = g.math("SUBTRACT", g.math("MULTIPLY", glaze.outputs["Fac"], 0.1), brick.outputs["Fac"])
        bsdf = g.principled(Base_Color=brick.outputs["Color"], Roughness=rough,
                            Normal=g.bump(height, strength=0.3, distance=0.002))
        g.output(bsdf)
    return cached_material(name, build)


def brick_wall(name: str, colour=(0.55, 0.24, 0.16), mortar=(0.72, 0.7, 0.66)):
    """Exposed brick with per-brick tone, soot and recessed mortar."""
    def build(g: Graph) -> None:
        uv = g.coords("UV")
        brick = g.add("ShaderNodeTexBrick", {"offset": 0.5, "offset_frequency": 2}, Vector=uv, Scale=1.0,
                      Color1=(*_lin(colour), 1.0), Color2=(*_lin(_scaled(colour, 0.7)), 1.0),
                      Mortar=(*_lin(mortar), 1.0), Mortar_Size=0.01, Mortar_Smooth=0.4, Bias=0.0,
                      Brick_Width=0.215, Row_Height=0.075)
        dirt = g.noise(uv, scale=2.0, detail=6.0)
        grit = g.noise(uv, scale=120.0, detail=4.0)
        col = g.mix(brick.outputs["Color"], _lin(_scaled(colour, 0.45)),
                    g.math("MULTIPLY", g.math("SUBTRACT", dirt.outputs["Fac"], 0.45), 1.2, clamp=True))
        height = g.math("SUBTRACT", g.math("MULTIPLY", grit.outputs["Fac"], 0.3), brick.outputs["Fac"])
        bsdf = g.principled(Base_Color=col, Roughness=0.85, Normal=g.bump(height, strength=0.5, distance=0.004))
        g.output(bsdf)
    return cached_material(name, build)


def image_material(name: str, image_name: str, painter: Callable, roughness: float = 0.7, sheen: float = 0.0,
                   coat: float = 0.0, bump: float = 0.02):
    """A surface showing a painted image over its (0..1) UVs: prints, murals, rugs."""
    def build(g: Graph) -> None:
        uv = g.coords("UV")
        img = g.image(painted_image(image_name, painter), uv, extension="EXTEND")
        micro = g.noise(uv, scale=300.0, detail=2.0)
        bsdf = g.principled(Base_Color=img.outputs["Color"], Roughness=roughness, Sheen_Weight=sheen,
                            Coat_Weight=coat, Normal=g.bump(micro, strength=bump, distance=0.001))
        g.output(bsdf)
    return cached_material(name, build)


def emissive(name: str, colour, strength: float):
    """A glowing lamp shade or screen (also lights the scene a little)."""
    def build(g: Graph) -> None:
        g.output(g.principled(Base_Color=_lin(colour), Emission_Color=_lin(colour), Emission_Strength=strength,
                              Roughness=0.6))
    return cached_material(name, build)


def leaves(name: str, colour=(0.2, 0.42, 0.15)):
    """Plant foliage: veined green with some translucency."""
    def build(g: Graph) -> None:
        obj = g.coords("Object")
        n = g.noise(obj, scale=12.0, detail=3.0)
        col = g.mix(_lin(_scaled(colour, 0.7)), _lin(_scaled(colour, 1.25)), n.outputs["Fac"])
        bsdf = g.principled(Base_Color=col, Roughness=0.45, Sheen_Weight=0.2)
        g.output(bsdf)
    return cached_material(name, build)


def glass(name: str, tint=(0.9, 0.95, 1.0), roughness: float = 0.02):
    def build(g: Graph) -> None:
        g.output(g.principled(Base_Color=_lin(tint), Roughness=roughness, Transmission_Weight=1.0, IOR=1.45))
    return cached_material(name, build)


def sand(name: str, colour=(0.86, 0.76, 0.58)):
    """Beach sand: grainy tone and rippled bump."""
    def build(g: Graph) -> None:
        uv = g.coords("UV")
        ripples = g.add("ShaderNodeTexWave", {"wave_type": "BANDS", "bands_direction": "X"}, Vector=uv, Scale=3.0,
                        Distortion=8.0, Detail=2.0)
        grain = g.noise(uv, scale=300.0, detail=2.0)
        blotch = g.noise(uv, scale=0.6, detail=4.0)
        col = g.mix(_lin(_scaled(colour, 0.85)), _lin(_scaled(colour, 1.08)), blotch.outputs["Fac"])
        col = g.mix(col, _lin(_scaled(colour, 0.7)), g.math("GREATER_THAN", grain.outputs["Fac"], 0.66))
        height = g.math("ADD", g.math("MULTIPLY", ripples.outputs["Fac"], 0.5), grain.outputs["Fac"])
        g.output(g.principled(Base_Color=col, Roughness=0.95, Normal=g.bump(height, strength=0.4, distance=0.01)))
    return cached_material(name, build)


def water(name: str, colour=(0.05, 0.25, 0.32)):
    """Sea surface: dark teal, glossy, with wave bump."""
    def build(g: Graph) -> None:
        uv = g.coords("UV")
        waves = g.noise(g.mapping(uv, scale=(0.4, 1.5, 1.0)), scale=1.5, detail=6.0, roughness=0.55)
        g.output(g.principled(Base_Color=_lin(colour), Roughness=0.04, Specular_IOR_Level=0.6,
                              Normal=g.bump(waves, strength=0.15, distance=0.05)))
    return cached_material(name, build)


def rattan(name: str, colour=(0.72, 0.55, 0.33)):
    """Woven cane (basketry): crossing bands."""
    def build(g: Graph) -> None:
        uv = g.coords("UV")
        sep = g.separate(uv)
        a = g.math("SINE", g.math("MULTIPLY", g.math("ADD", sep[0], sep[1]), 300.0))
        b = g.math("SINE", g.math("MULTIPLY", g.math("SUBTRACT", sep[0], sep[1]), 300.0))
        weave = g.math("MAXIMUM", a, b)
        col = g.mix(_lin(_scaled(colour, 0.6)), _lin(colour), g.math("MULTIPLY_ADD", weave, 0.5, 0.5))
        g.output(g.principled(Base_Color=col, Roughness=0.7, Normal=g.bump(weave, strength=0.4, distance=0.002)))
    return cached_material(name, build)


# ---------------------------------------------------------------------------------------------
# Object skins


def skin(name: str, painter: Callable, roughness: float = 0.5, bump_scale: float = 250.0, bump: float = 0.1,
         sheen: float = 0.0, coat: float = 0.0, metallic: float = 0.0, image_bump: float = 0.0,
         variation: float = 0.12, specular: float = 0.5, roughness_from_image: float = 0.0,
         sheen_tint=(1.0, 1.0, 1.0), pits: float = 0.0):
    """An object surface: painted UV image (pattern) x object-space noise (tone, bump).

    ``image_bump`` > 0 raises bright image features (seams); < 0 recesses dark ones (die pips).
    ``pits`` adds Voronoi dimples (citrus peel) at the bump scale.
    """
    def build(g: Graph) -> None:
        uv = g.coords("UV")
        obj = g.coords("Object")
        img = g.image(painted_image(f"{name}_tex", painter), uv)
        tone = g.noise(obj, scale=bump_scale * 0.25, detail=3.0)
        value = g.math("MULTIPLY_ADD", tone.outputs["Fac"], 2 * variation, 1 - variation)
        col = g.add("ShaderNodeHueSaturation", Hue=0.5, Saturation=1.0, Value=value, Fac=1.0,
                    Color=img.outputs["Color"]).outputs[0]
        micro = g.noise(obj, scale=bump_scale, detail=4.0, roughness=0.6)
        height = micro.outputs["Fac"]
        if pits:
            cells = g.voronoi(obj, scale=bump_scale * 0.6)
            height = g.math("MULTIPLY_ADD", cells.outputs["Distance"], pits, height)
        if image_bump:
            lum = g.add("ShaderNodeRGBToBW", Color=img.outputs["Color"]).outputs[0]
            height = g.math("MULTIPLY_ADD", lum, image_bump, height)
        rough = roughness
        if roughness_from_image:
            lum = g.add("ShaderNodeRGBToBW", Color=img.outputs["Color"]).outputs[0]
            rough = g.math("MULTIPLY_ADD", lum, roughness_from_image, roughness)
        bsdf = g.principled(Base_Color=col, Roughness=rough, Metallic=metallic, Sheen_Weight=sheen,
                            Sheen_Roughness=0.35, Sheen_Tint=_lin(sheen_tint), Coat_Weight=coat, Coat_Roughness=0.05,
                            Specular_IOR_Level=specular, Normal=g.bump(height, strength=bump, distance=0.0005))
        g.output(bsdf)
    return cached_material(name, build)


def plain(name: str, colour, roughness: float = 0.5, metallic: float = 0.0, noise_scale: float = 300.0,
          bump: float = 0.1, coat: float = 0.0, transmission: float = 0.0, variation: float = 0.15):
    """A single-colour object part (stem, beak, cap, can end) with object-space tone and bump."""
    def build(g: Graph) -> None:
        obj = g.coords("Object")
        n = g.noise(obj, scale=noise_scale, detail=3.0)
        col = g.mix(_lin(_scaled(colour, 1 - variation)), _lin(_scaled(colour, 1 + variation)), n.outputs["Fac"])
        normal = g.bump(n.outputs["Fac"], strength=bump, distance=0.0005)
        bsdf = g.principled(Base_Color=col, Roughness=roughness, Metallic=metallic, Coat_Weight=coat,
                            Transmission_Weight=transmission, Normal=normal)
        g.output(bsdf)
    return cached_material(name, build)


def wall_image(name: str, image_name: str, painter: Callable, size_m: tuple[float, float], roughness: float = 0.85):
    """A painted image repeating every ``size_m`` (width, height) metres over metric UVs (murals, wallpaper)."""
    def build(g: Graph) -> None:
        uv = g.mapping(g.coords("UV"), scale=(1.0 / size_m[0], 1.0 / size_m[1], 1.0))
        img = g.image(painted_image(image_name, painter), uv)
        micro = g.noise(g.coords("UV"), scale=150.0, detail=3.0)
        g.output(g.principled(Base_Color=img.outputs["Color"], Roughness=roughness,
                              Normal=g.bump(micro, strength=0.05, distance=0.002)))
    return cached_material(name, build)


def terrazzo(name: str, colour=(0.9, 0.88, 0.84), chips=((0.75, 0.45, 0.35), (0.35, 0.5, 0.5), (0.3, 0.3, 0.3))):
    """Polished terrazzo: pale matrix with coloured stone chips."""
    def build(g: Graph) -> None:
        uv = g.coords("UV")
        cells = g.voronoi(uv, scale=40.0)
        chip = g.math("LESS_THAN", g.noise(uv, scale=45.0, detail=1.0).outputs["Fac"], 0.42)
        pick = g.ramp(cells.outputs["Color"], [(0.0, _lin(chips[0])), (0.33, _lin(chips[1])),
                                               (0.66, _lin(chips[2]))], interpolation="CONSTANT")
        base = g.mix(_lin(colour), _lin(_scaled(colour, 0.94)), g.noise(uv, scale=5.0).outputs["Fac"])
        col = g.mix(base, pick.outputs["Color"], chip)
        g.output(g.principled(Base_Color=col, Roughness=0.25, Coat_Weight=0.2))
    return cached_material(name, build)
