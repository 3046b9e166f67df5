#!/usr/bin/env python3
"""glTF material features: dray against Mitsuba 3, one small scene per feature, NVIDIA FLIP.

Each case is a sphere (radius 1, a 96 x 48 UV sphere with smooth normals, UVs, tangents and,
for one case, vertex colours) on a checkered ground quad (baseColorTexture, a 27 x 27 checker:
the same picture whichever way V runs), lit by a sun (KHR_lights_punctual directional,
irradiance 2) and a constant environment (radiance 0.25), seen by a perspective camera
(yfov 35 degrees) at 256x256. Only the sphere's material changes from case to case. The
script writes the glTF itself (one .bin with every buffer, one PNG texture per image), and
gives Mitsuba the very same triangles, normals, UVs, tangent direction (Mitsuba's shading
frame follows dp/du, which is the glTF tangent here) and vertex colours as `mi.Mesh`
objects in a scene built with `mi.load_dict`: Mitsuba's glTF importer is partial, and its
own `sphere` shape would be different geometry.

Mapping of each feature to the closest Mitsuba BSDF (the docstring of CASES says which
parts of the model differ; the report repeats it per row):
- metal base: `principled` with metallic 1 (Schlick Fresnel on base_color, GGX with
  alpha = roughness^2: glTF's metal, except Mitsuba's separable Smith masking against
  dray's height-correlated one).
- KHR_materials_anisotropy: `principled` with (roughness, anisotropic) solved so that its
  (alpha_u, alpha_v) equal glTF's (mix(alpha, 1, strength^2), alpha) along the tangent.
- KHR_materials_clearcoat: (a) the coat alone over a black base, against `roughplastic`
  (GGX, ior 1.5, black diffuse: the same lobe with exact instead of Schlick Fresnel);
  (b) the coat over the metal, against `principled`'s clearcoat: GTR1 with a fixed-
  roughness masking, weight 0.25 x clearcoat (so clearcoat 4 gives glTF's F0 0.04) and no
  attenuation of the base: a model difference, reported with that caveat.
- KHR_materials_sheen: `principled` sheen (Disney's: a Schlick-weighted grazing term on a
  Disney diffuse base, not the Charlie lobe); a sheen-less row shows what the base's
  model difference alone gives.
- KHR_materials_transmission + _ior: smooth glass against `dielectric`, rough glass
  against `roughdielectric` (GGX); Mitsuba's Fresnel is exact, glTF's Schlick.
- KHR_materials_volume: smooth glass with Beer-Lambert attenuation against `dielectric`
  with an interior `homogeneous` medium (sigma_t = -ln(attenuationColor) /
  attenuationDistance, albedo 0) under `volpath`.
- KHR_materials_dispersion: no Mitsuba counterpart in RGB, but dray traces one channel
  per path with that channel's index (n at 656.3, 587.6, 486.1 nm from the extension's
  Abbe-number fit), so the reference is three Mitsuba `dielectric` renders, one per
  index, whose R, G and B are composed into one image.
- KHR_materials_emissive_strength: an `area` emitter of radiance emissiveFactor x
  strength on the same mesh.
- COLOR_0: `diffuse` with a `mesh_attribute` reflectance holding the same vertex colours.
- KHR_texture_transform: a `bitmap` base colour with `to_uv` = the transform's matrix
  (offset x rotation x scale).
- KHR_materials_iridescence: no Mitsuba counterpart (no thin-film BSDF); checked against
  dray itself only (below), and the FLIP of the film against no film is reported as the
  size of its effect.

Checks against dray itself, per case: the extension at its neutral value (clearcoat 0,
sheen colour black, anisotropy 0, iridescence 0 and thickness 0, dispersion 0, emissive
strength 1, attenuation colour white, an identity texture transform, white vertex
colours) must render the same pixels, bit for bit, as the material without the
extension (a 16 spp render each; the EXR's float pixels are compared).

Quality: dray and Mitsuba (llvm_ad_rgb; scalar_rgb when the llvm variant cannot run)
render each case at --spp; the LDR images (clamp to [0,1], sRGB) are compared with NVIDIA
FLIP (PyPI flip-evaluator), averaged over the image and over the sphere's pixels (the
ground is the same in every case); a second Mitsuba render with another seed gives the
noise floor (FLIP Mitsuba against Mitsuba), and for volume and dispersion, whose dray
renders are noisier than Mitsuba's, a second dray render gives dray's. The sphere's mean
linear radiance, dray / Mitsuba per channel, is reported too, overall and in three bands
of the viewing cosine, so a bias shows even where FLIP stays low and says where it is.

Timed: dray's render_time_s (the renderer's own, from --stats) and the wall time of the
whole `dray render` process; Mitsuba's `mi.render` of the second seed (the first one
includes JIT compilation) and its load_dict + render; --runs N repeats dray and the warm
Mitsuba render N times and reports medians. Both run pinned to the same cores (taskset)
with the same thread count.

Depth and Russian roulette as benches/vs_mitsuba.py explains: Mitsuba max_depth = dray
--max-depth + 1, rr_depth 4 (dray's roulette starts on the bounce out of vertex depth 3).
Default --max-depth 16: glass needs several bounces; roulette ends most paths long before.

Usage (from the repository root; creates benches/.venv on first use):
    benches/gltf_vs_mitsuba.sh                          # builds dray, then runs this
    python3 benches/gltf_vs_mitsuba.py [--cases clearcoat,sheen] [--spp 256] [--runs 1]
Outputs go to benches/out/gltf_vs_mitsuba/ (per case: PNGs of both renderers, FLIP maps,
the glTF; results.json).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _bench_env as env  # noqa: E402
import vs_mitsuba as vsm  # noqa: E402  (tonemap, fetch_llvm, light_basis, gltf_matrix: one definition)

WIDTH = HEIGHT = 256
YFOV_DEG = 35.0
ZNEAR = 1e-3
EYE = (0.0, 2.1, 5.2)
TARGET = (0.0, 0.85, 0.0)
SUN_IRRADIANCE = 2.0
SUN_DIRECTION = (-0.45, -1.0, -0.35)
ENV_RADIANCE = 0.25
SPHERE_CENTER = (0.0, 1.0, 0.0)
SPHERE_RADIUS = 1.0
SPHERE_SEGMENTS = (96, 48)  # around, pole to pole
GROUND_HALF = 6.0
CHECKER_CELLS = 27  # odd: the checker is the same picture with V flipped
CHECKER_SRGB = (70, 190)  # the two greys (8-bit sRGB) of the ground
DRAY_RR_START = 3
MITSUBA_RR_DEPTH = DRAY_RR_START + 1
FRAUNHOFER_NM = (656.3, 587.6, 486.1)  # C, d, F: dray's R, G, B (core/src/dispersion.rs)

METAL = [0.95, 0.64, 0.54]  # copper-like F0
METAL_ROUGHNESS = 0.35


def ior_at(ior: float, dispersion: float, lam: float) -> float:
    """KHR_materials_dispersion's Cauchy fit through the Abbe number (as core/src/dispersion.rs)."""
    return max(ior + (ior - 1.0) * (dispersion / 20.0) * (523655.0 / (lam * lam) - 1.5168), 1.0)


def rgb(v):
    v = [v, v, v] if isinstance(v, (int, float)) else list(v)
    return {"type": "rgb", "value": v}


def principled_aniso(roughness: float, strength: float) -> tuple[float, float]:
    """(roughness, anisotropic) of Mitsuba's principled whose (alpha_u, alpha_v) are glTF's
    (mix(a, 1, s^2), a), a = roughness^2. Principled: aspect = sqrt(1 - 0.9 anisotropic),
    alpha_u = r^2 / aspect, alpha_v = r^2 aspect."""
    a = roughness * roughness
    at = a + (1.0 - a) * strength * strength
    r = (a * at) ** 0.25
    aspect2 = a / at
    aniso = (1.0 - aspect2) / 0.9
    if not 0.0 <= aniso <= 1.0:
        raise ValueError(f"anisotropy {strength} at roughness {roughness} is beyond principled's range")
    return r, aniso


def mat(name: str, base=(0.8, 0.8, 0.8), metallic=0.0, roughness=0.5, ext=None, **extra) -> dict:
    m = {"name": name, "doubleSided": True,
         "pbrMetallicRoughness": {"baseColorFactor": [*base, 1.0], "metallicFactor": metallic,
                                  "roughnessFactor": roughness}}
    if ext:
        m["extensions"] = ext
    m.update(extra)
    return m


NO_SPEC = {"KHR_materials_specular": {"specularFactor": 0.0}}  # pure Lambert dielectric base
LAMBERT_DARK = (0.05, 0.08, 0.3)


def glass(name, roughness=0.0, ior=1.5, **ext) -> dict:
    e = {"KHR_materials_transmission": {"transmissionFactor": 1.0}, "KHR_materials_ior": {"ior": ior}}
    e.update(ext)
    return mat(name, (1.0, 1.0, 1.0), 0.0, roughness, e)


def build_cases() -> list[dict]:
    """Every case: the sphere's glTF material, the Mitsuba BSDF (or none), what differs,
    and the neutral-value bit checks (pairs of materials that must render the same bits)."""
    metal = mat("metal", METAL, 1.0, METAL_ROUGHNESS)
    principled_metal = {"type": "principled", "base_color": rgb(METAL), "metallic": 1.0,
                        "roughness": METAL_ROUGHNESS}
    ar, aa = principled_aniso(METAL_ROUGHNESS, 0.6)
    coat_alpha = 0.1 ** 2
    lambert_dark = mat("lambert", LAMBERT_DARK, 0.0, 0.5, dict(NO_SPEC))
    principled_dark = {"type": "principled", "base_color": rgb(LAMBERT_DARK), "metallic": 0.0,
                       "roughness": 0.5, "specular": 0.0}
    n_d, disp = 1.5, 3.0
    att = (0.9, 0.55, 0.25)
    att_dist = 1.0
    sigma_t = [-math.log(c) / att_dist for c in att]
    emis, strength = (0.2, 0.12, 0.04), 4.0
    tt = {"offset": [0.1, 0.2], "rotation": 0.4, "scale": [3.0, 2.0]}
    film = {"iridescenceFactor": 1.0, "iridescenceIor": 1.3, "iridescenceThicknessMaximum": 400.0}
    dark_dielectric = (0.02, 0.02, 0.02)
    cases = [
        {"name": "metal", "feature": "base: rough metal (pbrMetallicRoughness)",
         "material": metal, "mitsuba": principled_metal,
         "mapping": "principled, metallic 1 (Schlick F on base_color, GGX alpha = roughness^2)",
         "differs": "Smith masking: Mitsuba separable, dray height-correlated"},
        {"name": "anisotropy", "feature": "KHR_materials_anisotropy (strength 0.6, rotation 0)",
         "material": mat("aniso", METAL, 1.0, METAL_ROUGHNESS,
                         {"KHR_materials_anisotropy": {"anisotropyStrength": 0.6}}),
         "mitsuba": {"type": "principled", "base_color": rgb(METAL), "metallic": 1.0, "roughness": ar,
                     "anisotropic": aa},
         "mapping": f"principled, metallic 1, roughness {ar:.4f}, anisotropic {aa:.4f} (same alpha_u, alpha_v "
                    "along the tangent = dp/du)",
         "differs": "as the metal base",
         "bits": [("anisotropyStrength 0 = no extension", "KHR_materials_anisotropy", {"anisotropyStrength": 0.0},
                   metal)]},
        {"name": "clearcoat_lobe", "feature": "KHR_materials_clearcoat over a black base (coat roughness 0.2)",
         "material": mat("coat_only", (0.0, 0.0, 0.0), 0.0, 1.0,
                         {**NO_SPEC, "KHR_materials_clearcoat": {"clearcoatFactor": 1.0,
                                                                 "clearcoatRoughnessFactor": 0.2}}),
         "mitsuba": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.04, "int_ior": 1.5, "ext_ior": 1.0,
                     "diffuse_reflectance": rgb(0.0), "nonlinear": False},
         "mapping": "roughplastic, GGX alpha 0.04, ior 1.5, black diffuse",
         "differs": "Fresnel: Mitsuba exact, dray Schlick F0 0.04; Smith masking as the metal"},
        {"name": "clearcoat", "feature": "KHR_materials_clearcoat over the metal (factor 1, roughness 0.1)",
         "material": mat("coated_metal", METAL, 1.0, METAL_ROUGHNESS,
                         {"KHR_materials_clearcoat": {"clearcoatFactor": 1.0, "clearcoatRoughnessFactor": 0.1}}),
         "mitsuba": dict(principled_metal, clearcoat=4.0, clearcoat_gloss=(0.1 - coat_alpha) / 0.099),
         "mapping": f"principled, clearcoat 4 (its weight is 0.25 x clearcoat), clearcoat_gloss "
                    f"{(0.1 - coat_alpha) / 0.099:.3f} (GTR1 alpha {coat_alpha:.2f})",
         "differs": "model: Disney's coat is GTR1 with a fixed 0.25-roughness masking and does not attenuate "
                    "the base; glTF's is GGX and the base is attenuated by 1 - F_coat in and out",
         "bits": [("clearcoatFactor 0 = no extension", "KHR_materials_clearcoat", {"clearcoatFactor": 0.0,
                                                                                   "clearcoatRoughnessFactor": 0.1},
                   metal)]},
        {"name": "lambert", "feature": "base: Lambert (specularFactor 0), for the sheen rows",
         "material": lambert_dark, "mitsuba": principled_dark,
         "mapping": "principled, metallic 0, specular 0, roughness 0.5",
         "differs": "model: principled's diffuse is Disney's (retro-reflection, grazing darkening), not Lambert"},
        {"name": "sheen", "feature": "KHR_materials_sheen (colour 1, roughness 0.5) over the Lambert base",
         "material": mat("sheen", LAMBERT_DARK, 0.0, 0.5,
                         {**NO_SPEC, "KHR_materials_sheen": {"sheenColorFactor": [1.0, 1.0, 1.0],
                                                             "sheenRoughnessFactor": 0.5}}),
         "mitsuba": dict(principled_dark, sheen=1.0, sheen_tint=0.0),
         "mapping": "principled, sheen 1, sheen_tint 0, on the base above",
         "differs": "model: Disney's sheen (Schlick weight of the half-angle cosine, no roughness) against "
                    "the Charlie lobe with albedo scaling; plus the base's difference (row above)",
         "bits": [("sheenColorFactor 0 = no extension", "KHR_materials_sheen",
                   {"sheenColorFactor": [0.0, 0.0, 0.0], "sheenRoughnessFactor": 0.5}, lambert_dark)]},
        {"name": "glass", "feature": "KHR_materials_transmission + _ior, smooth (ior 1.5)",
         "material": glass("glass"), "mitsuba": {"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.0},
         "mapping": "dielectric, ior 1.5", "differs": "Fresnel: Mitsuba exact, dray Schlick (TIR exact in both)"},
        {"name": "glass_rough", "feature": "KHR_materials_transmission + _ior, rough (roughness 0.3, ior 1.33)",
         "material": glass("rough_glass", 0.3, 1.33),
         "mitsuba": {"type": "roughdielectric", "distribution": "ggx", "alpha": 0.09, "int_ior": 1.33,
                     "ext_ior": 1.0},
         "mapping": "roughdielectric, GGX alpha 0.09, ior 1.33",
         "differs": "Fresnel: exact against Schlick; Smith masking as the metal"},
        {"name": "volume", "feature": f"KHR_materials_volume (attenuationColor {list(att)}, distance {att_dist})",
         "material": glass("absorbing_glass", KHR_materials_volume={
             "thicknessFactor": 2.0, "attenuationColor": list(att), "attenuationDistance": att_dist}),
         "mitsuba": {"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.0},
         # sigma_t as an RGB in [0, 1] times `scale` (Mitsuba's RGB reflectance range)
         "interior": {"type": "homogeneous", "albedo": rgb(0.0), "scale": max(sigma_t),
                      "sigma_t": rgb([x / max(sigma_t) for x in sigma_t])},
         "integrator": "volpath",
         "mapping": "dielectric + interior homogeneous medium, sigma_t = -ln(colour)/distance, albedo 0, volpath",
         "differs": "Fresnel as the smooth glass", "dray_noise": True,
         "bits": [("attenuationColor white = no extension", "KHR_materials_volume",
                   {"thicknessFactor": 2.0, "attenuationColor": [1.0, 1.0, 1.0], "attenuationDistance": att_dist},
                   glass("glass"))]},
        {"name": "dispersion", "feature": f"KHR_materials_dispersion (dispersion {disp}, ior {n_d}: Abbe "
                                          f"{20.0 / disp:.2f})",
         "material": glass("dispersive_glass", ior=n_d, KHR_materials_dispersion={"dispersion": disp}),
         "mitsuba": {"type": "dielectric", "ext_ior": 1.0},
         "channels_ior": [ior_at(n_d, disp, lam) for lam in FRAUNHOFER_NM],
         "mapping": "no dispersive Mitsuba BSDF: three dielectric renders at n(656.3), n(587.6), n(486.1) = "
                    + ", ".join(f"{ior_at(n_d, disp, lam):.4f}" for lam in FRAUNHOFER_NM)
                    + ", composed channel by channel",
         "differs": "Fresnel as the smooth glass; the reference is exact for dray's RGB model of dispersion, "
                    "but dray's one-channel paths are noisier than three full renders (dray's own noise floor "
                    "is measured)", "dray_noise": True,
         "bits": [("dispersion 0 = no extension", "KHR_materials_dispersion", {"dispersion": 0.0}, glass("glass"))]},
        {"name": "emissive_strength", "feature": f"KHR_materials_emissive_strength (factor {list(emis)}, "
                                                 f"strength {strength})",
         "material": mat("emitter", (0.5, 0.5, 0.5), 0.0, 0.5,
                         {**NO_SPEC, "KHR_materials_emissive_strength": {"emissiveStrength": strength}},
                         emissiveFactor=list(emis), doubleSided=False),
         "mitsuba": {"type": "diffuse", "reflectance": rgb(0.5)},
         "emitter": {"type": "area", "radiance": rgb([c * strength for c in emis])},
         "mapping": "diffuse 0.5 + area emitter of radiance factor x strength (one-sided in both)",
         "differs": "none expected",
         "bits": [("emissiveStrength 1 = no extension", "KHR_materials_emissive_strength",
                   {"emissiveStrength": 1.0}, mat("emitter", (0.5, 0.5, 0.5), 0.0, 0.5, dict(NO_SPEC),
                                                  emissiveFactor=list(emis), doubleSided=False))]},
        {"name": "vertex_colors", "feature": "COLOR_0 (vertex colours x baseColorFactor)",
         "material": mat("vertex_coloured", (0.9, 0.9, 0.9), 0.0, 0.5, dict(NO_SPEC)), "colors": True,
         "mitsuba": {"type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_color",
                                                         "scale": 0.9}},
         "mapping": "diffuse with a mesh_attribute reflectance (the colours x 0.9)",
         "differs": "none expected",
         "bits": [("all-white COLOR_0 = no COLOR_0", None, "white_colors",
                   mat("vertex_coloured", (0.9, 0.9, 0.9), 0.0, 0.5, dict(NO_SPEC)))]},
        {"name": "texture_transform", "feature": "KHR_texture_transform on baseColorTexture (offset [0.1, 0.2], "
                                                 "rotation 0.4, scale [3, 2])",
         "material": mat("transformed", (1.0, 1.0, 1.0), 0.0, 0.5, dict(NO_SPEC)), "texture": tt,
         "mitsuba": {"type": "diffuse"},
         "mapping": "diffuse with a bitmap (sRGB, bilinear, repeat) and to_uv = the transform's matrix",
         "differs": "none expected",
         "bits": [("identity transform = no extension", None, "identity_transform", None)]},
        {"name": "iridescence", "feature": "KHR_materials_iridescence (factor 1, ior 1.3, 400 nm) over a dark "
                                           "dielectric (roughness 0.25)",
         "material": mat("film", dark_dielectric, 0.0, 0.25, {"KHR_materials_iridescence": film}),
         "mitsuba": None, "reference": mat("film", dark_dielectric, 0.0, 0.25),
         "mapping": "none: Mitsuba 3 has no thin-film BSDF",
         "differs": "not compared with Mitsuba; FLIP column: the film against the same material without it "
                    "(dray, the effect's size)",
         "bits": [("iridescenceFactor 0 = no extension", "KHR_materials_iridescence",
                   dict(film, iridescenceFactor=0.0), mat("film", dark_dielectric, 0.0, 0.25)),
                  ("thickness 0 = no extension", "KHR_materials_iridescence",
                   dict(film, iridescenceThicknessMaximum=0.0), mat("film", dark_dielectric, 0.0, 0.25))]},
    ]
    return cases


# ---------------------------------------------------------------------------------------
# Geometry and files
# ---------------------------------------------------------------------------------------

def sphere_mesh(colors: bool):
    """UV sphere: positions, normals, uvs (glTF's: v = 0 at the north pole, the image's top),
    tangents (dp/du, w = 1), optional colours, uint32 triangles wound outwards."""
    import numpy as np

    nu, nv = SPHERE_SEGMENTS
    u = np.linspace(0.0, 1.0, nu + 1)
    v = np.linspace(0.0, 1.0, nv + 1)
    uu, vv = np.meshgrid(u, v)  # (nv+1, nu+1)
    phi, theta = 2 * np.pi * uu, np.pi * vv
    n = np.stack([np.sin(theta) * np.cos(phi), np.cos(theta), -np.sin(theta) * np.sin(phi)], -1)
    t = np.stack([-np.sin(phi), np.zeros_like(phi), -np.cos(phi)], -1)
    pos = np.array(SPHERE_CENTER) + SPHERE_RADIUS * n
    idx = []
    for j in range(nv):
        for i in range(nu):
            a, b = j * (nu + 1) + i, j * (nu + 1) + i + 1
            c, d = (j + 1) * (nu + 1) + i, (j + 1) * (nu + 1) + i + 1
            if j != 0:
                idx.append((a, c, b))
            if j != nv - 1:
                idx.append((b, c, d))
    idx = np.array(idx, dtype=np.uint32)
    p = pos.reshape(-1, 3)
    tri = p[idx]
    ng = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    out = np.einsum("ij,ij->i", ng, tri.mean(1) - np.array(SPHERE_CENTER)) < 0
    idx[out] = idx[out][:, [0, 2, 1]]
    m = {"pos": p.astype("<f4"), "nrm": n.reshape(-1, 3).astype("<f4"),
         "uv": np.stack([uu, vv], -1).reshape(-1, 2).astype("<f4"),
         "tan": np.concatenate([t.reshape(-1, 3), np.ones((p.shape[0], 1))], 1).astype("<f4"), "idx": idx}
    if colors:
        m["col"] = (0.5 + 0.45 * m["nrm"]).astype("<f4")
    return m


def ground_mesh():
    import numpy as np

    h = GROUND_HALF
    p = np.array([[-h, 0, -h], [h, 0, -h], [h, 0, h], [-h, 0, h]], dtype="<f4")
    uv = ((p[:, [0, 2]] + h) / (2 * h)).astype("<f4")
    idx = np.array([[0, 2, 1], [0, 3, 2]], dtype=np.uint32)  # counter-clockwise seen from +Y
    return {"pos": p, "nrm": np.tile(np.array([0, 1, 0], "<f4"), (4, 1)), "uv": uv, "idx": idx}


def write_checker(path: Path):
    import numpy as np
    from PIL import Image

    cell = 32
    i = np.arange(CHECKER_CELLS * cell) // cell
    g = np.where((i[:, None] + i[None, :]) % 2 == 0, CHECKER_SRGB[0], CHECKER_SRGB[1]).astype(np.uint8)
    Image.fromarray(np.stack([g, g, g], -1)).save(path)


def write_test_texture(path: Path):
    """An asymmetric picture (stripes and a gradient) so a wrong transform or V convention shows."""
    import numpy as np
    from PIL import Image

    s = 256
    y, x = np.mgrid[0:s, 0:s]
    r = (x * 255 // (s - 1)).astype(np.uint8)
    g = np.where((x // 32 + y // 64) % 2 == 0, 220, 40).astype(np.uint8)
    b = (y * 255 // (s - 1)).astype(np.uint8)
    Image.fromarray(np.stack([r, g, b], -1)).save(path)


def texture_matrix(tt: dict):
    """KHR_texture_transform as a 3x3 (uv' = T R S uv; R = [[cos, sin], [-sin, cos]])."""
    c, s = math.cos(tt["rotation"]), math.sin(tt["rotation"])
    sx, sy = tt["scale"]
    ox, oy = tt["offset"]
    return [[c * sx, s * sy, ox], [-s * sx, c * sy, oy], [0.0, 0.0, 1.0]]


def camera_frame():
    fwd = vsm.normalize(tuple(t - e for t, e in zip(TARGET, EYE)))
    right = vsm.normalize(vsm.cross(fwd, (0.0, 1.0, 0.0)))
    up = vsm.cross(right, fwd)
    return EYE, right, up, fwd


class Buffer:
    """One glTF buffer with its views and accessors."""

    def __init__(self) -> None:
        self.data = bytearray()
        self.views: list = []
        self.accessors: list = []

    def add(self, arr, gl_type: str, target: int | None = None, minmax: bool = False) -> int:
        import numpy as np

        while len(self.data) % 4:
            self.data += b"\0"
        raw = arr.tobytes()
        view = {"buffer": 0, "byteOffset": len(self.data), "byteLength": len(raw)}
        if target:
            view["target"] = target
        self.views.append(view)
        self.data += raw
        comp = 5125 if arr.dtype == np.uint32 else 5126
        count = arr.size if gl_type == "SCALAR" else arr.shape[0]
        acc = {"bufferView": len(self.views) - 1, "componentType": comp, "count": count, "type": gl_type}
        if minmax:
            acc["min"], acc["max"] = arr.min(0).tolist(), arr.max(0).tolist()
        self.accessors.append(acc)
        return len(self.accessors) - 1


def write_gltf(case_dir: Path, sphere_material: dict, sphere, ground, texture_tt=None,
               texture_in_material: bool = False) -> Path:
    """The scene for dray: sphere (material 0), ground (material 1, checker), camera, sun."""
    buf = Buffer()

    def prim(m, material):
        attrs = {"POSITION": buf.add(m["pos"], "VEC3", 34962, True), "NORMAL": buf.add(m["nrm"], "VEC3", 34962),
                 "TEXCOORD_0": buf.add(m["uv"], "VEC2", 34962)}
        if "tan" in m:
            attrs["TANGENT"] = buf.add(m["tan"], "VEC4", 34962)
        if "col" in m:
            attrs["COLOR_0"] = buf.add(m["col"], "VEC3", 34962)
        return {"attributes": attrs, "indices": buf.add(m["idx"].reshape(-1), "SCALAR", 34963),
                "material": material, "mode": 4}

    eye, right, up, fwd = camera_frame()
    back = tuple(-c for c in fwd)
    lx, ly, lz = vsm.light_basis(SUN_DIRECTION)
    sphere_material = json.loads(json.dumps(sphere_material))
    images = [{"uri": "checker.png"}]
    textures = [{"source": 0}]
    if texture_in_material:
        images.append({"uri": "test_texture.png"})
        textures.append({"source": 1})
        info = {"index": 1}
        if texture_tt is not None:
            info["extensions"] = {"KHR_texture_transform": texture_tt}
        sphere_material["pbrMetallicRoughness"]["baseColorTexture"] = info
    ground_material = {"name": "checker", "doubleSided": True,
                       "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicFactor": 0.0,
                                                "roughnessFactor": 1.0},
                       "extensions": {"KHR_materials_specular": {"specularFactor": 0.0}}}
    meshes = [{"name": "sphere", "primitives": [prim(sphere, 0)]}, {"name": "ground", "primitives": [prim(ground, 1)]}]
    used = {"KHR_lights_punctual", "KHR_materials_specular"}
    for m in (sphere_material, ground_material):
        used.update(m.get("extensions", {}))
        tex = m["pbrMetallicRoughness"].get("baseColorTexture", {})
        used.update(tex.get("extensions", {}))
    doc = {
        "asset": {"version": "2.0", "generator": "dray benches/gltf_vs_mitsuba.py"},
        "extensionsUsed": sorted(used),
        "extensions": {"KHR_lights_punctual": {"lights": [
            {"name": "sun", "type": "directional", "color": [1.0, 1.0, 1.0], "intensity": SUN_IRRADIANCE}]}},
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 2, 3]}],
        "nodes": [
            {"name": "sphere", "mesh": 0},
            {"name": "ground", "mesh": 1},
            {"name": "camera", "camera": 0, "matrix": vsm.gltf_matrix(right, up, back, eye)},
            {"name": "sun", "matrix": vsm.gltf_matrix(lx, ly, lz, (0.0, 0.0, 0.0)),
             "extensions": {"KHR_lights_punctual": {"light": 0}}},
        ],
        "cameras": [{"name": "camera", "type": "perspective",
                     "perspective": {"yfov": math.radians(YFOV_DEG), "aspectRatio": WIDTH / HEIGHT,
                                     "znear": ZNEAR}}],
        "materials": [sphere_material, ground_material],
        "meshes": meshes,
        "images": images,
        "samplers": [{"magFilter": 9729, "minFilter": 9729, "wrapS": 10497, "wrapT": 10497}],
        "textures": [dict(t, sampler=0) for t in textures],
        "buffers": [{"uri": "scene.bin", "byteLength": len(buf.data)}],
        "bufferViews": buf.views,
        "accessors": buf.accessors,
    }
    (case_dir / "scene.bin").write_bytes(bytes(buf.data))
    path = case_dir / "scene.gltf"
    path.write_text(json.dumps(doc, indent=1) + "\n")
    return path


# ---------------------------------------------------------------------------------------
# Mitsuba worker (own process, pinned): python gltf_vs_mitsuba.py --mitsuba-worker cfg.json
# ---------------------------------------------------------------------------------------

def mi_mesh(mi, name: str, m: dict, bsdf: dict, emitter=None, interior=None):
    import numpy as np

    props = mi.Properties()
    props["bsdf"] = mi.load_dict(bsdf)
    if emitter:
        props["emitter"] = mi.load_dict(emitter)
    if interior:
        props["interior"] = mi.load_dict(interior)
    mesh = mi.Mesh(name, len(m["pos"]), len(m["idx"]), props=props, has_vertex_normals=True,
                   has_vertex_texcoords=True)
    p = mi.traverse(mesh)
    p["vertex_positions"] = mi.Float(np.ascontiguousarray(m["pos"], np.float32).ravel())
    p["vertex_normals"] = mi.Float(np.ascontiguousarray(m["nrm"], np.float32).ravel())
    p["vertex_texcoords"] = mi.Float(np.ascontiguousarray(m["uv"], np.float32).ravel())
    p["faces"] = mi.UInt32(np.ascontiguousarray(m["idx"], np.uint32).ravel())
    if "col" in m:
        mesh.add_attribute("vertex_color", 3, mi.Float(np.ascontiguousarray(m["col"], np.float32).ravel()))
    p.update()
    return mesh


def mitsuba_scene(mi, cfg: dict, bsdf: dict):
    import numpy as np

    eye, right, up, fwd = (tuple(v) for v in cfg["camera"])
    left = tuple(-c for c in right)
    to_world = mi.ScalarTransform4f([[left[0], up[0], fwd[0], eye[0]], [left[1], up[1], fwd[1], eye[1]],
                                     [left[2], up[2], fwd[2], eye[2]], [0.0, 0.0, 0.0, 1.0]])
    sphere = {k: np.load(v) for k, v in cfg["sphere"].items()}
    ground = {k: np.load(v) for k, v in cfg["ground"].items()}
    checker = {"type": "diffuse", "reflectance": {"type": "bitmap", "filename": cfg["checker"],
                                                  "filter_type": "bilinear", "wrap_mode": "repeat"}}
    if cfg.get("texture"):
        bsdf = dict(bsdf, reflectance={"type": "bitmap", "filename": cfg["texture"], "filter_type": "bilinear",
                                       "wrap_mode": "repeat",
                                       "to_uv": mi.ScalarTransform3f(cfg["texture_matrix"])})
    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": cfg["integrator"], "max_depth": cfg["max_depth"], "rr_depth": cfg["rr_depth"]},
        "sensor": {"type": "perspective", "fov_axis": "y", "fov": YFOV_DEG, "near_clip": ZNEAR, "far_clip": 1e4,
                   "to_world": to_world,
                   "film": {"type": "hdrfilm", "width": cfg["width"], "height": cfg["height"], "pixel_format": "rgb",
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": cfg["spp"]}},
        "sphere": mi_mesh(mi, "sphere", sphere, bsdf, cfg.get("emitter"), cfg.get("interior")),
        "ground": mi_mesh(mi, "ground", ground, checker),
        "sun": {"type": "directional", "direction": list(SUN_DIRECTION), "irradiance": rgb(SUN_IRRADIANCE)},
        "env": {"type": "constant", "radiance": rgb(ENV_RADIANCE)},
    })


def mitsuba_worker(cfg_path: Path) -> None:
    import numpy as np

    cfg = json.loads(cfg_path.read_text())
    import drjit as dr
    import mitsuba as mi

    mi.set_variant(cfg["variant"])
    dr.set_thread_count(cfg["threads"])
    # One BSDF per pass: one for most cases, one per colour channel for dispersion.
    passes = ([dict(cfg["bsdf"], int_ior=n) for n in cfg["channels_ior"]] if cfg.get("channels_ior")
              else [cfg["bsdf"]])
    runs = []
    for run in cfg["runs"]:
        img = None
        load_s = render_s = 0.0
        for c, bsdf in enumerate(passes):
            t0 = time.perf_counter()
            scene = mitsuba_scene(mi, cfg, bsdf)
            t1 = time.perf_counter()
            x = np.array(mi.render(scene, spp=cfg["spp"], seed=run["seed"]), dtype=np.float32)[..., :3]
            t2 = time.perf_counter()
            load_s += t1 - t0
            render_s += t2 - t1
            if len(passes) == 1:
                img = x
            else:
                img = np.zeros_like(x) if img is None else img
                img[..., c] = x[..., c]
        if run.get("save"):
            np.save(run["save"], img)
        runs.append({"seed": run["seed"], "load_s": load_s, "render_s": render_s, "total_s": load_s + render_s})
        print(f"run: {runs[-1]}", file=sys.stderr, flush=True)
    print(json.dumps({"variant": cfg["variant"], "thread_count": dr.thread_count(), "mitsuba": mi.__version__,
                      "runs": runs}))


# ---------------------------------------------------------------------------------------
# Driver
# ---------------------------------------------------------------------------------------

def add_comparison_args(ap, out: Path) -> None:
    """The options every dray-against-Mitsuba comparison with FLIP takes (this script's and
    benches/lens_sun_vs_mitsuba.py's): timed runs, threads and cores, seed, variant, outputs,
    and the hidden worker mode."""
    ap.add_argument("--runs", type=int, default=1, help="timed renders per renderer and case (medians; FLIP "
                    "uses the first); default 1")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--cores", default="0,1", help="cores for both renderers (taskset -c)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--variant", choices=("llvm_ad_rgb", "scalar_rgb"), default="llvm_ad_rgb",
                    help="Mitsuba variant (falls back to scalar_rgb when llvm cannot run)")
    ap.add_argument("--out", type=Path, default=out)
    ap.add_argument("--mitsuba-worker", type=Path, help=argparse.SUPPRESS)


def parse_args():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", help="comma-separated case names (default: all): " +
                    ", ".join(c["name"] for c in build_cases()))
    ap.add_argument("--spp", type=int, default=256, help="samples per pixel of every render (default 256)")
    ap.add_argument("--bits-spp", type=int, default=16, help="spp of the bit-for-bit dray checks (default 16)")
    ap.add_argument("--max-depth", type=int, default=16, help="dray's --max-depth; Mitsuba's is one more")
    add_comparison_args(ap, env.OUT / "gltf_vs_mitsuba")
    args = ap.parse_args()
    if args.mitsuba_worker:
        return args
    names = [c["name"] for c in build_cases()]
    args.case_names = names if not args.cases else [c.strip() for c in args.cases.split(",") if c.strip()]
    bad = [c for c in args.case_names if c not in names]
    if bad:
        ap.error(f"unknown case(s) {bad}; known: {names}")
    if min(args.spp, args.bits_spp, args.max_depth, args.runs, args.threads) < 1:
        ap.error("--spp, --bits-spp, --max-depth, --runs and --threads must be positive")
    if args.threads > len(env.parse_cores(args.cores)):
        ap.error("--threads is more than the number of --cores")
    return args


def run_dray(args, dray, gltf: Path, out: Path, tag: str, spp: int, seed: int) -> dict:
    png, exr, stats = out / f"dray_{tag}.png", out / f"dray_{tag}.exr", out / f"dray_{tag}.stats.json"
    cmd = env.pin(args.cores, [dray, "render", gltf, "--width", WIDTH, "--height", HEIGHT, "--spp", spp,
                               "--integrator", "path", "--max-depth", args.max_depth, "--seed", seed,
                               "--env", f"{ENV_RADIANCE},{ENV_RADIANCE},{ENV_RADIANCE}", "--threads", args.threads,
                               "--output", png, "--exr", exr, "--stats", stats, "-q"])
    r = env.run_timed(cmd)
    s = json.loads(stats.read_text())
    warn = [ln for ln in r["stderr"].splitlines() if ln.strip()]
    return {"cmd": r["cmd"], "wall_s": r["wall_s"], "render_s": s["render_time_s"], "exr": str(exr),
            "warnings": warn}


def run_mitsuba(args, cfg: dict, tag: str, extra_env: dict) -> dict:
    path = args.out / f"mitsuba_{tag}.json"
    path.write_text(json.dumps(cfg))
    e = dict(os.environ, **extra_env, HOME=str(args.out / "drjit_home"))  # Dr.Jit's kernel cache: with the outputs
    cmd = env.pin(args.cores, [sys.executable, Path(__file__).resolve(), "--mitsuba-worker", path])
    r = env.run_timed(cmd, env=e, check=False)
    if r["rc"] != 0:
        err = [ln for ln in r["stderr"].splitlines() if ln.strip()]
        key = next((ln for ln in err if "ERROR" in ln or "Error" in ln), err[-1] if err else "")
        return {"ok": False, "error": key.strip()[:400], "cmd": r["cmd"]}
    d = env.last_json_line(r["stdout"])
    d.update(ok=True, cmd=r["cmd"], process_wall_s=r["wall_s"])
    return d


def pick_variant(args, base_cfg: dict) -> tuple[str, dict]:
    """The Mitsuba variant that runs here, with the environment it needs (llvm_ad_rgb may
    need Debian's libLLVM 19, fetched into benches/.venv as vs_mitsuba.py does)."""
    if args.variant == "scalar_rgb":
        return "scalar_rgb", {}
    probe = dict(base_cfg, variant="llvm_ad_rgb", spp=1, runs=[{"seed": 0}], width=8, height=8,
                 bsdf={"type": "diffuse"}, integrator="path")
    tries = [dict(DRJIT_LIBLLVM_PATH=os.environ["DRJIT_LIBLLVM_PATH"])] if os.environ.get("DRJIT_LIBLLVM_PATH") \
        else [{}]
    for extra in tries:
        if run_mitsuba(args, probe, "probe", extra)["ok"]:
            return "llvm_ad_rgb", extra
    lib, how = vsm.fetch_llvm(env.VENV / "llvm")
    env.log(f"llvm_ad_rgb failed with the system LLVM; {how}")
    if lib and run_mitsuba(args, probe, "probe", {"DRJIT_LIBLLVM_PATH": str(lib)})["ok"]:
        return "llvm_ad_rgb", {"DRJIT_LIBLLVM_PATH": str(lib)}
    env.log("llvm_ad_rgb cannot run here: using scalar_rgb")
    return "scalar_rgb", {}


def same_pixels(a: str, b: str) -> bool:
    import numpy as np

    x, y = vsm.read_exr(a), vsm.read_exr(b)
    return x.shape == y.shape and np.array_equal(x.view(np.uint32), y.view(np.uint32))


def with_extension(material: dict, ext_name: str, ext_value: dict) -> dict:
    m = json.loads(json.dumps(material))
    m.setdefault("extensions", {})[ext_name] = ext_value
    return m


def sphere_mask():
    """Pixels whose centre ray (the pinhole camera of both renderers) hits the sphere: the
    ground is the same in every case, so differences are also averaged over these alone."""
    import numpy as np

    eye, right, up, fwd = (np.array(v) for v in camera_frame())
    t = math.tan(math.radians(YFOV_DEG) / 2)
    x = (2 * (np.arange(WIDTH) + 0.5) / WIDTH - 1) * t * WIDTH / HEIGHT
    y = (1 - 2 * (np.arange(HEIGHT) + 0.5) / HEIGHT) * t
    d = fwd + x[None, :, None] * right + y[:, None, None] * up
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    oc = eye - np.array(SPHERE_CENTER)
    b = d @ oc
    disc = b * b - (oc @ oc - SPHERE_RADIUS ** 2)
    hit = disc > 0
    p = eye + (-b - np.sqrt(np.maximum(disc, 0.0)))[..., None] * d
    cos_view = np.clip(-(d * (p - np.array(SPHERE_CENTER))).sum(-1) / SPHERE_RADIUS, 0.0, 1.0)
    return hit, cos_view


# Bands of the viewing cosine on the sphere: near-normal, middle, grazing (Schlick's
# Fresnel is furthest below the exact one in the middle band).
COS_BANDS = ((0.8, 1.0), (0.5, 0.8), (0.0, 0.5))


def flip_mean(ref, test, mask, path: Path | None = None) -> tuple[float, float]:
    """(mean FLIP over the image, mean FLIP over the sphere's pixels); the colour-mapped
    error map goes to `path`."""
    import flip_evaluator as flip
    import numpy as np

    raw, mean, _ = flip.evaluate(ref, test, "LDR", applyMagma=False)
    raw = np.asarray(raw)
    raw = raw[..., 0] if raw.ndim == 3 else raw
    if path is not None:
        vsm.save_png(np.asarray(flip.evaluate(ref, test, "LDR")[0]), path)
    return float(mean), float(raw[mask].mean())


def run_case(args, dray, case: dict, sphere_plain, sphere_coloured, ground, base_cfg, variant, llvm_env) -> dict:
    import numpy as np

    out = args.out / case["name"]
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    shutil.copy(args.out / "checker.png", out / "checker.png")
    shutil.copy(args.out / "test_texture.png", out / "test_texture.png")
    sphere = sphere_coloured if case.get("colors") else sphere_plain
    tt = case.get("texture")
    gltf = write_gltf(out, case["material"], sphere, ground, tt, texture_in_material=tt is not None)
    mask, cos_view = sphere_mask()
    res = {"name": case["name"], "feature": case["feature"], "mapping": case["mapping"], "differs": case["differs"]}

    # 1. Bit-for-bit checks against the material without the extension.
    checks = []
    for i, (label, ext_name, ext_value, plain) in enumerate(case.get("bits", [])):
        da, db = out / f"bits{i}_a", out / f"bits{i}_b"
        da.mkdir()
        db.mkdir()
        for d in (da, db):
            shutil.copy(out / "checker.png", d / "checker.png")
            shutil.copy(out / "test_texture.png", d / "test_texture.png")
        if ext_value == "white_colors":
            white = dict(sphere, col=np.ones_like(sphere["col"]))
            ga = write_gltf(da, case["material"], white, ground)
            gb = write_gltf(db, plain, sphere_plain, ground)
        elif ext_value == "identity_transform":
            ident = {"offset": [0.0, 0.0], "rotation": 0.0, "scale": [1.0, 1.0]}
            ga = write_gltf(da, case["material"], sphere, ground, ident, texture_in_material=True)
            gb = write_gltf(db, case["material"], sphere, ground, None, texture_in_material=True)
        else:
            ga = write_gltf(da, with_extension(plain, ext_name, ext_value), sphere, ground)
            gb = write_gltf(db, plain, sphere, ground)
        ra = run_dray(args, dray, ga, da, "a", args.bits_spp, args.seed)
        rb = run_dray(args, dray, gb, db, "b", args.bits_spp, args.seed)
        ok = same_pixels(ra["exr"], rb["exr"])
        checks.append({"check": label, "same_bits": ok})
        env.log(f"  bits: {label}: {'same' if ok else 'DIFFERENT'}")
    res["bit_checks"] = checks

    # 2. dray at --spp (runs for timing; the first for FLIP).
    druns = []
    for r in range(args.runs):
        druns.append(run_dray(args, dray, gltf, out, f"run{r}", args.spp, args.seed))
        env.log(f"  dray: render {druns[-1]['render_s']:.2f} s, wall {druns[-1]['wall_s']:.2f} s")
    res["dray"] = {"render_s": statistics.median(x["render_s"] for x in druns),
                   "wall_s": statistics.median(x["wall_s"] for x in druns), "cmd": druns[0]["cmd"],
                   "warnings": druns[0]["warnings"]}
    img_d = vsm.read_exr(druns[0]["exr"])
    ldr_d = vsm.tonemap(img_d)
    vsm.save_png(ldr_d, out / "dray.png")
    if case.get("dray_noise"):  # dray's own noise floor, where it is expected to exceed Mitsuba's
        d2 = run_dray(args, dray, gltf, out, "seed2", args.spp, args.seed + 1000)
        res["flip_dray_vs_dray"], res["flip_dray_vs_dray_sphere"] = flip_mean(
            vsm.tonemap(vsm.read_exr(d2["exr"])), ldr_d, mask)
        env.log(f"  FLIP dray vs dray (other seed): {res['flip_dray_vs_dray']:.4f} (sphere "
                f"{res['flip_dray_vs_dray_sphere']:.4f})")

    # 3. Mitsuba: seed, seed + 1000 (noise floor), then warm timing runs.
    if case.get("mitsuba") is None:
        ref = case["reference"]
        rd = out / "reference"
        rd.mkdir()
        for f in ("checker.png", "test_texture.png"):
            shutil.copy(out / f, rd / f)
        rr = run_dray(args, dray, write_gltf(rd, ref, sphere, ground), rd, "ref", args.spp, args.seed)
        ldr_r = vsm.tonemap(vsm.read_exr(rr["exr"]))
        vsm.save_png(ldr_r, out / "dray_without_feature.png")
        res["flip_effect_vs_without"], res["flip_effect_vs_without_sphere"] = flip_mean(
            ldr_r, ldr_d, mask, out / "flip_with_vs_without.png")
        env.log(f"  FLIP dray with the feature vs without: {res['flip_effect_vs_without']:.4f} (sphere "
                f"{res['flip_effect_vs_without_sphere']:.4f})")
        return res
    cfg = dict(base_cfg, variant=variant, spp=args.spp, bsdf=case["mitsuba"],
               integrator=case.get("integrator", "path"), emitter=case.get("emitter"),
               interior=case.get("interior"), channels_ior=case.get("channels_ior"),
               sphere=base_cfg["sphere_coloured" if case.get("colors") else "sphere"])
    if tt is not None:
        cfg["texture"] = str(args.out / "test_texture.png")
        cfg["texture_matrix"] = texture_matrix(tt)
    runs = [{"seed": args.seed, "save": str(out / "mitsuba_a.npy")},
            {"seed": args.seed + 1000, "save": str(out / "mitsuba_b.npy")}]
    runs += [{"seed": args.seed + 2000 + r} for r in range(args.runs - 1)]
    cfg["runs"] = runs
    m = run_mitsuba(args, cfg, case["name"], llvm_env)
    if not m["ok"]:
        raise RuntimeError(f"mitsuba failed on {case['name']}: {m['error']}")
    warm = m["runs"][1:]
    res["mitsuba"] = {"variant": variant, "render_s": statistics.median(x["render_s"] for x in warm),
                      "total_s": statistics.median(x["total_s"] for x in warm),
                      "cold_total_s": m["runs"][0]["total_s"], "cmd": m["cmd"]}
    img_a, img_b = np.load(out / "mitsuba_a.npy"), np.load(out / "mitsuba_b.npy")
    ldr_a, ldr_b = vsm.tonemap(img_a), vsm.tonemap(img_b)
    vsm.save_png(ldr_a, out / "mitsuba.png")
    res["flip_dray_vs_mitsuba"], res["flip_dray_vs_mitsuba_sphere"] = flip_mean(
        ldr_a, ldr_d, mask, out / "flip_dray_vs_mitsuba.png")
    res["flip_mitsuba_vs_mitsuba"], res["flip_mitsuba_vs_mitsuba_sphere"] = flip_mean(ldr_a, ldr_b, mask)
    # Mean linear radiance over the sphere's pixels (the ground is the same in every case).
    res["mean_ratio_dray_over_mitsuba_rgb"] = (img_d[mask].mean(0) / np.maximum(img_a[mask].mean(0), 1e-9)).tolist()
    res["mean_ratio_mitsuba_seeds_rgb"] = (img_b[mask].mean(0) / np.maximum(img_a[mask].mean(0), 1e-9)).tolist()
    res["mean_ratio_image_rgb"] = (img_d.mean((0, 1)) / np.maximum(img_a.mean((0, 1)), 1e-9)).tolist()
    res["mean_ratio_by_view_cosine"] = {}
    for lo, hi in COS_BANDS:
        band = mask & (cos_view >= lo) & (cos_view <= hi)
        res["mean_ratio_by_view_cosine"][f"{lo}-{hi}"] = (
            img_d[band].mean(0) / np.maximum(img_a[band].mean(0), 1e-9)).tolist()
    for f in out.glob("mitsuba_*.npy"):
        f.unlink()
    env.log(f"  FLIP dray vs mitsuba {res['flip_dray_vs_mitsuba']:.4f} (mitsuba vs mitsuba "
            f"{res['flip_mitsuba_vs_mitsuba']:.4f}); sphere {res['flip_dray_vs_mitsuba_sphere']:.4f} "
            f"({res['flip_mitsuba_vs_mitsuba_sphere']:.4f}); sphere's mean dray/mitsuba "
            + ", ".join(f"{x:.3f}" for x in res["mean_ratio_dray_over_mitsuba_rgb"])
            + f"; mitsuba render {res['mitsuba']['render_s']:.2f} s")
    return res


def main() -> None:
    args = parse_args()
    if args.mitsuba_worker:
        mitsuba_worker(args.mitsuba_worker)
        return
    import numpy as np

    dray = env.dray_binary()
    args.out.mkdir(parents=True, exist_ok=True)
    write_checker(args.out / "checker.png")
    write_test_texture(args.out / "test_texture.png")
    sphere_plain, sphere_col, ground = sphere_mesh(False), sphere_mesh(True), ground_mesh()
    arrays = args.out / "arrays"
    arrays.mkdir(exist_ok=True)
    files: dict = {"sphere": {}, "sphere_coloured": {}, "ground": {}}
    for key, m in (("sphere", sphere_plain), ("sphere_coloured", sphere_col), ("ground", ground)):
        for k, a in m.items():
            p = arrays / f"{key}_{k}.npy"
            np.save(p, a)
            files[key][k] = str(p)
    base_cfg = {"camera": [list(v) for v in camera_frame()], "width": WIDTH, "height": HEIGHT,
                "max_depth": args.max_depth + 1, "rr_depth": MITSUBA_RR_DEPTH, "threads": args.threads,
                "checker": str(args.out / "checker.png"), **files}
    info = env.machine_info()
    info["busy_cores_before_start"] = round(env.idle_check(), 2)
    load = env.OtherLoad()
    info["packages"] = env.package_versions(["mitsuba", "drjit", "flip-evaluator", "numpy"])
    info["dray_binary"] = env.binary_info(dray)
    variant, llvm_env = pick_variant(args, base_cfg)
    env.log(f"mitsuba variant {variant} {llvm_env or ''}")
    results = []
    cases = {c["name"]: c for c in build_cases()}
    for name in args.case_names:
        env.log(f"case {name}: {cases[name]['feature']}")
        results.append(run_case(args, dray, cases[name], sphere_plain, sphere_col, ground, base_cfg, variant,
                                llvm_env))
    shutil.rmtree(args.out / "drjit_home", ignore_errors=True)
    info["variant"] = variant
    env.save_results(args.out / "results.json", info, args, results, load)
    report(info, args, results)


def report(info: dict, args, results: list) -> None:
    print(f"# glTF material features, dray against Mitsuba {info['packages']['mitsuba']} ({info['variant']}), "
          f"{WIDTH}x{HEIGHT}, {args.spp} spp, dray --max-depth {args.max_depth} (Mitsuba max_depth "
          f"{args.max_depth + 1}, rr_depth {MITSUBA_RR_DEPTH}), {args.threads} threads on cores {args.cores}")
    print(f"# {info['cpu_model']}, {info['date']}, dray {info['dray_git']}; other processes used "
          f"{info['other_processes_cores_during_run']:.2f} cores on average; runs {args.runs} (median times)")
    print("# FLIP: mean over the image / over the sphere's pixels; noise = Mitsuba against itself with another "
          "seed; mean = the sphere's mean linear radiance, dray / Mitsuba")
    print("\n| feature | Mitsuba counterpart | FLIP dray vs Mitsuba | FLIP noise floor "
          "| sphere's mean dray/Mitsuba (R, G, B) | dray render (s) | Mitsuba render (s) | bit checks |")
    print("|---|---|---:|---:|---|---:|---:|---|")
    for r in results:
        bits = "; ".join(f"{c['check']}: {'same bits' if c['same_bits'] else 'DIFFERENT'}" for c in r["bit_checks"])
        dnoise = (f" (dray vs dray {r['flip_dray_vs_dray']:.4f} / {r['flip_dray_vs_dray_sphere']:.4f})"
                  if "flip_dray_vs_dray" in r else "")
        if "mitsuba" in r:
            ratio = ", ".join(f"{x:.3f}" for x in r["mean_ratio_dray_over_mitsuba_rgb"])
            print(f"| {r['feature']} | {r['mapping']} | {r['flip_dray_vs_mitsuba']:.4f} / "
                  f"{r['flip_dray_vs_mitsuba_sphere']:.4f} | {r['flip_mitsuba_vs_mitsuba']:.4f} / "
                  f"{r['flip_mitsuba_vs_mitsuba_sphere']:.4f}{dnoise} | {ratio} | {r['dray']['render_s']:.2f} | "
                  f"{r['mitsuba']['render_s']:.2f} | {bits or '-'} |")
        else:
            print(f"| {r['feature']} | {r['mapping']} | n/a (with vs without the feature: "
                  f"{r['flip_effect_vs_without']:.4f} / {r['flip_effect_vs_without_sphere']:.4f}) "
                  f"| | | {r['dray']['render_s']:.2f} | | {bits or '-'} |")
    print()
    for r in results:
        print(f"- {r['name']}: differs: {r['differs']}")
        if "mean_ratio_by_view_cosine" in r:
            print("  sphere's mean dray/Mitsuba by viewing cosine: " + "; ".join(
                f"{band}: " + ", ".join(f"{x:.3f}" for x in v) for band, v in r["mean_ratio_by_view_cosine"].items()))
        for w in r["dray"]["warnings"]:
            print(f"  dray warning: {w}")
    print(f"\noutputs: {args.out}")


if __name__ == "__main__":
    env.ensure_venv()
    main()
