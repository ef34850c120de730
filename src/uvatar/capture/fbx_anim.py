"""FBX animation as stored: the owner of its time unit, its scene frame rates, and its curves
(``AnimationStack`` → ``AnimationLayer`` → ``AnimationCurveNode`` → ``AnimationCurve``) read from an
:class:`~uvatar.capture.mesh_fbx.FbxScene`, and their evaluation.

- **Time**: FBX 7's KTime, 46,186,158,000 ticks a second. The scene's rate is ``GlobalSettings``
  ``TimeMode`` (the FBX SDK's ``EMode``: 6 is 30 fps, 11 is 24, ...; 14, custom, takes
  ``CustomFrameRate``); its range the first stack's ``LocalStart``/``LocalStop``, else
  ``TimeSpanStart``/``TimeSpanStop``.
- **Curves**: a curve node (``AnimCurveNode::T``, ``::Visibility``, ...) animates one property of an
  object (an ``OP`` link to it, the property's name), each channel (``d|X``, ``d|Visibility``) an
  ``AnimationCurve`` (``KeyTime`` int64 KTime, ``KeyValueFloat``, ``KeyAttrFlags`` shared by runs of
  keys as ``KeyAttrRefCount`` says). A channel without a curve holds the node's ``d|...`` default.
- **Evaluation** (:meth:`FbxCurve.at`): before the first key its value, after the last the last's;
  at a key its value; between keys, constant keys hold their value (``eConstantNext`` the next one's), linear keys
  interpolate; cubic keys are evaluated linearly between their values (exact for the stepped and
  linear curves volumetric takes key; :attr:`FbxCurve.cubic` says where that is not all).

:mod:`uvatar.avh.exporters.fbx_motion` writes curves with these constants; :mod:`uvatar.motion.fbx`
evaluates skeletal motion through ufbx.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["KTIME_PER_SECOND", "CUSTOM_TIME_MODE", "LINEAR_KEY", "CONSTANT_KEY", "FbxCurve", "scene_frame_rate",
           "scene_time_span", "animated_properties"]

KTIME_PER_SECOND = 46186158000       # FBX 7's time unit
CONSTANT_KEY = 1 << 1                # KeyAttrFlags: eInterpolationConstant
LINEAR_KEY = 1 << 2                  # eInterpolationLinear
CUBIC_KEY = 1 << 3                   # eInterpolationCubic
CONSTANT_NEXT = 1 << 8               # eConstantNext: a constant key takes the next key's value
CUSTOM_TIME_MODE = 14                # GlobalSettings TimeMode: the rate in CustomFrameRate
#: GlobalSettings TimeMode (the FBX SDK's FbxTime::EMode) -> frames a second; 0 (default) says none
TIME_MODE_FPS = {1: 120.0, 2: 100.0, 3: 60.0, 4: 50.0, 5: 48.0, 6: 30.0, 7: 30.0, 8: 30000 / 1001, 9: 30000 / 1001,
                 10: 25.0, 11: 24.0, 12: 1000.0, 13: 24000 / 1001, 15: 96.0, 16: 72.0, 17: 60000 / 1001,
                 18: 120000 / 1001}


@dataclass
class FbxCurve:
    """One animation channel: ``times`` (K,) int64 KTime, ascending; ``values`` (K,) float64; ``flags``
    (K,) int each key's KeyAttrFlags (its interpolation to the next key)."""

    times: np.ndarray
    values: np.ndarray
    flags: np.ndarray

    @classmethod
    def constant(cls, value: float) -> FbxCurve:
        return cls(np.zeros(1, np.int64), np.array([float(value)]), np.array([CONSTANT_KEY]))

    @property
    def cubic(self) -> bool:
        """Whether a key between two different values interpolates cubically (evaluated linearly here)."""
        changes = np.flatnonzero(np.diff(self.values) != 0)
        return bool(np.any(self.flags[changes] & CUBIC_KEY))

    @property
    def varies(self) -> bool:
        return bool(np.ptp(self.values) > 0) if len(self.values) else False

    def at(self, ktimes, tolerance: int = 0) -> np.ndarray:
        """(N,) the channel's values at ``ktimes`` (N,) KTime (module doc); a key up to ``tolerance`` ticks
        after a time counts as reached (keys other tools rounded to other ticks than a frame's)."""
        t = np.asarray(ktimes, np.int64).reshape(-1)
        if len(self.times) == 1:
            return np.full(len(t), self.values[0])
        k = np.clip(np.searchsorted(self.times, t + int(tolerance), side="right") - 1, 0, len(self.times) - 2)
        t = np.maximum(t, np.minimum(self.times[k], t + int(tolerance)))       # the key before, when within reach
        t0, t1 = self.times[k], self.times[k + 1]
        v0, v1 = self.values[k], self.values[k + 1]
        a = np.clip((t - t0) / np.maximum(t1 - t0, 1).astype(np.float64), 0.0, 1.0)
        flags = self.flags[k]
        constant = (flags & CONSTANT_KEY) != 0
        held = np.where((flags & CONSTANT_NEXT) != 0, v1, v0)
        out = np.where(constant, np.where(a >= 1.0, v1, np.where(t == t0, v0, held)), v0 + a * (v1 - v0))
        out = np.where(t <= self.times[0], self.values[0], out)
        return np.where(t >= self.times[-1], self.values[-1], out)


def _curve(node) -> FbxCurve:
    """An ``AnimationCurve`` record as a :class:`FbxCurve` (one key at its ``Default`` when it has none)."""
    times = node.array("KeyTime", np.int64)
    values = node.array("KeyValueFloat", np.float64)
    if times is None or values is None or len(times) == 0:
        return FbxCurve.constant(float(node.value("Default", 0.0)))
    if len(times) != len(values):
        raise ValueError(f"an AnimationCurve has {len(times)} key times and {len(values)} values")
    order = np.argsort(times, kind="stable")
    flags = node.array("KeyAttrFlags", np.int64)
    counts = node.array("KeyAttrRefCount", np.int64)
    if flags is None or len(flags) == 0:
        per_key = np.full(len(times), LINEAR_KEY)
    elif counts is not None and len(counts) == len(flags) and counts.sum() >= len(times):
        per_key = np.repeat(flags, np.maximum(counts, 0))[: len(times)]
    else:
        per_key = np.resize(flags, len(times))
    return FbxCurve(times[order], values[order], per_key[order])


def scene_frame_rate(scene) -> float:
    """Frames a second the scene's ``GlobalSettings`` state (0 where they state none)."""
    props = scene.settings
    mode = int(props["TimeMode"][0]) if props.get("TimeMode") else 0
    if mode == CUSTOM_TIME_MODE:
        rate = float(props["CustomFrameRate"][0]) if props.get("CustomFrameRate") else 0.0
        return rate if rate > 0 and np.isfinite(rate) else 0.0
    return TIME_MODE_FPS.get(mode, 0.0)


def _stacks(scene) -> list:
    return [oid for oid, node in scene.objects.items() if node.name == "AnimationStack"]


def scene_time_span(scene) -> tuple[int, int] | None:
    """(start, stop) KTime of the first animation stack (``LocalStart``/``LocalStop``), else of the
    ``GlobalSettings``' ``TimeSpanStart``/``TimeSpanStop``; None where neither says."""
    for oid in _stacks(scene)[:1]:
        p = scene.objects[oid].properties70()
        if p.get("LocalStart") and p.get("LocalStop"):
            return int(p["LocalStart"][0]), int(p["LocalStop"][0])
    p = scene.settings
    if p.get("TimeSpanStart") and p.get("TimeSpanStop"):
        return int(p["TimeSpanStart"][0]), int(p["TimeSpanStop"][0])
    return None


def animated_properties(scene) -> dict[tuple, dict[str, FbxCurve]]:
    """{(object id, property name): {channel ("X", "Visibility", ...): curve}} of the curve nodes of the
    first animation stack's layers (of every curve node where the file has no stack); a channel a node
    states but no curve keys is its default held."""
    stacks = _stacks(scene)
    layers = None
    if stacks:
        layers = {child for child, _ in scene.children_of.get(stacks[0], [])
                  if scene.objects.get(child) is not None and scene.objects[child].name == "AnimationLayer"}
    out: dict[tuple, dict[str, FbxCurve]] = {}
    for oid, node in scene.objects.items():
        if node.name != "AnimationCurveNode":
            continue
        if layers is not None and not layers.intersection(scene.parent_of.get(oid, [])):
            continue
        targets = scene.property_targets(oid)
        if not targets:
            continue
        channels = {name[2:]: FbxCurve.constant(float(v[0])) for name, v in node.properties70().items()
                    if name.startswith("d|") and v and isinstance(v[0], int | float)}
        for child, prop in scene.children_of.get(oid, []):
            curve = scene.objects.get(child)
            if curve is not None and curve.name == "AnimationCurve" and prop.startswith("d|"):
                channels[prop[2:]] = _curve(curve)
        for target in targets:
            out[target] = channels
    return out
