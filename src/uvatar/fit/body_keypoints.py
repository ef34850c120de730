"""Where each BlazePose landmark lies on a body model: ``BodyKeypoints(body)(posed) -> (B, K, 3)``.

Every keypoint is a fixed linear blend of posed vertices and posed joint positions,
``X_k = sum_v A[k, v] V_v + sum_j G[k, j] J_j``, so it moves with the body and is differentiable.

anny (the default body): the COCO-WholeBody names (nose, eyes, ears, shoulders, elbows, wrists,
hips, knees, ankles, heels, toes) come from anny's own keypoint regressor (``anny/data/keypoints/
coco.pth``, per base-mesh vertex weights; uvatar's anny vertices are anny's ``template_vertices`` in
the same order, so the weights are read through ``base_mesh_vertex_indices`` exactly as
``anny.keypoints`` does). That regressor was made for detector keypoints, so its hips sit where a
detector puts them (lower and wider than the anatomical hip joint centres), which a joint mapping
would bias by centimetres. ``foot_index`` blends big and small toe (BlazePose's foot tip lies
between them); eye corners and mouth corners are the template vertices nearest to fixed offsets
from the regressed eyes / nose (rest pose); pinky / index / thumb are finger joints (pinky and index
knuckle, thumb IP joint).

Any other body (SMPL, SMPL-X): a generic fallback from ``semantic_joints`` (shoulders, elbows,
wrists, hips, knees, ankles) and rest-template vertices chosen relative to them (nose, ears, eyes,
mouth, heels, toe tips, hand). Keypoints the body cannot place get weight 0 in ``weights``; finger
keypoints get a reduced weight because body fits keep the fingers at rest.
"""

from __future__ import annotations

import numpy as np
import torch

from uvatar.body.base import BodyModel, PosedBody

try:  # the detector half owns the names; keep a copy until both halves are merged
    from uvatar.fit.keypoints import BLAZEPOSE_NAMES
except ImportError:  # pragma: no cover - depends on the merge state
    BLAZEPOSE_NAMES = (
        "nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye",
        "right_eye_outer", "left_ear", "right_ear", "mouth_left", "mouth_right", "left_shoulder",
        "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_pinky",
        "right_pinky", "left_index", "right_index", "left_thumb", "right_thumb", "left_hip", "right_hip",
        "left_knee", "right_knee", "left_ankle", "right_ankle", "left_heel", "right_heel",
        "left_foot_index", "right_foot_index")

__all__ = ["BLAZEPOSE_NAMES", "BodyKeypoints", "FINGER_WEIGHT"]

PRUNE = 1e-3
FINGER_WEIGHT = 0.3   # body fits keep the fingers at rest: their landmarks only steer the wrist
_SIDES = (("left", "L", "l", 1.0), ("right", "R", "r", -1.0))  # uvatar: the body's left is +X


def _nearest_vertex(vertices: np.ndarray, target, candidates: np.ndarray | None = None) -> int:
    idx = np.arange(len(vertices)) if candidates is None or not len(candidates) else candidates
    return int(idx[np.argmin(np.linalg.norm(vertices[idx] - np.asarray(target), axis=1))])


class BodyKeypoints(torch.nn.Module):
    """Keypoints ``names`` on ``body``. ``weights`` (K,) float32: 0 where the body cannot place one.

    ``use_regressor``: for anny, use its COCO regressor (default); False forces the generic fallback.
    Call with a :class:`PosedBody` of that body -> (B, K, 3) world positions (zeros where weight 0).
    """

    def __init__(self, body: BodyModel, names=BLAZEPOSE_NAMES, use_regressor: bool = True):
        super().__init__()
        self.names = tuple(names)
        K, V, J = len(self.names), body.template.num_vertices, body.num_joints
        self._A = np.zeros((K, V))
        self._G = np.zeros((K, J))
        self.weights = np.zeros(K, dtype=np.float32)
        self.source = ["none"] * K
        coco = _anny_coco(body) if use_regressor and body.name == "anny" else None
        self._place(body, coco)
        # drop regressor weights below 0.1% of a keypoint's largest (~0.1 mm change; 1.4k instead of
        # 8.8k support vertices for anny), so a fit needs to skin only a few vertices
        keep = self._A >= PRUNE * self._A.max(1, keepdims=True)
        pruned = np.where(keep & (self._A > 0), self._A, 0.0)
        sums = pruned.sum(1, keepdims=True)
        self._A = np.where(sums > 0, pruned / np.maximum(sums, 1e-12), 0.0)
        self.support = np.flatnonzero((self._A > 0).any(0))
        self.register_buffer("vertex_weights", torch.as_tensor(self._A, dtype=torch.float32), persistent=False)
        self.register_buffer("joint_weights", torch.as_tensor(self._G, dtype=torch.float32), persistent=False)
        self.to(body.device)

    # -- building --------------------------------------------------------------------------------
    def _set(self, name, *, vertex=None, joint=None, blend=None, weight=1.0, source=""):
        if name not in self.names:
            return
        k = self.names.index(name)
        if blend is not None:
            self._A[k] = blend
        elif vertex is not None:
            self._A[k, vertex] = 1.0
        elif joint is not None:
            self._G[k, joint] = 1.0
        else:
            return
        self.weights[k] = weight
        self.source[k] = source

    def _place(self, body: BodyModel, coco: dict[str, np.ndarray] | None) -> None:
        t = body.template
        rest = t.vertices.astype(np.float64)
        joints = {n: i for i, n in enumerate(t.joint_names)}
        rj = t.rest_joints.astype(np.float64)

        def rest_point(name):  # rest-pose position of a placed keypoint
            k = self.names.index(name)
            return self._A[k] @ rest + self._G[k] @ rj

        if coco is not None:
            for name, w in coco.items():
                if name in ("left_big_toe", "right_big_toe", "left_small_toe", "right_small_toe"):
                    continue
                self._set(name, blend=w, source="anny-coco")
            for side, *_ in _SIDES:
                toe = 0.7 * coco[f"{side}_big_toe"] + 0.3 * coco[f"{side}_small_toe"]
                self._set(f"{side}_foot_index", blend=toe, source="anny-coco")
        else:
            self._generic_core(body, rest, rj)
        # head details relative to the (regressed or generic) eyes and nose, on the rest surface
        head = self._region(body, ("head", "neck"))
        for side, _, _, sx in _SIDES:
            eye = f"{side}_eye"
            if eye in self.names and self.weights[self.names.index(eye)] > 0:
                e = rest_point(eye)
                self._set(f"{side}_eye_inner", vertex=_nearest_vertex(rest, e - [sx * 0.016, 0, 0], head),
                          source="template")
                self._set(f"{side}_eye_outer", vertex=_nearest_vertex(rest, e + [sx * 0.016, 0, -0.004], head),
                          source="template")
            if "nose" in self.names and self.weights[self.names.index("nose")] > 0:
                n = rest_point("nose")
                self._set(f"mouth_{side}", vertex=_nearest_vertex(rest, n + [sx * 0.024, -0.045, -0.01], head),
                          source="template")
        # hands: finger joints where the rig has them, else the hand end of the wrist
        for side, s, _, _ in _SIDES:
            for name, bone, smpl in (("pinky", "finger5-1", "pinky1"), ("index", "finger2-1", "index1"),
                                     ("thumb", "finger1-3", "thumb3")):
                j = joints.get(f"{bone}.{s}", joints.get(f"{side}_{smpl}"))
                if j is not None:
                    self._set(f"{side}_{name}", joint=j, weight=FINGER_WEIGHT, source="joint")
                elif f"{side}_hand" in joints:
                    self._set(f"{side}_{name}", joint=joints[f"{side}_hand"], weight=0.5 * FINGER_WEIGHT,
                              source="joint")

    def _region(self, body: BodyModel, semantic: tuple[str, ...]) -> np.ndarray:
        """Template vertices mostly skinned to the named semantic joints or their descendants."""
        from uvatar.avh.bake.refine import subtree_weights

        t = body.template
        ids = [body.semantic_joints[n] for n in semantic if n in body.semantic_joints]
        if not ids:
            return np.arange(t.num_vertices)
        w = subtree_weights(t.skin_weights, t.joint_parents, ids[:1])[:, 0]
        return np.flatnonzero(w > 0.5)

    def _generic_core(self, body: BodyModel, rest: np.ndarray, rj: np.ndarray) -> None:
        """Fallback from semantic joints and template vertices (any BodyModel)."""
        sem = body.semantic_joints
        for side, _, s, _ in _SIDES:
            for name, key in (("shoulder", "shoulder"), ("elbow", "elbow"), ("wrist", "wrist"),
                              ("knee", "knee"), ("ankle", "ankle")):
                if f"{s}_{key}" in sem:
                    self._set(f"{side}_{name}", joint=sem[f"{s}_{key}"], source="joint")
            if f"{s}_hip" in sem:  # anatomical hip centre: detector hips lie a little off it
                self._set(f"{side}_hip", joint=sem[f"{s}_hip"], weight=0.5, source="joint")
            if f"{s}_ankle" in sem:
                a = rj[sem[f"{s}_ankle"]]
                foot = self._region(body, (f"{s}_ankle",))
                low = foot[rest[foot, 1] < a[1] - 0.03] if len(foot) else foot
                if len(low):
                    self._set(f"{side}_heel", vertex=int(low[np.argmin(rest[low, 2])]), source="template")
                    self._set(f"{side}_foot_index", vertex=int(low[np.argmax(rest[low, 2])]), source="template")
            if f"{s}_eye" in sem:
                self._set(f"{side}_eye", joint=sem[f"{s}_eye"], source="joint")
        head = self._region(body, ("head",))
        if "head" in sem and len(head):
            h = rj[sem["head"]]
            face = head[rest[head, 1] > h[1]]
            if len(face):  # the nose tip is the most frontal point of the head above its joint
                n = rest[face[np.argmax(rest[face, 2])]]
                self._set("nose", vertex=int(face[np.argmax(rest[face, 2])]), source="template")
                band = face[np.abs(rest[face, 1] - n[1]) < 0.02]
                for side, _, _, sx in _SIDES:
                    self._set(f"{side}_ear", vertex=int(band[np.argmax(sx * rest[band, 0])]), source="template")
                    if f"{side}_eye" not in self.names or self.weights[self.names.index(f"{side}_eye")] == 0:
                        self._set(f"{side}_eye", vertex=_nearest_vertex(rest, n + [sx * 0.032, 0.03, -0.02], head),
                                  source="template")

    # -- evaluation ------------------------------------------------------------------------------
    def forward(self, posed: PosedBody) -> torch.Tensor:
        """(B, K, 3) world keypoints of ``posed`` (differentiable)."""
        return self.blend(posed.vertices[:, self.support], self.support, posed.joints)

    def blend(self, vertices: torch.Tensor, ids, joints: torch.Tensor) -> torch.Tensor:
        """Keypoints from some posed vertices: vertices (B, N, 3) are template vertices ``ids`` (N,)
        (they must include ``support``), joints (B, J, 3) -> (B, K, 3)."""
        A = self.vertex_weights[:, torch.as_tensor(ids, device=self.vertex_weights.device)].to(vertices)
        out = torch.einsum("kv,bvc->bkc", A, vertices)
        return out + torch.einsum("kj,bjc->bkc", self.joint_weights.to(vertices), joints.to(vertices))


def _anny_coco(body) -> dict[str, np.ndarray]:
    """anny's COCO regressor weights per uvatar vertex (V,) for each of its labels."""
    from pathlib import Path

    import anny

    model = body.anny
    path = Path(anny.__file__).parent / "data" / "keypoints" / "coco.pth"
    data = torch.load(path, weights_only=True, map_location="cpu")
    index = model.base_mesh_vertex_indices.cpu()
    if len(index) != body.template.num_vertices:
        raise ValueError(f"anny keypoint regressor: {len(index)} base-mesh vertices, body has "
                         f"{body.template.num_vertices}")
    return {name: w[index].double().numpy() for name, w in data.items()}
