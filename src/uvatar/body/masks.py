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

__all__ = ["PART_NAMES", "REGION_NAMES", "PartMaskConfig", "part_joint_groups", "part_masks", "part_vertex_weights",
           "region_label_map", "region_vertex_labels"]

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


# Regions a viewer judges an avatar by (the face and hands first); every vertex / texel has exactly one.
REGION_NAMES = ("face", "head", "hands", "arms", "torso", "legs", "feet")


def region_vertex_labels(body, config: PartMaskConfig | None = None) -> np.ndarray:
    """(V,) int8 index into :data:`REGION_NAMES` per template vertex: the region whose joints carry the
    most skinning weight there (torso: the weight of every joint not in another region); ``face`` is
    the front of the head as in :func:`part_masks` (rest normal z > ``face_min_forward``, in front of
    the head joint), ``head`` the rest of it (hair, ears, back of the head).

    hands: wrists and below; arms: upper arms and below, hands excluded; feet: ankles and below;
    legs: upper legs and below, feet excluded.
    """
    from uvatar.geometry import vertex_normals

    cfg = config or PartMaskConfig()
    t = body.template
    parents = np.asarray(t.joint_parents)
    sj = body.semantic_joints
    groups = part_joint_groups(body)
    arms = [j for j in subtree(parents, [sj["l_shoulder"], sj["r_shoulder"]]).tolist() if j not in groups["hands"]]
    legs = [j for j in subtree(parents, [sj["l_hip"], sj["r_hip"]]).tolist() if j not in groups["feet"]]
    w = np.asarray(t.skin_weights, dtype=np.float32)
    columns = {"head": groups["head"], "hands": groups["hands"], "arms": arms, "legs": legs, "feet": groups["feet"]}
    weights = {name: w[:, joints].sum(1) for name, joints in columns.items()}
    weights["torso"] = np.clip(1.0 - sum(weights.values()), 0.0, None)
    order = [n for n in REGION_NAMES if n != "face"]
    labels = np.asarray([REGION_NAMES.index(n) for n in order], np.int8)[
        np.argmax(np.stack([weights[n] for n in order], 1), 1)]
    normals = np.asarray(vertex_normals(t.vertices.astype(np.float64), t.faces), dtype=np.float32)
    head_z = float(t.rest_joints[sj["head"], 2])
    face = (labels == REGION_NAMES.index("head")) & (normals[:, 2] > cfg.face_min_forward) & (
        t.vertices[:, 2] - head_z > 0.0)
    labels[face] = REGION_NAMES.index("face")
    return labels


def region_label_map(body, resolution: int, config: PartMaskConfig | None = None) -> np.ndarray:
    """(R, R) int8 region index per texel in the body's UV layout (row 0 is v = 1), -1 outside the
    charts: each texel takes the region of its triangle's corner with the largest barycentric weight."""
    from uvatar.geometry import rasterize_uv

    t = body.template
    raster = rasterize_uv(t.uvs, t.uv_faces, resolution)
    labels = region_vertex_labels(body, config)
    out = np.full((resolution, resolution), -1, np.int8)
    m = raster.mask
    corner = np.argmax(np.asarray(raster.bary)[m], axis=-1)
    out[m] = labels[np.asarray(t.faces)[np.asarray(raster.face_index)[m], corner]]
    return out
