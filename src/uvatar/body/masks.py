"""Per-texel body-part masks in UV space, from the skinning weights of each part's joints.

A texel belongs to a part when the part's joints together carry more than ``threshold`` of the
skinning weight there (weights interpolated barycentrically from the vertices):

- ``hands``: the wrists and every joint below them (palm and fingers)
- ``feet``: the ankles and every joint below them
- ``head``: the head joint and every joint below it (eyes, jaw)
- ``fingers_toes``: the joints below the wrists and ankles, metacarpals (palm bones) excluded
- ``face``: head texels on the front of the head: rest-pose normal within ~60 degrees of +Z and
  the rest position in front of the head joint

So ``fingers_toes`` lies inside ``hands | feet``, ``face`` inside ``head``, and hands, feet and
head are disjoint. Masks follow the UV image convention: (R, R) bool, row 0 is v = 1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uvatar.body.kinematics import subtree

__all__ = ["PART_NAMES", "PartMaskConfig", "part_joint_groups", "part_vertex_weights", "part_masks"]

PART_NAMES = ("hands", "feet", "face", "head", "fingers_toes")


@dataclass
class PartMaskConfig:
    """threshold: part weight above which a texel belongs to the part; face_min_forward: minimum
    rest-normal z component of a face texel (cos of the largest angle to +Z)."""

    threshold: float = 0.5
    face_min_forward: float = 0.5


def part_joint_groups(body) -> dict[str, list[int]]:
    """Joint indices of each part ("hands", "feet", "head", "fingers_toes") from semantic joints."""
    t = body.template
    parents = np.asarray(t.joint_parents)
    sj = body.semantic_joints
    wrists = [sj["l_wrist"], sj["r_wrist"]]
    ankles = [sj["l_ankle"], sj["r_ankle"]]
    hands = subtree(parents, wrists).tolist()
    feet = subtree(parents, ankles).tolist()
    digits = [j for j in hands + feet if j not in wrists + ankles and "metacarpal" not in t.joint_names[j]]
    return {"hands": hands, "feet": feet, "head": subtree(parents, sj["head"]).tolist(), "fingers_toes": digits}


def part_vertex_weights(body) -> dict[str, np.ndarray]:
    """(V,) float32 skinning weight of each part's joints at each vertex (0..1)."""
    w = np.asarray(body.template.skin_weights, dtype=np.float32)
    return {name: w[:, joints].sum(1) for name, joints in part_joint_groups(body).items()}


def part_masks(body, resolution: int, config: PartMaskConfig | None = None) -> dict[str, np.ndarray]:
    """Per-texel part masks in the body's UV layout: {name: (R, R) bool} for :data:`PART_NAMES`."""
    from uvatar.geometry import rasterize_uv, sample_vertex_attribute, vertex_normals

    cfg = config or PartMaskConfig()
    t = body.template
    raster = rasterize_uv(t.uvs, t.uv_faces, resolution)
    weights = part_vertex_weights(body)
    names = ["hands", "feet", "head", "fingers_toes"]
    normals = np.asarray(vertex_normals(t.vertices.astype(np.float64), t.faces), dtype=np.float32)
    head_z = float(t.rest_joints[body.semantic_joints["head"], 2])
    attr = np.stack([weights[n] for n in names] + [normals[:, 2], t.vertices[:, 2] - head_z], -1)
    # texel values interpolate the vertices of the triangle's 3D corners (faces, not uv_faces)
    texels = np.asarray(sample_vertex_attribute(raster, t.faces, attr.astype(np.float32)))
    valid = raster.mask
    masks = {n: valid & (texels[..., k] > cfg.threshold) for k, n in enumerate(names)}
    masks["face"] = masks["head"] & (texels[..., 4] > cfg.face_min_forward) & (texels[..., 5] > 0.0)
    return {n: masks[n] for n in PART_NAMES}
