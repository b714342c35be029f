"""Relightable maps for other tools: glTF 2.0 and MaterialX (``params/<model>.gltf``,
``params/<model>.mtlx`` and their PNG textures beside them).

- glTF 2.0: one textured quad the size of the surface (metres; the surface frame's x
  right, y up, the quad facing +z), with the core metallic-roughness material:
  ``<stem>_baseColor.png`` (sRGB), ``<stem>_metallicRoughness.png`` (linear: roughness
  in G, metallic in B, as the specification has it) and a flat ``<stem>_normal.png``;
  geometry in one buffer embedded as a data URI. Texture row 0 is the surface's top
  edge, as in the EXRs (glTF's uv origin is the image's top-left corner).
- MaterialX: a ``standard_surface`` (base 1, base_color, metalness and
  specular_roughness from ``<stem>_baseColor.png``, ``<stem>_metallic.png`` and
  ``<stem>_roughness.png``) and its ``surfacematerial``; standard_surface's roughness is
  perceptual (alpha = roughness^2), as glTF's.

Every file goes through a temporary name; the ``.gltf`` and ``.mtlx`` last, once the
textures they name are in place.
"""

from __future__ import annotations

import base64
import json
from pathlib import Path

import numpy as np

from .common import software
from .images import write_image_atomic

__all__ = ["GLTF_TEXTURES", "srgb_encode", "write_gltf", "write_materialx"]

GLTF_TEXTURES = ("baseColor", "metallicRoughness", "normal")


def srgb_encode(x: np.ndarray) -> np.ndarray:
    """Linear [0, 1] -> 8-bit sRGB (IEC 61966-2-1)."""
    x = np.clip(np.asarray(x, float), 0, 1)
    y = np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
    return np.round(255 * y).astype(np.uint8)


def _u8(x: np.ndarray) -> np.ndarray:
    return np.round(255 * np.clip(np.asarray(x, float), 0, 1)).astype(np.uint8)


def _textures(path: Path, base_color: np.ndarray, metallic: np.ndarray,
              roughness: np.ndarray) -> dict[str, str]:
    """Write the PNG textures of both formats beside ``path``; their file names."""
    stem = path.stem
    T, S = metallic.shape
    zero = np.zeros((T, S), np.uint8)
    planes = {
        "baseColor": srgb_encode(base_color),
        "metallicRoughness": np.stack([zero, _u8(roughness), _u8(metallic)], -1),
        "normal": np.broadcast_to(np.array([128, 128, 255], np.uint8), (T, S, 3)),
        "metallic": np.repeat(_u8(metallic)[..., None], 3, -1),
        "roughness": np.repeat(_u8(roughness)[..., None], 3, -1),
    }
    names = {}
    for key, img in planes.items():
        names[key] = f"{stem}_{key}.png"
        write_image_atomic(path.with_name(names[key]), img)
    return names


def _write_text(path: Path, text: str) -> Path:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    tmp.replace(path)
    return path


def write_gltf(path: str | Path, base_color: np.ndarray, metallic: np.ndarray,
               roughness: np.ndarray, width_mm: float, height_mm: float,
               extras: dict | None = None) -> Path:
    """Write a glTF 2.0 quad with the metallic-roughness material.

    Parameters
    ----------
    base_color : (T, S, 3) linear [0, 1]; metallic, roughness : (T, S) in [0, 1];
    width_mm, height_mm : the surface's size; extras : JSON-able facts for the
        material's ``extras`` (where the scale came from, the model...).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    names = _textures(path, base_color, metallic, roughness)
    w, h = width_mm / 1000.0, height_mm / 1000.0
    pos = np.array([[0, h, 0], [w, h, 0], [0, 0, 0], [w, 0, 0]], np.float32)
    nrm = np.tile(np.array([0, 0, 1], np.float32), (4, 1))
    uv = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], np.float32)
    idx = np.array([0, 2, 1, 1, 2, 3], np.uint16)
    blobs = [pos.tobytes(), nrm.tobytes(), uv.tobytes(), idx.tobytes()]
    offsets = np.cumsum([0] + [len(b) for b in blobs])
    data = b"".join(blobs)
    views = [{"buffer": 0, "byteOffset": int(offsets[i]), "byteLength": len(b),
              "target": 34963 if i == 3 else 34962} for i, b in enumerate(blobs)]
    accessors = [
        {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
         "min": pos.min(0).tolist(), "max": pos.max(0).tolist()},
        {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC3"},
        {"bufferView": 2, "componentType": 5126, "count": 4, "type": "VEC2"},
        {"bufferView": 3, "componentType": 5123, "count": 6, "type": "SCALAR"},
    ]
    doc = {
        "asset": {"version": "2.0", "generator": software()},
        "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "surface"}],
        "meshes": [{"name": "surface", "primitives": [{
            "attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2}, "indices": 3,
            "material": 0}]}],
        "materials": [{"name": "parammap", "pbrMetallicRoughness": {
            "baseColorTexture": {"index": 0}, "metallicRoughnessTexture": {"index": 1},
            "baseColorFactor": [1, 1, 1, 1], "metallicFactor": 1.0, "roughnessFactor": 1.0},
            "normalTexture": {"index": 2}, "extras": extras or {}}],
        "textures": [{"source": i, "sampler": 0} for i in range(len(GLTF_TEXTURES))],
        "images": [{"uri": names[k]} for k in GLTF_TEXTURES],
        "samplers": [{"magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071}],
        "buffers": [{"byteLength": len(data), "uri": "data:application/octet-stream;base64,"
                     + base64.b64encode(data).decode("ascii")}],
        "bufferViews": views, "accessors": accessors,
    }
    return _write_text(path, json.dumps(doc, indent=1))


def write_materialx(path: str | Path, base_color: np.ndarray, metallic: np.ndarray,
                    roughness: np.ndarray) -> Path:
    """Write a MaterialX document (``standard_surface``) with its PNG textures."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    names = _textures(path, base_color, metallic, roughness)
    text = f"""<?xml version="1.0"?>
<materialx version="1.39">
  <!-- written by {software()} -->
  <image name="base_color_tex" type="color3">
    <input name="file" type="filename" value="{names['baseColor']}" colorspace="srgb_texture" />
  </image>
  <image name="metalness_tex" type="float">
    <input name="file" type="filename" value="{names['metallic']}" />
  </image>
  <image name="roughness_tex" type="float">
    <input name="file" type="filename" value="{names['roughness']}" />
  </image>
  <standard_surface name="parammap_surface" type="surfaceshader">
    <input name="base" type="float" value="1.0" />
    <input name="base_color" type="color3" nodename="base_color_tex" />
    <input name="metalness" type="float" nodename="metalness_tex" />
    <input name="specular" type="float" value="1.0" />
    <input name="specular_roughness" type="float" nodename="roughness_tex" />
  </standard_surface>
  <surfacematerial name="parammap" type="material">
    <input name="surfaceshader" type="surfaceshader" nodename="parammap_surface" />
  </surfacematerial>
</materialx>
"""
    return _write_text(path, text)
