"""BVH motion files: parse into numpy (vectorized over frames), forward kinematics, write.

A joint's local transform is ``translate(t) @ R``, with ``R`` the product of its rotation channels
in the order the file lists them (``Zrotation Yrotation Xrotation`` → ``Rz @ Ry @ Rx``, degrees;
:func:`uvatar.motion.rotations.euler_to_matrix`) and ``t`` its OFFSET. Position channels come in
two kinds, told apart per joint by comparing them with the OFFSET over the clip: *absolute* ones
hold the whole local translation (files that give every joint 6 channels store the offset there)
and replace the OFFSET; *relative* ones are added to it (the usual root channels, whose OFFSET is
0). World transforms compose parent first (:func:`uvatar.body.kinematics.forward_kinematics_numpy`).
Units are the file's (CMU: 1 unit = 1/0.45 inch ≈ 5.64 cm); nothing is rescaled here.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from uvatar.body.kinematics import forward_kinematics_numpy
from uvatar.errors import InputError
from uvatar.io_utils import atomic_path
from uvatar.motion.rotations import euler_to_matrix, matrix_to_euler

_AXES = {"Xrotation": "X", "Yrotation": "Y", "Zrotation": "Z"}
_POSITIONS = {"Xposition": 0, "Yposition": 1, "Zposition": 2}
MAX_CHANNELS = 6


@dataclass(frozen=True)
class Skeleton:
    """names (J,), parents (J,) int64 (-1 root, parents before children), offsets (J, 3) in file
    units, channels: per joint the channel names in file order; end_sites: joint index → End Site
    offset (3,); absolute_positions: per joint, whether its position channels replace the offset
    (True) or add to it (False; also for joints without position channels)."""

    names: tuple[str, ...]
    parents: np.ndarray
    offsets: np.ndarray
    channels: tuple[tuple[str, ...], ...]
    end_sites: dict[int, np.ndarray] = field(default_factory=dict)
    absolute_positions: tuple[bool, ...] = ()

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

    def is_absolute(self, j: int) -> bool:
        return bool(self.absolute_positions[j]) if self.absolute_positions else False


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

    def _rotation_groups(self) -> dict[str, list[tuple[int, list[int]]]]:
        groups: dict[str, list[tuple[int, list[int]]]] = {}  # channel order → joints (one batch each)
        for j, (names, cols) in enumerate(zip(self.skeleton.channels, self.skeleton.channel_columns(), strict=True)):
            rot = [(c, _AXES[n]) for n, c in zip(names, cols, strict=True) if n in _AXES]
            if rot:
                groups.setdefault("".join(a for _, a in rot), []).append((j, [c for c, _ in rot]))
        return groups

    def local_rotations(self) -> np.ndarray:
        """(T, J, 3, 3) each joint's rotation relative to its parent (file channel order)."""
        T, J = self.num_frames, self.skeleton.num_joints
        out = np.broadcast_to(np.eye(3), (T, J, 3, 3)).copy()
        for order, members in self._rotation_groups().items():
            joints = [j for j, _ in members]
            angles = self.channel_values[:, [c for _, cols in members for c in cols]].reshape(T, len(joints), -1)
            out[:, joints] = euler_to_matrix(angles, order, degrees=True)
        return out

    def local_translations(self) -> np.ndarray:
        """(T, J, 3) offsets, with position channels replacing (absolute) or added to them."""
        sk = self.skeleton
        out = np.broadcast_to(sk.offsets, (self.num_frames, sk.num_joints, 3)).copy()
        for j, (names, cols) in enumerate(zip(sk.channels, sk.channel_columns(), strict=True)):
            for n, c in zip(names, cols, strict=True):
                if n in _POSITIONS:
                    k = _POSITIONS[n]
                    out[:, j, k] = self.channel_values[:, c] + (0.0 if sk.is_absolute(j) else sk.offsets[j, k])
        return out

    def world_transforms(self) -> tuple[np.ndarray, np.ndarray]:
        """→ (world rotations (T, J, 3, 3), world positions (T, J, 3)) by forward kinematics."""
        return forward_kinematics_numpy(self.skeleton.parents, self.local_rotations(), self.local_translations())

    def with_rotations(self, local_rotations: np.ndarray, root_positions: np.ndarray | None = None) -> BvhMotion:
        """A copy whose rotation channels encode ``local_rotations`` (T, J, 3, 3) (and the root's
        position channels the world root positions ``root_positions`` (T, 3), when given). Other
        position channels keep their values (or, for a new frame count, their offset meaning)."""
        sk = self.skeleton
        T = local_rotations.shape[0]
        values = np.zeros((T, self.channel_values.shape[1]))
        for order, members in self._rotation_groups().items():
            joints = [j for j, _ in members]
            euler = matrix_to_euler(local_rotations[:, joints], order, degrees=True)
            values[:, [c for _, cols in members for c in cols]] = euler.reshape(T, -1)
        for j, (names, cols) in enumerate(zip(sk.channels, sk.channel_columns(), strict=True)):
            for n, c in zip(names, cols, strict=True):
                if n in _POSITIONS:
                    k, base = _POSITIONS[n], (0.0 if sk.is_absolute(j) else sk.offsets[j, _POSITIONS[n]])
                    if root_positions is not None and sk.parents[j] < 0:
                        values[:, c] = root_positions[:, k] - base
                    elif T == self.num_frames:
                        values[:, c] = self.channel_values[:, c]
                    else:
                        values[:, c] = sk.offsets[j, k] - base
        return replace(self, channel_values=values)


def _absolute_position_channels(channels, columns, offsets, values) -> tuple[bool, ...]:
    """Per joint: do its position channels hold the whole local translation? Yes when they stay
    closer to the OFFSET than to 0 over the clip (median distance)."""
    out = []
    for j, (names, cols) in enumerate(zip(channels, columns, strict=True)):
        pos = [(c, _POSITIONS[n]) for n, c in zip(names, cols, strict=True) if n in _POSITIONS]
        if not pos or not len(values):
            out.append(False)
            continue
        v = values[:, [c for c, _ in pos]]
        o = offsets[j, [k for _, k in pos]]
        out.append(bool(np.median(np.linalg.norm(v - o, axis=1)) < np.median(np.linalg.norm(v, axis=1))))
    return tuple(out)


def _parse_hierarchy(tokens: list[str], path) -> tuple[list, list, list, list, dict]:
    names, parents, offsets, channels, end_sites = [], [], [], [], {}
    stack: list[int] = []
    i, pending_end = 1, False
    while i < len(tokens):
        tok = tokens[i]
        if tok in ("ROOT", "JOINT"):
            if (tok == "ROOT") != (not stack) or (names and not stack):
                raise InputError(path, f"{tok} {tokens[i + 1]} is misplaced (one ROOT, JOINTs inside it)")
            if tokens[i + 1] in names:
                raise InputError(path, f"joint name {tokens[i + 1]!r} appears twice")
            names.append(tokens[i + 1])
            parents.append(stack[-1] if stack else -1)
            offsets.append(np.zeros(3))
            channels.append(())
            i += 2
        elif tok == "End":
            if not stack or stack[-1] < 0:
                raise InputError(path, "End Site outside a joint")
            pending_end = True
            i += 2
        elif tok == "{":
            if not names:
                raise InputError(path, "'{' before the ROOT")
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
            if value.shape != (3,) or not np.all(np.isfinite(value)):
                raise InputError(path, f"OFFSET {' '.join(tokens[i + 1: i + 4])} is not 3 finite numbers")
            if not stack:
                raise InputError(path, "OFFSET outside a joint")
            if pending_end:
                end_sites[[s for s in stack if s >= 0][-1]] = value
            else:
                offsets[-1] = value
            i += 4
        elif tok == "CHANNELS":
            n = int(tokens[i + 1])
            chans = tuple(tokens[i + 2: i + 2 + n])
            if not 0 <= n <= MAX_CHANNELS or len(chans) != n or pending_end or not names:
                raise InputError(path, f"bad CHANNELS line ({n} channels)")
            if any(c not in _AXES and c not in _POSITIONS for c in chans) or len(set(chans)) != n:
                raise InputError(path, f"unknown or repeated channel in {' '.join(chans)}")
            channels[-1] = chans
            i += 2 + n
        else:
            raise InputError(path, f"unexpected token {tok!r} in HIERARCHY")
    if not names or stack:
        raise InputError(path, "empty or unbalanced HIERARCHY")
    return names, parents, offsets, channels, end_sites


def _parse_values(body: str, n_frames: int, n_channels: int, first_line: int, path) -> np.ndarray:
    """MOTION rows → (n_frames, n_channels) float64; errors give the line and the bad token."""
    rows = [(k, line) for k, line in enumerate(body.splitlines(), first_line) if line.strip()]
    if len(rows) != n_frames:
        raise InputError(path, f"MOTION has {len(rows)} rows of values, 'Frames:' says {n_frames}")
    try:
        values = np.array(body.split(), dtype=np.float64)
    except ValueError:
        for k, line in rows:
            for tok in line.split():
                try:
                    float(tok)
                except ValueError:
                    raise InputError(path, f"line {k}: {tok[:20]!r} is not a number") from None
        raise InputError(path, "MOTION values are not numbers") from None
    if values.size != n_frames * n_channels:
        for k, line in rows:
            if len(line.split()) != n_channels:
                raise InputError(path, f"line {k} has {len(line.split())} values, expected {n_channels} channels")
    if not np.all(np.isfinite(values)):
        bad = int(np.flatnonzero(~np.isfinite(values))[0])
        raise InputError(path, f"line {rows[bad // n_channels][0]}: channel value {values[bad]} is not finite")
    return values.reshape(n_frames, n_channels)


def parse_bvh(text: str, path: str | Path = "<bvh>") -> BvhMotion:
    """Parse BVH text (HIERARCHY + MOTION) → :class:`BvhMotion` (every problem an InputError)."""
    import re

    found = re.search(r"^[ \t]*MOTION[ \t]*\r?$", text, re.MULTILINE)  # the line, not a joint named MOTION...
    if not found or "HIERARCHY" not in text[: found.start()]:
        raise InputError(path, "not a BVH file (needs HIERARCHY and MOTION sections)")
    head, sep, motion = text[: found.start()], text[found.start(): found.end()], text[found.end():]
    tokens = head[head.index("HIERARCHY"):].split()
    try:
        names, parents, offsets, channels, end_sites = _parse_hierarchy(tokens, path)
    except (IndexError, ValueError, OverflowError) as exc:
        raise InputError(path, f"malformed HIERARCHY ({exc})") from None
    frames = re.match(r"\s*Frames:[ \t]*(\S+)[ \t]*\r?\n\s*Frame Time:[ \t]*(\S+)[ \t]*(?:\r?\n|$)", motion)
    if not frames:
        raise InputError(path, "MOTION must start with 'Frames: N' and 'Frame Time: SECONDS' lines")
    try:
        n_frames, frame_time = int(frames.group(1)), float(frames.group(2))
    except ValueError:
        raise InputError(path, f"'Frames: {frames.group(1)}' / 'Frame Time: {frames.group(2)}' are not numbers") from None
    if n_frames <= 0:
        raise InputError(path, f"the motion has no frames (Frames: {n_frames})")
    if not np.isfinite(frame_time) or frame_time <= 0:
        raise InputError(path, f"Frame Time must be positive, got {frame_time}")
    first_line = text[: len(head) + len(sep) + frames.end()].count("\n") + 1
    n_channels = sum(len(c) for c in channels)
    values = _parse_values(motion[frames.end():], n_frames, n_channels, first_line, path)
    offsets = np.array(offsets)
    skeleton = Skeleton(tuple(names), np.array(parents, np.int64), offsets, tuple(channels), end_sites)
    absolute = _absolute_position_channels(skeleton.channels, skeleton.channel_columns(), offsets, values)
    return BvhMotion(replace(skeleton, absolute_positions=absolute), frame_time, values)


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
