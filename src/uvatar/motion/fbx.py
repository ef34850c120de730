"""FBX skeletal motions (binary and ASCII) through ufbx's own Python binding (``pip install
'uvatar[formats]'``): the skeleton's animated world transforms → :class:`SkeletonMotion`.

The file is loaded converted to uvatar's world (right-handed, +Y up, metres: ufbx's
``target_axes``/``target_unit_meters``, applied at the scene root), so Mixamo's centimetres and Z-up
exports arrive in metres, +Y up. The skeleton: the nodes with a bone attribute (``LimbNode``;
Mixamo, Unity, Maya, Blender exports), else the bones of the skin clusters; each joint's parent is
its nearest skeleton ancestor. The rest pose: the nodes' own (unanimated) transforms, as a BVH's
zero channels. The motion: the first animation stack (or the longest, when several) evaluated by
ufbx at the scene's frame rate over the stack's time range (pivots, pre/post rotations and
inheritance handled by ufbx), world matrices from which :func:`skeleton_motion_from_world` takes
rotations and positions.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.errors import InputError, require
from uvatar.motion.skeleton import SkeletonMotion, clean_fps, skeleton_motion_from_world, trs_to_matrix

MAX_FRAMES = 200_000


def _matrix(m) -> np.ndarray:
    """ufbx Matrix (columns c0..c3) → (4, 4)."""
    out = np.eye(4)
    for k, c in enumerate((m.c0, m.c1, m.c2, m.c3)):
        out[:3, k] = (c.x, c.y, c.z)
    return out


def _node_table(scene, keep: list) -> tuple[list[tuple[str, int, bool, int]], list]:
    """(name, typed id, is a bone, parent's typed id or -1) per node, and the nodes. ``keep`` holds every wrapper
    the binding hands out until the scene is done with (it frees memory with its temporaries)."""
    listed = scene.nodes
    keep.append(listed)
    table, nodes = [], []
    for node in listed:
        nodes.append(node)
        parent, bone = node.parent, node.bone
        keep += [node, parent, bone]
        table.append((node.name, node.typed_id, bone is not None and not node.is_root,
                      -1 if parent is None else parent.typed_id))
    if not any(t[2] for t in table):  # no LimbNode: the bones the skin clusters name
        skins = scene.skin_deformers
        keep.append(skins)
        named = set()
        for skin in skins:
            clusters = skin.clusters
            keep += [skin, clusters]
            for cluster in clusters:
                bone_node = cluster.bone_node
                keep += [cluster, bone_node]
                if bone_node is not None:
                    named.add(bone_node.typed_id)
        table = [(n, t, t in named, p) for n, t, _, p in table]
    return table, nodes


def _transforms(transforms) -> np.ndarray:
    """ufbx Transforms → (n, 4, 4)."""
    t = np.array([(x.translation.x, x.translation.y, x.translation.z) for x in transforms])
    q = np.array([(x.rotation.x, x.rotation.y, x.rotation.z, x.rotation.w) for x in transforms])
    s = np.array([(x.scale.x, x.scale.y, x.scale.z) for x in transforms])
    return trs_to_matrix(t, q, s)


def _depth(t: int, parent_of: dict[int, int]) -> int:
    d = 0
    while parent_of[t] >= 0:
        t, d = parent_of[t], d + 1
    return d


def _load(ufbx, path: Path):
    axes = ufbx.CoordinateAxes(ufbx.CoordinateAxis.POSITIVE_X, ufbx.CoordinateAxis.POSITIVE_Y,
                               ufbx.CoordinateAxis.POSITIVE_Z)
    try:
        return ufbx.load_file(str(path), target_axes=axes, target_unit_meters=1.0,
                              space_conversion=ufbx.SpaceConversion.TRANSFORM_ROOT)
    except ufbx.UfbxError as exc:
        what = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise InputError(path, f"not a readable FBX file ({type(exc).__name__}: {what})") from None


def read_fbx_skeleton(path: str | Path, fps: float | None = None) -> SkeletonMotion:
    """Read an FBX file's skeletal animation → :class:`SkeletonMotion` (metres, +Y up). ``fps``:
    sample at this rate instead of the file's. Problems are one-line InputErrors naming the file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "FBX file is missing")
    ufbx = require("ufbx", "formats", "reading FBX motions")
    scene = _load(ufbx, path)
    try:  # every wrapper of the scene lives in _animation's frame and is gone before the scene
        names, parents, rest, world, rate = _animation(ufbx, scene, path, fps)
    finally:
        del scene
    return skeleton_motion_from_world(names, parents, rest, world, rate, units_to_metres=1.0, source=path.name,
                                      what=path)


def _animation(ufbx, scene, path: Path, fps: float | None):
    """(names, parents, rest world (J, 4, 4), world (T, J, 4, 4), fps) of the skeleton's animation."""
    keep: list = []
    try:
        table, wrappers = _node_table(scene, keep)
        bones = [t for t in table if t[2]]
        if not bones:
            raise InputError(path, "no skeleton: no bone (LimbNode) nodes and no skin clusters")
        listed = scene.anim_stacks
        keep.append(listed)
        stacks = [(s.time_begin, s.time_end, s) for s in listed if s.time_end > s.time_begin]
        keep += [s for *_, s in stacks]
        if not stacks:
            raise InputError(path, "no animation: the file has no animation stack with a time range")
        begin, end, stack = max(stacks, key=lambda s: s[1] - s[0])  # the first of the longest
        anim = stack.anim
        keep.append(anim)
        settings = scene.settings
        keep.append(settings)
        rate = clean_fps(float(fps or settings.frames_per_second or 30.0))
        count = int(np.floor((end - begin) * rate + 1e-3)) + 1
        if count > MAX_FRAMES:
            raise InputError(path, f"the animation has {count} frames at {rate:g} fps (more than {MAX_FRAMES})")
        ids = [t for _, t, _, _ in bones]
        index = {t: j for j, t in enumerate(ids)}
        parent_of = {t: p for _, t, _, p in table}
        parents = []
        for t in ids:
            p = parent_of[t]
            while p >= 0 and p not in index:
                p = parent_of[p]
            parents.append(index[p] if p >= 0 else -1)
        chain = []  # the bones and every node above them, parents first (typed ids ascend down the tree)
        for t in ids:
            while t >= 0 and t not in chain:
                chain.append(t)
                t = parent_of[t]
        chain.sort(key=lambda t: _depth(t, parent_of))
        nodes = {row[1]: n for row, n in zip(table, wrappers, strict=True) if row[1] in chain}
        local_rest = _transforms([nodes[t].local_transform for t in chain])
        local = np.empty((count, len(chain), 4, 4))
        for k in range(count):  # ufbx evaluates each node's local transform (pivots, pre/post rotation)
            time = begin + k / rate
            local[k] = _transforms([ufbx.evaluate_transform(anim, nodes[t], time) for t in chain])
        at = {t: c for c, t in enumerate(chain)}
        world_rest, world = np.empty_like(local_rest), np.empty_like(local)
        for c, t in enumerate(chain):
            p = parent_of[t]
            world_rest[c] = (world_rest[at[p]] if p >= 0 else np.eye(4)) @ local_rest[c]
            world[:, c] = (world[:, at[p]] if p >= 0 else np.eye(4)) @ local[:, c]
        rows = [at[t] for t in ids]
        rest, world = world_rest[rows], world[:, rows]
    finally:
        keep.clear()
    return [n for n, _, _, _ in bones], parents, rest, world, rate
