"""Engine-ready avatar bundle: a skinned GLB of the body plus a manifest for the ONNX generator.

``uvatar export RUN OUT`` writes ``OUT/model.onnx`` (the generator) and ``OUT/avatar.json`` and then
calls :func:`write_engine_bundle`, which adds:

``avatar.glb``
    the body template in its rest pose (the avatar's shape) subdivided with midpoints
    (``config.subdivisions`` times) so the displacement map has vertices to move; one glTF vertex per
    (vertex, UV) pair (seams split); ``TEXCOORD_0`` the texture UV, ``TEXCOORD_1`` one *canonical* UV
    per geometric vertex, shared by all its seam copies, at which the displacement is sampled (so the
    surface never cracks along a seam); joints (node hierarchy with the rest orientation of each joint
    frame), inverse bind matrices, skin weights (at most 4 influences, renormalized); a material whose
    base colour is the mean texture (the generator at the rest pose).
``avatar.fbx``
    the same skinned body as binary FBX (joints as LimbNodes with the same frames, a skin cluster a
    joint, the mean texture embedded, the displacement UVs as a second UV set ``displacement``), for
    engines and tools that take rigs as FBX (:mod:`uvatar.avh.exporters.fbx`).
``manifest.json``
    what a runtime needs to drive the generator: joint order, pose encoding, ONNX input/output names,
    texel resolution, displacement scale and space, the finger/toe mask PNG.
``finger_toe_mask.png``
    (R, R) 0/255, row 0 is v = 1; 255 where displacement is suppressed (fingers and toes).

glTF has no displacement map; ``docs/viewer.md`` says how the viewer applies it (sampled at
``TEXCOORD_1``; rest-frame maps are added to the rest vertex before skinning, body-frame maps after
skinning in the skinned mesh's model space; ``manifest.json`` ``displacement.frame``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from uvatar.avh.avatar_file import avatar_body, read_avatar_json
from uvatar.avh.displacement_frame import frame_of_space
from uvatar.avh.exporters.glb import SkinnedMesh, local_joint_transforms, write_glb
from uvatar.body.base import BodyTemplate
from uvatar.errors import InputError
from uvatar.geometry.frames import vertex_normals
from uvatar.io_utils import encode_image, read_npz, write_image, write_json

MANIFEST_FORMAT = "uvatar-engine/1"
DEFAULT_SPACE = "body frame: world axes of the posed body with the global rotation Rh removed"
#: How a runtime applies the map D for each displacement frame (:mod:`uvatar.avh.displacement_frame`).
APPLIED = {"rest": "before skinning: p = skinned(p_rest + scale * mask * D(TEXCOORD_1))",
           "body": "after skinning: p = skinned(p_rest) + scale * mask * D(TEXCOORD_1)"}


@dataclass(frozen=True)
class EngineExportConfig:
    """subdivisions: midpoint subdivision levels of the template (each ×4 triangles; 1 keeps the GLB
    ~4 MB for anny); max_influences: skin influences kept per vertex (glTF JOINTS_0 holds 4);
    fbx_name: the same skinned body as FBX beside the GLB (:mod:`uvatar.avh.exporters.fbx`; None: none)."""

    subdivisions: int = 1
    max_influences: int = 4
    glb_name: str = "avatar.glb"
    fbx_name: str | None = "avatar.fbx"
    manifest_name: str = "manifest.json"
    mask_name: str = "finger_toe_mask.png"


# ----------------------------------------------------------------------------------------------- mesh
def joint_frames(body: BodyTemplate) -> np.ndarray:
    """(J, 4, 4) rest world transforms of the joint frames: ``body.joint_world_rest``, else axis-aligned
    frames at ``body.rest_joints``."""
    if body.joint_world_rest is not None:
        return np.asarray(body.joint_world_rest, np.float64)
    world = np.tile(np.eye(4), (len(body.joint_names), 1, 1))
    world[:, :3, 3] = body.rest_joints
    return world


def subdivide_with_weights(body: BodyTemplate, levels: int) -> BodyTemplate:
    """Midpoint-subdivide ``levels`` times (``uvatar.geometry.subdivide``); skin weights follow the
    vertices linearly (a new vertex gets the mean weights of its edge's ends), renormalized."""
    from uvatar.geometry import subdivide

    v, f, uv, uvf, origin = subdivide(body.vertices, body.faces, body.uvs, body.uv_faces, levels, "midpoint")
    weights = np.asarray(origin.vertex_matrix @ body.skin_weights.astype(np.float64))
    weights /= np.maximum(weights.sum(axis=1, keepdims=True), 1e-12)
    return replace(body, vertices=np.asarray(v, np.float32), faces=np.asarray(f, np.int64),
                   uvs=np.asarray(uv, np.float32), uv_faces=np.asarray(uvf, np.int64),
                   skin_weights=weights.astype(np.float32))


def top_influences(weights: np.ndarray, k: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """(V, J) weights -> (V, k) joint indices and (V, k) weights, the k largest, renormalized to sum 1."""
    k_eff = min(k, weights.shape[1])
    idx = np.argpartition(-weights, k_eff - 1, axis=1)[:, :k_eff]
    w = np.take_along_axis(weights, idx, axis=1).clip(min=0)
    order = np.argsort(-w, axis=1)
    idx, w = np.take_along_axis(idx, order, 1), np.take_along_axis(w, order, 1)
    total = w.sum(axis=1, keepdims=True)
    w = np.where(total > 0, w / np.where(total > 0, total, 1), np.eye(1, k_eff)[0])
    if k_eff < k:
        idx = np.pad(idx, ((0, 0), (0, k - k_eff)))
        w = np.pad(w, ((0, 0), (0, k - k_eff)))
    w = np.where(w > 0, w, 0)
    return idx.astype(np.int64), w.astype(np.float32)


def _to_gltf_uv(uv: np.ndarray) -> np.ndarray:
    """(N, 2) v-up UVs -> glTF texture coordinates (origin at the image's top-left): (u, 1 - v)."""
    return np.stack([uv[:, 0], 1.0 - uv[:, 1]], 1).astype(np.float32)


def engine_mesh(body: BodyTemplate, config: EngineExportConfig = EngineExportConfig(),
                texture_png: bytes | None = None) -> SkinnedMesh:
    """Subdivide, split seams into one vertex per (vertex, UV) pair, and pack glTF arrays."""
    if config.subdivisions > 0:
        body = subdivide_with_weights(body, config.subdivisions)
    pairs = np.stack([body.faces.reshape(-1), body.uv_faces.reshape(-1)], axis=1)
    unique, inverse = np.unique(pairs, axis=0, return_inverse=True)
    vid, uid = unique[:, 0], unique[:, 1]
    first_uv = np.full(len(body.vertices), -1, np.int64)
    present, first = np.unique(vid, return_index=True)  # pairs are sorted: first = smallest UV index
    first_uv[present] = uid[first]
    joints, weights = top_influences(body.skin_weights[vid], config.max_influences)
    return SkinnedMesh(
        positions=body.vertices[vid].astype(np.float32),
        normals=vertex_normals(body.vertices.astype(np.float64), body.faces)[vid].astype(np.float32),
        uv0=_to_gltf_uv(body.uvs[uid]), uv1=_to_gltf_uv(body.uvs[first_uv[vid]]),
        joints=joints, weights=weights, indices=inverse.reshape(-1, 3).astype(np.uint32),
        joint_names=tuple(body.joint_names), joint_parents=np.asarray(body.joint_parents, np.int64),
        joint_world_rest=joint_frames(body), texture_png=texture_png,
    )


def posed_joint_transforms(joint_world_rest: np.ndarray, joint_parents: np.ndarray,
                           local_rotmats: np.ndarray) -> np.ndarray:
    """World transforms (J, 4, 4) of the joint frames for local rotations (J, 3, 3), glTF semantics:
    ``world_j = world_parent @ rest_local_j @ [R_j | 0]`` -- the viewer sets each bone's quaternion to
    ``rest_quaternion * quat(rotvec)``. Matches ``BodyModel.pose(...).joint_transforms`` (tested).
    The chain is :func:`uvatar.body.kinematics.forward_kinematics` with local rotation
    ``rest_local_j[:3, :3] @ R_j`` and offset ``rest_local_j[:3, 3]``."""
    import torch

    from uvatar.body.kinematics import forward_kinematics, kinematic_levels

    rest_local = torch.as_tensor(local_joint_transforms(joint_world_rest, joint_parents))
    local = rest_local[:, :3, :3] @ torch.as_tensor(np.asarray(local_rotmats, np.float64))
    F, p = forward_kinematics(kinematic_levels(joint_parents), local[None], rest_local[None, :, :3, 3])
    world = np.tile(np.eye(4), (len(joint_parents), 1, 1))
    world[:, :3, :3], world[:, :3, 3] = F[0].numpy(), p[0].numpy()
    return world


def skin_reference(mesh: SkinnedMesh, local_rotmats: np.ndarray) -> np.ndarray:
    """glTF linear blend skinning of ``mesh`` in numpy (the reference for the viewer's skinning):
    :func:`uvatar.body.kinematics.skin` with the mesh's (at most 4) influences per vertex.

    local_rotmats (J, 3, 3): rotation of each joint relative to its rest frame. Returns (V, 3) metres.
    """
    import torch

    from uvatar.body.kinematics import skin

    world = posed_joint_transforms(mesh.joint_world_rest, mesh.joint_parents, local_rotmats)
    transforms = world @ np.linalg.inv(mesh.joint_world_rest)  # (J, 4, 4) rest -> posed
    V, J = len(mesh.positions), len(mesh.joint_parents)
    weights = np.zeros((V, J))
    np.add.at(weights, (np.repeat(np.arange(V), mesh.joints.shape[1]), mesh.joints.reshape(-1)),
              mesh.weights.reshape(-1).astype(np.float64))
    out = skin(torch.as_tensor(mesh.positions, dtype=torch.float64)[None], torch.as_tensor(weights),
               torch.as_tensor(transforms[None, :, :3, :]))
    return out[0].numpy()


# ------------------------------------------------------------------------------------------- bundle
def _meta(meta: dict, path: Path, *keys, default=None, required=True):
    for key in keys:
        node, ok = meta, True
        for part in key.split("."):
            if isinstance(node, dict) and part in node:
                node = node[part]
            else:
                ok = False
                break
        if ok:
            return node
    if required and default is None:
        raise InputError(path, f"missing {keys[0]!r}")
    return default


def onnx_io_names(model_path: Path) -> dict:
    """{"input": name, "input_size": N, "texture": name, "displacement": name} read from the ONNX graph."""
    import onnx

    try:
        graph = onnx.load(str(model_path), load_external_data=False).graph
    except FileNotFoundError:
        raise InputError(model_path, "missing ONNX generator") from None
    except Exception as exc:  # noqa: BLE001 - onnx raises several types for bad files
        raise InputError(model_path, f"not a readable ONNX model ({exc})") from None
    init = {i.name for i in graph.initializer}
    inputs = [i for i in graph.input if i.name not in init]
    outs = [o.name for o in graph.output]
    if len(inputs) != 1 or len(outs) < 2:
        raise InputError(model_path, f"expected 1 input and 2 outputs, got {len(inputs)} and {len(outs)}")
    tex = next((o for o in outs if "tex" in o.lower()), outs[0])
    disp = next((o for o in outs if "disp" in o.lower() and o != tex), outs[1] if outs[1] != tex else outs[0])
    dims = inputs[0].type.tensor_type.shape.dim
    size = dims[-1].dim_value if dims and dims[-1].dim_value > 0 else None
    return {"input": inputs[0].name, "input_size": size, "texture": tex, "displacement": disp}


def run_generator(model_path: Path, io_names: dict, model_input: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(B, N) model input -> texture (B, 3, R, R), displacement (B, 3, R, R) with onnxruntime (CPU)."""
    import onnxruntime as ort

    session = ort.InferenceSession(str(model_path), providers=["CPUExecutionProvider"])
    tex, disp = session.run([io_names["texture"], io_names["displacement"]],
                            {io_names["input"]: np.asarray(model_input, np.float32)})
    return tex, disp


def pose_to_model_input(pose: np.ndarray, encoding: dict) -> np.ndarray:
    """(..., J*3) local axis-angle pose -> (..., N) generator input, as the manifest's encoding says.

    ``encoding["joints"]``: conditioning joint indices; ``encoding["type"]``: ``"angles"`` (the model
    encodes sin/cos itself; input = the 3·J_c angles) or ``"sincos"`` (input = [sin a0, cos a0, ...]).
    The viewer's JavaScript twin is ``poseToModelInput`` in web/src/pose.js.
    """
    pose = np.asarray(pose, np.float32)
    angles = pose.reshape(*pose.shape[:-1], -1, 3)[..., list(encoding["joints"]), :]
    angles = angles.reshape(*pose.shape[:-1], -1)
    if encoding["type"] == "sincos":
        return np.stack([np.sin(angles), np.cos(angles)], -1).reshape(*angles.shape[:-1], -1)
    return angles


def write_engine_bundle(avatar_dir: str | Path, config: EngineExportConfig = EngineExportConfig(), *,
                        body: BodyTemplate | None = None, body_model=None, fingers_toes_mask: np.ndarray | None = None,
                        semantic_joints: dict | None = None) -> dict:
    """Write ``avatar.glb``, ``manifest.json`` and the finger/toe mask into ``avatar_dir``; return the manifest.

    ``avatar_dir`` must hold ``avatar.json`` and the ONNX generator. The body comes from ``body``, else
    from ``body_model`` (a BodyModel), else from ``uvatar.body.load_body_model(avatar.json's body model)``.
    """
    avatar_dir = Path(avatar_dir)
    meta_path = avatar_dir / "avatar.json"
    meta = read_avatar_json(avatar_dir)
    onnx_name = _meta(meta, meta_path, "onnx", "model", "files.onnx", default="model.onnx")
    io_names = onnx_io_names(avatar_dir / onnx_name)
    cond = [int(j) for j in _meta(meta, meta_path, "conditioning_joints", "pose_encoding.joints")]
    n_in = io_names["input_size"]
    kind = "sincos" if n_in == 6 * len(cond) else "angles"
    if n_in is not None and n_in not in (3 * len(cond), 6 * len(cond)):
        raise InputError(avatar_dir / onnx_name, f"input size {n_in} fits neither 3 nor 6 x {len(cond)} joints")
    encoding = {"type": kind, "joints": cond, "angles": "local axis-angle components (x, y, z) in radians",
                "input": io_names["input"], "size": n_in or 3 * len(cond),
                # "studio": the last joint is the root, whose slot carries the global orientation Rh (a
                # root-zero pose, as the viewer's, is the body facing the studio's +Z)
                "orientation": (meta.get("model_config") or {}).get("orientation", "body")}
    body_name, shape = avatar_body(meta, meta_path)

    if body is None:
        if body_model is None and str(body_name).lower() in ("none", "", "null"):
            raise InputError(meta_path, "no body model: the engine bundle (GLB) needs one")
        if body_model is None:
            from uvatar.body import load_body_model

            body_model = load_body_model(str(body_name))
        body = body_model.rest_template(shape)
        semantic_joints = semantic_joints or dict(getattr(body_model, "semantic_joints", {}) or {})
    joint_names = list(meta.get("joint_names") or body.joint_names)
    if max(cond, default=0) >= len(joint_names) or min(cond, default=0) < 0:
        raise InputError(meta_path, f"conditioning_joints index out of range for {len(joint_names)} joints")
    if list(body.joint_names) != joint_names:
        raise InputError(meta_path, f"joint order ({len(joint_names)} joints) differs from the body model's "
                                    f"({len(body.joint_names)})")

    model_input = pose_to_model_input(np.zeros((1, 3 * len(joint_names)), np.float32), encoding)
    texture, displacement = run_generator(avatar_dir / onnx_name, io_names, model_input)
    R = int(texture.shape[-1])
    mean_texture = texture[0].transpose(1, 2, 0)  # (R, R, 3), row 0 is v = 1
    mesh = engine_mesh(body, config, texture_png=encode_image(mean_texture))
    write_glb(avatar_dir / config.glb_name, mesh)
    if config.fbx_name:
        from uvatar.avh.exporters.fbx import write_skinned_fbx

        write_skinned_fbx(avatar_dir / config.fbx_name, mesh)

    if fingers_toes_mask is None and (avatar_dir / "body.npz").is_file():
        fingers_toes_mask = read_npz(avatar_dir / "body.npz").get("fingers_toes")  # errors name the file
    if fingers_toes_mask is None and body_model is not None:
        from uvatar.body import part_masks

        fingers_toes_mask = part_masks(body_model, R)["fingers_toes"]
    if fingers_toes_mask is None:
        fingers_toes_mask = np.zeros((R, R), bool)
    if np.shape(fingers_toes_mask) != (R, R):
        raise InputError(avatar_dir / "body.npz", f"fingers_toes mask is {np.shape(fingers_toes_mask)}, "
                                                  f"expected ({R}, {R})")
    write_image(avatar_dir / config.mask_name, np.asarray(fingers_toes_mask, bool).astype(np.uint8) * 255)

    disp_meta = meta.get("displacement", {}) if isinstance(meta.get("displacement"), dict) else {}
    space = meta.get("displacement_space", disp_meta.get("space", DEFAULT_SPACE))
    frame = meta.get("displacement_frame") or frame_of_space(space)
    manifest = {
        "format": MANIFEST_FORMAT,
        "glb": config.glb_name,
        **({"fbx": config.fbx_name} if config.fbx_name else {}),
        "generator": {"file": onnx_name, "input": io_names["input"], "input_size": encoding["size"],
                      "texture_output": io_names["texture"], "displacement_output": io_names["displacement"],
                      "layout": "NCHW float32, image row 0 is v = 1; texture in [0, 1] (sRGB)",
                      **({"file_fp16": meta["model_fp16"]} if isinstance(meta.get("model_fp16"), str)
                         and (avatar_dir / meta["model_fp16"]).is_file() else {})},
        "body_model": str(body_name), "shape": None if shape is None else [float(v) for v in shape],
        "joint_names": joint_names, "joint_parents": [int(p) for p in body.joint_parents],
        "semantic_joints": {k: int(v) for k, v in (semantic_joints or {}).items()},
        "pose_encoding": encoding,
        "texels": R,
        "displacement": {
            "scale": 1.0,
            "units": "m (generator output x scale)",
            "max_abs_m": meta.get("displacement_scale", disp_meta.get("scale")),
            "space": space,
            "frame": frame,
            "applied": APPLIED[frame],
            "uv_attribute": "TEXCOORD_1",
        },
        "finger_toe_mask": config.mask_name,
        "mesh": {"vertices": int(len(mesh.positions)), "triangles": int(len(mesh.indices)),
                 "subdivisions": config.subdivisions, "max_influences": config.max_influences},
        "mean_displacement_abs_m": float(np.abs(displacement).mean()),
    }
    write_json(avatar_dir / config.manifest_name, manifest)
    return manifest
