"""BVH motion files: parse into numpy (vectorized over frames), forward kinematics, write.

A joint's local transform is ``translate(offset + position channels) @ R``, with ``R`` the product
of its rotation channels in the order the file lists them (``Zrotation Yrotation Xrotation`` →
``Rz @ Ry @ Rx``, angles in degrees). World transforms compose parent first. Units are the file's
(CMU: 1 unit = 1/0.45 inch ≈ 5.64 cm); nothing is rescaled here.
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from uvatar.errors import InputError
from uvatar.io_utils import atomic_path

_AXES = {"Xrotation": "X", "Yrotation": "Y", "Zrotation": "Z"}
_POSITIONS = {"Xposition": 0, "Yposition": 1, "Zposition": 2}


@dataclass(frozen=True)
class Skeleton:
    """names (J,), parents (J,) int64 (-1 root), offsets (J, 3) in file units, channels: per joint
    the channel names in file order; end_sites: joint index → End Site offset (3,)."""

    names: tuple[str, ...]
    parents: np.ndarray
    offsets: np.ndarray
    channels: tuple[tuple[str, ...], ...]
    end_sites: dict[int, np.ndarray] = field(default_factory=dict)

    @property
    def num_joints(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        return self.names.index(name)

    def channel_columns(self) -> list[np.ndarray]:
        """Per joint, the column indices of its channels in a frame row."""
        out, start = [], 0
        for ch in self.channels:
            out.append(np.arange(start, start + len(ch)))
            start += len(ch)
        return out


@dataclass
class BvhMotion:
    """skeleton; frame_time seconds; channel_values (T, C) raw values in file order (degrees,
    file units). Derived arrays: :meth:`local_rotations` (T, J, 3, 3) and :meth:`local_translations`
    (T, J, 3)."""

    skeleton: Skeleton
    frame_time: float
    channel_values: np.ndarray

    @property
    def num_frames(self) -> int:
        return int(self.channel_values.shape[0])

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time

    def local_rotations(self) -> np.ndarray:
        """(T, J, 3, 3) each joint's rotation relative to its parent (file channel order)."""
        T, J = self.num_frames, self.skeleton.num_joints
        out = np.broadcast_to(np.eye(3), (T, J, 3, 3)).copy()
        groups: dict[str, list[tuple[int, list[int]]]] = {}  # channel order → joints (one batch each)
        for j, (names, cols) in enumerate(zip(self.skeleton.channels, self.skeleton.channel_columns(), strict=True)):
            rot = [(c, _AXES[n]) for n, c in zip(names, cols, strict=True) if n in _AXES]
            if rot:
                groups.setdefault("".join(a for _, a in rot), []).append((j, [c for c, _ in rot]))
        for order, members in groups.items():
            joints = [j for j, _ in members]
            angles = self.channel_values[:, [c for _, cols in members for c in cols]].reshape(T, len(joints), -1)
            out[:, joints] = euler_to_matrix(np.deg2rad(angles), order)
        return out

    def local_translations(self) -> np.ndarray:
        """(T, J, 3) offset plus any position channels, in file units."""
        T = self.num_frames
        out = np.broadcast_to(self.skeleton.offsets, (T, self.skeleton.num_joints, 3)).copy()
        for j, (names, cols) in enumerate(zip(self.skeleton.channels, self.skeleton.channel_columns(), strict=True)):
            for n, c in zip(names, cols, strict=True):
                if n in _POSITIONS:
                    out[:, j, _POSITIONS[n]] += self.channel_values[:, c]
        return out

    def world_transforms(self) -> tuple[np.ndarray, np.ndarray]:
        """→ (world rotations (T, J, 3, 3), world positions (T, J, 3)) by forward kinematics."""
        return forward_kinematics(self.skeleton.parents, self.local_rotations(), self.local_translations())

    def with_rotations(self, local_rotations: np.ndarray, root_positions: np.ndarray | None = None) -> BvhMotion:
        """A copy whose rotation channels encode ``local_rotations`` (T, J, 3, 3) (and root position
        channels ``root_positions`` (T, 3) minus the root offset, when given)."""
        from scipy.spatial.transform import Rotation

        T = local_rotations.shape[0]
        values = np.zeros((T, self.channel_values.shape[1]))
        for j, (names, cols) in enumerate(zip(self.skeleton.channels, self.skeleton.channel_columns(), strict=True)):
            rot = [(c, _AXES[n]) for n, c in zip(names, cols, strict=True) if n in _AXES]
            if rot:
                order = "".join(a for _, a in rot)
                with warnings.catch_warnings():  # gimbal lock: angles differ, the rotation is exact
                    warnings.simplefilter("ignore", UserWarning)
                    euler = Rotation.from_matrix(local_rotations[:, j]).as_euler(order, degrees=True)
                values[:, [c for c, _ in rot]] = euler
            for n, c in zip(names, cols, strict=True):
                if n in _POSITIONS:
                    if root_positions is not None and j == 0:
                        values[:, c] = root_positions[:, _POSITIONS[n]] - self.skeleton.offsets[0, _POSITIONS[n]]
                    elif T == self.num_frames:
                        values[:, c] = self.channel_values[:, c]
        return replace(self, channel_values=values)


def axis_rotation(angles: np.ndarray, axis: str) -> np.ndarray:
    """Rotation matrices (..., 3, 3) about "X", "Y" or "Z" by ``angles`` (...) radians."""
    c, s = np.cos(angles), np.sin(angles)
    out = np.zeros((*np.shape(angles), 3, 3))
    i, j = {"X": (1, 2), "Y": (2, 0), "Z": (0, 1)}[axis]
    k = 3 - i - j
    out[..., k, k] = 1.0
    out[..., i, i], out[..., i, j], out[..., j, i], out[..., j, j] = c, -s, s, c
    return out


def euler_to_matrix(angles: np.ndarray, order: str) -> np.ndarray:
    """Intrinsic Euler angles (..., len(order)) radians in ``order`` (e.g. "ZYX") → (..., 3, 3)
    ``R = R_order[0] @ R_order[1] @ ...`` (the BVH convention)."""
    out = axis_rotation(angles[..., 0], order[0])
    for k in range(1, len(order)):
        out = out @ axis_rotation(angles[..., k], order[k])
    return out


def forward_kinematics(parents: np.ndarray, local_rotations: np.ndarray, local_translations: np.ndarray):
    """World transforms of a joint tree, vectorized over leading dims.

    parents (J,) with parents[j] < j; local_rotations (..., J, 3, 3); local_translations (..., J, 3)
    → (world_rotations (..., J, 3, 3), world_positions (..., J, 3)).
    """
    world_r = np.empty_like(local_rotations)
    world_p = np.empty_like(local_translations)
    for j, p in enumerate(parents):
        if p < 0:
            world_r[..., j, :, :] = local_rotations[..., j, :, :]
            world_p[..., j, :] = local_translations[..., j, :]
        else:
            world_r[..., j, :, :] = world_r[..., p, :, :] @ local_rotations[..., j, :, :]
            world_p[..., j, :] = (world_r[..., p, :, :] @ local_translations[..., j, :, None])[..., 0] + world_p[..., p, :]
    return world_r, world_p


def parse_bvh(text: str, path: str | Path = "<bvh>") -> BvhMotion:
    """Parse BVH text (HIERARCHY + MOTION) → :class:`BvhMotion`."""
    head, sep, motion = text.partition("MOTION")
    if not sep or "HIERARCHY" not in head:
        raise InputError(path, "not a BVH file (needs HIERARCHY and MOTION sections)")
    tokens = head.split()
    names, parents, offsets, channels, end_sites = [], [], [], [], {}
    stack: list[int] = []
    i, pending_end = tokens.index("HIERARCHY") + 1, False
    try:
        while i < len(tokens):
            tok = tokens[i]
            if tok in ("ROOT", "JOINT"):
                names.append(tokens[i + 1])
                parents.append(stack[-1] if stack else -1)
                offsets.append(np.zeros(3))
                channels.append(())
                i += 2
            elif tok == "End":
                pending_end = True
                i += 2
            elif tok == "{":
                stack.append(-2 if pending_end else len(names) - 1)
                i += 1
            elif tok == "}":
                if not stack:
                    raise InputError(path, "unbalanced braces in HIERARCHY")
                stack.pop()
                pending_end = False
                i += 1
            elif tok == "OFFSET":
                value = np.array([float(t) for t in tokens[i + 1: i + 4]])
                if pending_end:
                    end_sites[[s for s in stack if s >= 0][-1]] = value
                else:
                    offsets[-1] = value
                i += 4
            elif tok == "CHANNELS":
                n = int(tokens[i + 1])
                chans = tuple(tokens[i + 2: i + 2 + n])
                if any(c not in _AXES and c not in _POSITIONS for c in chans):
                    raise InputError(path, f"unknown channel in {' '.join(chans)}")
                channels[-1] = chans
                i += 2 + n
            else:
                raise InputError(path, f"unexpected token {tok!r} in HIERARCHY")
    except (IndexError, ValueError) as exc:
        raise InputError(path, f"malformed HIERARCHY ({exc})") from None
    if not names or stack:
        raise InputError(path, "empty or unbalanced HIERARCHY")
    frames = re.search(r"Frames:\s*(\d+)", motion)
    ftime = re.search(r"Frame Time:\s*([0-9.eE+-]+)", motion)
    if not frames or not ftime:
        raise InputError(path, "MOTION section lacks 'Frames:' or 'Frame Time:'")
    body = motion[ftime.end():]
    n_frames, n_channels = int(frames.group(1)), sum(len(c) for c in channels)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        values = np.fromstring(body, dtype=np.float64, sep=" ")  # noqa: NPY201
    if values.size != n_frames * n_channels:
        raise InputError(path, f"MOTION has {values.size} values, expected {n_frames} frames x {n_channels} channels")
    frame_time = float(ftime.group(1))
    if frame_time <= 0:
        raise InputError(path, f"Frame Time must be positive, got {frame_time}")
    skeleton = Skeleton(tuple(names), np.array(parents, np.int64), np.array(offsets), tuple(channels), end_sites)
    return BvhMotion(skeleton, frame_time, values.reshape(n_frames, n_channels))


def read_bvh(path: str | Path) -> BvhMotion:
    """Read a .bvh file → :class:`BvhMotion` (errors name the file)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "BVH file is missing")
    return parse_bvh(path.read_text(errors="replace"), path)


def format_bvh(motion: BvhMotion, precision: int = 6) -> str:
    sk = motion.skeleton
    children: dict[int, list[int]] = {j: [] for j in range(sk.num_joints)}
    for j, p in enumerate(sk.parents):
        if p >= 0:
            children[int(p)].append(j)
    lines = ["HIERARCHY"]

    def emit(j: int, depth: int) -> None:
        pad = "\t" * depth
        kind = "ROOT" if sk.parents[j] < 0 else "JOINT"
        lines.append(f"{pad}{kind} {sk.names[j]}")
        lines.append(pad + "{")
        lines.append(f"{pad}\tOFFSET " + " ".join(f"{x:.{precision}f}" for x in sk.offsets[j]))
        lines.append(f"{pad}\tCHANNELS {len(sk.channels[j])} " + " ".join(sk.channels[j]))
        for c in children[j]:
            emit(c, depth + 1)
        if j in sk.end_sites:
            lines.extend([f"{pad}\tEnd Site", pad + "\t{",
                          f"{pad}\t\tOFFSET " + " ".join(f"{x:.{precision}f}" for x in sk.end_sites[j]), pad + "\t}"])
        lines.append(pad + "}")

    for root in np.flatnonzero(sk.parents < 0):
        emit(int(root), 0)
    lines += ["MOTION", f"Frames: {motion.num_frames}", f"Frame Time: {motion.frame_time:.7f}"]
    row = " ".join([f"%.{precision}f"] * motion.channel_values.shape[1]) + "\n"
    return "\n".join(lines) + "\n" + (row * motion.num_frames) % tuple(motion.channel_values.ravel())


def write_bvh(path: str | Path, motion: BvhMotion, precision: int = 6) -> None:
    """Write a .bvh file atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(format_bvh(motion, precision))
