"""glTF 2.0 / GLB skin animations through pygltflib (``pip install 'uvatar[formats]'``): the
skeleton's animated world transforms → :class:`SkeletonMotion`.

glTF's world is uvatar's (metres, +Y up, right-handed). The skeleton: the joints of the file's
skin (the one with most joints, when several); without a skin, the nodes the animation moves and
their ancestors. Each joint's parent is its nearest skeleton ancestor; nodes above the skeleton (an
``Armature`` node with a rotation or a 0.01 scale) are part of every world matrix. The rest pose:
the nodes' own transforms (``translation``/``rotation``/``scale`` or ``matrix``), as a BVH's zero
channels. The motion: the first animation (or the longest, when several) sampled at the rate of
its keyframes (median spacing), LINEAR (slerp for rotations), STEP, or CUBICSPLINE (keyframe
values, linear in between).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.errors import InputError, require
from uvatar.motion.skeleton import SkeletonMotion, clean_fps, skeleton_motion_from_world, trs_to_matrix

_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
_DTYPES = {5120: (np.int8, 127.0), 5121: (np.uint8, 255.0), 5122: (np.int16, 32767.0),
           5123: (np.uint16, 65535.0), 5125: (np.uint32, None), 5126: (np.float32, None)}
MAX_FRAMES = 200_000


def _check_container(path: Path) -> None:
    """One-line reasons for files that are no glTF at all, before pygltflib's own errors: an empty
    file, a GLB without the ``glTF`` magic, a GLB shorter than its header says, a ``.gltf`` that is
    not JSON."""
    import json
    import struct

    size = path.stat().st_size
    if size == 0:
        raise InputError(path, "empty file (0 bytes): not a glTF/GLB motion")
    with open(path, "rb") as fh:
        head = fh.read(12)
    if head[:4] == b"glTF":
        if size < 12:
            raise InputError(path, f"truncated GLB: {size} bytes, shorter than its 12-byte header")
        declared = struct.unpack("<I", head[8:12])[0]
        if declared > size:
            raise InputError(path, f"truncated GLB: its header says {declared} bytes, the file has {size}")
        return
    if path.suffix.lower() == ".glb" and not head.lstrip()[:1] == b"{":
        start = head[:8].decode("latin-1")
        shown = repr(start) if start.isprintable() else " ".join(f"{b:02x}" for b in head[:8])
        raise InputError(path, f"not a GLB file: it starts with {shown}, not with the bytes 'glTF'")
    try:
        json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise InputError(path, f"not a glTF file: neither the binary GLB form nor JSON ({str(exc).split(':')[0]})") \
            from None


def _load(path: Path):
    g = require("pygltflib", "formats", "reading glTF motions")
    _check_container(path)
    try:
        gltf = g.GLTF2().load(str(path))
        if gltf is None:
            raise ValueError("unreadable")
        gltf.convert_buffers(g.BufferFormat.BINARYBLOB)  # data URIs and .bin files → one blob
        blob = gltf.binary_blob() or b""
    except Exception as exc:  # noqa: BLE001 - pygltflib raises json, struct, key and OS errors
        from uvatar.errors import one_line

        raise InputError(path, f"not a readable glTF/GLB file ({type(exc).__name__}: {one_line(exc)[:120]})") from None
    return gltf, blob


def _accessor(gltf, blob: bytes, index: int, path: Path) -> np.ndarray:
    """Accessor ``index`` → (count, components) float64 (normalized integers scaled to [-1, 1])."""
    try:
        acc = gltf.accessors[index]
        view = gltf.bufferViews[acc.bufferView]
        dtype, norm = _DTYPES[acc.componentType]
        width = _COMPONENTS[acc.type]
    except (IndexError, KeyError, TypeError):
        raise InputError(path, f"accessor {index} is missing or of an unknown type") from None
    item = np.dtype(dtype).itemsize * width
    stride = view.byteStride or item
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    end = start + stride * (acc.count - 1) + item if acc.count else start
    if acc.count <= 0 or end > min(len(blob), (view.byteOffset or 0) + view.byteLength):
        raise InputError(path, f"accessor {index} reaches past its buffer (a truncated file?)")
    raw = np.frombuffer(blob, np.uint8, end - start, start)
    rows = np.lib.stride_tricks.as_strided(raw, (acc.count, item), (stride, 1))
    out = np.ascontiguousarray(rows).view(dtype).reshape(acc.count, width).astype(np.float64)
    if acc.normalized and norm:
        out = np.maximum(out / norm, -1.0)
    return out


def _node_trs(node) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """(translation (3,), quaternion xyzw (4,), scale (3,), matrix (4, 4) or None)."""
    matrix = None
    if node.matrix is not None and len(node.matrix) == 16:
        matrix = np.asarray(node.matrix, np.float64).reshape(4, 4).T  # column-major
    return (np.asarray(node.translation if node.translation is not None else [0, 0, 0], np.float64),
            np.asarray(node.rotation if node.rotation is not None else [0, 0, 0, 1], np.float64),
            np.asarray(node.scale if node.scale is not None else [1, 1, 1], np.float64), matrix)


def _sample(times: np.ndarray, keys: np.ndarray, values: np.ndarray, mode: str, rotation: bool) -> np.ndarray:
    """Values (K, C) keyed at ``keys`` (K,) → at ``times`` (T,)."""
    if mode == "CUBICSPLINE":  # (in-tangent, value, out-tangent) per key: the values, linear between
        values = values.reshape(len(keys), 3, -1)[:, 1]
    if rotation:  # unit quaternions; a zero one (a broken key) is the identity
        norms = np.linalg.norm(values, axis=-1, keepdims=True)
        values = np.where(norms > 1e-12, values / np.maximum(norms, 1e-12), [0.0, 0.0, 0.0, 1.0])
    i1 = np.clip(np.searchsorted(keys, times, side="right"), 1, max(len(keys) - 1, 1))
    i0 = i1 - 1
    if len(keys) == 1:
        return np.repeat(values[:1], len(times), 0)
    w = np.clip((times - keys[i0]) / np.maximum(keys[i1] - keys[i0], 1e-12), 0.0, 1.0)
    if mode == "STEP":
        w = (w >= 1.0).astype(np.float64)
    if not rotation:
        return values[i0] * (1 - w[:, None]) + values[i1] * w[:, None]
    from scipy.spatial.transform import Rotation

    from uvatar.motion.rotations import slerp_rotvecs

    r0, r1 = (Rotation.from_quat(values[i]).as_rotvec() for i in (i0, i1))
    return Rotation.from_rotvec(slerp_rotvecs(r0, r1, w)).as_quat()


def _skeleton(gltf, animation, path: Path) -> list[int]:
    if gltf.skins:
        skin = max(gltf.skins, key=lambda s: len(s.joints or []))
        if skin.joints:
            return list(dict.fromkeys(skin.joints))
    if animation is None:
        raise InputError(path, "no skin and no animation: nothing to read a motion from")
    moved = {c.target.node for c in animation.channels if c.target is not None and c.target.node is not None}
    parent = _parents(gltf)
    joints = set()
    for n in moved:
        while n is not None and n not in joints:
            joints.add(n)
            n = parent.get(n)
    return sorted(joints)


def _parents(gltf) -> dict[int, int]:
    return {c: p for p, node in enumerate(gltf.nodes) for c in (node.children or [])}


def _animation(gltf):
    anims = [a for a in (gltf.animations or []) if a.channels]
    if not anims:
        return None
    return max(anims, key=lambda a: len(a.channels))  # the first of the fullest


def read_gltf_skeleton(path: str | Path, fps: float | None = None) -> SkeletonMotion:
    """Read a .gltf/.glb file's skin animation → :class:`SkeletonMotion` (metres, +Y up). ``fps``:
    sample at this rate instead of the keyframes'. Problems are one-line InputErrors naming the file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "glTF file is missing")
    gltf, blob = _load(path)
    if not gltf.nodes:
        raise InputError(path, "the file has no nodes (no skeleton)")
    animation = _animation(gltf)
    joints = _skeleton(gltf, animation, path)
    if animation is None:
        raise InputError(path, "no animation: the file has a skin but no animation of it")
    N = len(gltf.nodes)
    if any(not 0 <= j < N for j in joints):
        raise InputError(path, "the skin names nodes the file does not have")
    parent = _parents(gltf)
    # sampled channels: node → {path: (T, C)}
    channels = []
    key_times = []
    for c in animation.channels:
        if c.target is None or c.target.node is None or c.target.path not in ("translation", "rotation", "scale"):
            continue
        try:
            sampler = animation.samplers[c.sampler]
        except (IndexError, TypeError):
            raise InputError(path, f"animation channel names a missing sampler {c.sampler}") from None
        keys = _accessor(gltf, blob, sampler.input, path)[:, 0]
        values = _accessor(gltf, blob, sampler.output, path)
        if len(keys) == 0 or np.any(np.diff(keys) < 0) or not np.all(np.isfinite(keys)):
            raise InputError(path, "animation keyframe times are empty, decreasing or not finite")
        channels.append((c.target.node, c.target.path, keys, values, sampler.interpolation or "LINEAR"))
        key_times.append(keys)
    if not channels:
        raise InputError(path, "no animation: no channel moves a node (translation, rotation, scale)")
    every = np.unique(np.concatenate(key_times))
    t0, t1 = float(every[0]), float(every[-1])
    steps = np.diff(every)
    rate = clean_fps(float(fps) if fps else (1.0 / float(np.median(steps)) if len(steps) else 30.0))
    count = int(np.floor((t1 - t0) * rate + 1e-3)) + 1  # float32 key times
    if count > MAX_FRAMES:
        raise InputError(path, f"the animation has {count} frames at {rate:g} fps (more than {MAX_FRAMES})")
    times = t0 + np.arange(count) / rate
    trs = [_node_trs(n) for n in gltf.nodes]
    animated: dict[int, dict[str, np.ndarray]] = {}
    for node, kind, keys, values, mode in channels:
        width = {"translation": 3, "rotation": 4, "scale": 3}[kind]
        if values.shape[1] != width or len(values) != len(keys) * (3 if mode == "CUBICSPLINE" else 1):
            raise InputError(path, f"node {node} {kind}: {len(values)} values of width {values.shape[1]} "
                                   f"for {len(keys)} keyframes")
        animated.setdefault(node, {})[kind] = _sample(times, keys, values, mode, kind == "rotation")
    # world matrices of the joints and of every ancestor above them, frame by frame (vectorized over T)
    needed = set()
    for j in joints:
        n = j
        while n is not None and n not in needed:
            needed.add(n)
            n = parent.get(n)
    world: dict[int, np.ndarray] = {}
    rest: dict[int, np.ndarray] = {}

    def local(n: int, at_rest: bool) -> np.ndarray:
        t, q, s, m = trs[n]
        moved = {} if at_rest else animated.get(n, {})
        if m is not None and not moved:
            return m
        return trs_to_matrix(moved.get("translation", t), moved.get("rotation", q), moved.get("scale", s))

    def resolve(n: int) -> None:
        chain = []
        while n is not None and n not in world:
            chain.append(n)
            n = parent.get(n)
        for m in reversed(chain):
            p = parent.get(m)
            world[m] = (world[p] if p is not None else np.eye(4)) @ local(m, False)
            rest[m] = (rest[p] if p is not None else np.eye(4)) @ local(m, True)

    for j in joints:
        resolve(j)
    index = {n: k for k, n in enumerate(joints)}
    parents = []
    for j in joints:
        p = parent.get(j)
        while p is not None and p not in index:
            p = parent.get(p)
        parents.append(-1 if p is None else index[p])
    W = np.stack([np.broadcast_to(world[j], (count, 4, 4)) for j in joints], 1)
    R = np.stack([rest[j] for j in joints])
    names = [gltf.nodes[j].name or f"node{j}" for j in joints]
    return skeleton_motion_from_world(names, parents, R, W, rate, units_to_metres=1.0, source=path.name, what=path)
