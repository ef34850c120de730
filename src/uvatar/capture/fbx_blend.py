"""FBX blend shapes (morph targets) and their evaluation: how a tracked take -- one mesh whose vertices
move, one topology -- is stored in an FBX scene that engines import (a shape a frame, or in-between
shapes of one channel, keyed by ``DeformPercent``).

Layout (FBX 7): a mesh ``Geometry`` ← ``Deformer`` of class ``BlendShape`` ← ``Deformer`` (``SubDeformer``)
of class ``BlendShapeChannel`` ← ``Geometry`` of class ``Shape`` (``Indexes``: the control points it
moves; ``Vertices``: their offsets, in the mesh's units). A channel's weight is its ``DeformPercent``
(0-100, animated by an ``AnimationCurveNode::DeformPercent``); its shapes apply fully at their
``FullWeights`` (percent; one shape: 100). At weight w a channel adds ``w / F0 · S0`` below its first
full weight, the linear blend of the two shapes around w between them, and the last two's line
extended above the last (one shape: ``w / 100 · S``) -- the FBX SDK's in-between blending. Blender
writes ``FullWeights`` as a weight an offset of a channel's one shape (its vertex group); those scale
the offsets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uvatar.capture.fbx_anim import FbxCurve
from uvatar.errors import InputError

__all__ = ["BlendChannel", "blend_channels", "blend_offsets"]


@dataclass
class BlendChannel:
    """One channel of a mesh's blend shapes: ``name``; ``full_weights`` (S,) percent, ascending; ``shapes``
    [(indexes (k,) int64, offsets (k, 3) float64)] in that order; ``weight`` its DeformPercent curve."""

    name: str
    full_weights: np.ndarray
    shapes: list
    weight: FbxCurve

    def offsets(self, percent: float, n_points: int) -> np.ndarray:
        """(n_points, 3) the channel's offsets at weight ``percent`` (module doc)."""
        out = np.zeros((n_points, 3))
        fw = self.full_weights
        if percent == 0 or not len(fw):
            return out
        if len(fw) == 1 or percent <= fw[0]:
            terms = [(0, percent / fw[0])]
        else:                                               # between two shapes, or past the last two's line
            k = min(int(np.searchsorted(fw, percent)), len(fw) - 1)
            a = (percent - fw[k - 1]) / (fw[k] - fw[k - 1])
            terms = [(k - 1, 1.0 - a), (k, a)]
        for s, w in terms:
            indexes, deltas = self.shapes[s]
            np.add.at(out, indexes, w * deltas)
        return out


def _class(node) -> str:
    return node.props[2] if len(node.props) > 2 and isinstance(node.props[2], str) else ""


def _name(node) -> str:
    name = node.props[1] if len(node.props) > 1 and isinstance(node.props[1], str) else "?"
    return name.split("::", 1)[-1].split("\x00")[0]


def _children(scene, parent, name: str, kind: str) -> list:
    out = []
    for child, _ in scene.children_of.get(parent, []):
        node = scene.objects.get(child)
        if node is not None and node.name == name and _class(node) == kind:
            out.append((child, node))
    return out


def blend_channels(scene, geometry_id, n_points: int, anim: dict) -> list[BlendChannel]:
    """The blend-shape channels deforming the mesh geometry ``geometry_id`` (of ``n_points`` control
    points); ``anim``: :func:`uvatar.capture.fbx_anim.animated_properties`. InputError naming the file for
    a shape whose indexes or offsets do not fit the mesh."""
    channels = []
    for deformer, _ in _children(scene, geometry_id, "Deformer", "BlendShape"):
        for channel_id, channel in _children(scene, deformer, "Deformer", "BlendShapeChannel"):
            shapes = []
            for _, shape in _children(scene, channel_id, "Geometry", "Shape"):
                indexes = shape.array("Indexes", np.int64)
                deltas = shape.array("Vertices", np.float64)
                if indexes is None or deltas is None or len(deltas) != 3 * len(indexes):
                    raise InputError(scene.path, f"FBX blend shape {_name(shape)}: {0 if deltas is None else len(deltas)} "
                                                 f"offset values for {0 if indexes is None else len(indexes)} indexes")
                if len(indexes) and (indexes.min() < 0 or indexes.max() >= n_points):
                    raise InputError(scene.path, f"FBX blend shape {_name(shape)} moves a point past the mesh's "
                                                 f"{n_points}")
                shapes.append((indexes, deltas.reshape(-1, 3)))
            if not shapes:
                continue
            full = channel.array("FullWeights", np.float64)
            if full is not None and len(shapes) == 1 and len(full) == len(shapes[0][0]) != 1:
                # Blender writes a weight an offset here (its vertex group), not a full weight a shape
                shapes = [(shapes[0][0], shapes[0][1] * (full[:, None] / 100.0))]
                full = None
            if full is None or len(full) != len(shapes):
                full = 100.0 * np.arange(1, len(shapes) + 1) / len(shapes)
            order = np.argsort(full, kind="stable")
            if np.any(np.diff(full[order]) <= 0) or full[order][0] <= 0:
                raise InputError(scene.path, f"FBX blend channel {_name(channel)}: FullWeights {full.tolist()} are "
                                             "not distinct positive percentages")
            curves = anim.get((channel_id, "DeformPercent"), {})
            if "DeformPercent" in curves:
                weight = curves["DeformPercent"]
            else:
                p = channel.properties70()
                weight = FbxCurve.constant(float(p["DeformPercent"][0]) if p.get("DeformPercent")
                                           else float(channel.value("DeformPercent", 0.0)))
            channels.append(BlendChannel(_name(channel), full[order], [shapes[i] for i in order], weight))
    return channels


def blend_offsets(channels: list[BlendChannel], weights: np.ndarray, n_points: int) -> np.ndarray:
    """(n_points, 3) the channels' offsets summed at ``weights`` (C,) percent."""
    out = np.zeros((n_points, 3))
    for channel, w in zip(channels, weights, strict=True):
        if w:
            out += channel.offsets(float(w), n_points)
    return out
