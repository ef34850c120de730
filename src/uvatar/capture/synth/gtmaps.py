"""Exact ground-truth maps of a synthetic capture at any texel resolution.

``gt/frames/F.npz`` stores the true texture and surface at ``gt_texels`` (256 by default). A bake
at R != gt_texels must not be scored against a bilinear resample of those maps: the shirt's plaid
lines (6 mm) are point-sampled at 256 texels, and resampling them blurs and aliases the reference
itself (on /tmp/perfcap: 256 -> 512 bilinear is only ~28 dB against the exact 512 maps). Since the
studio is a deterministic function of its config (saved in ``gt/info.json``), :class:`GtRenderer`
re-evaluates the true appearance and surface at the texel centres of any resolution, from the
frame's stored true pose (``gt/frames/F.npz``: pose, Rh, Th; the bends, garment drape and drift are
recomputed from it exactly as when the frame was made, :meth:`.frame.Studio.posed`).
"""

from __future__ import annotations

import json
from dataclasses import fields
from pathlib import Path

import numpy as np

from uvatar.capture.gt import read_gt_info

__all__ = ["config_from_dict", "GtRenderer"]


def config_from_dict(data: dict):
    """A :class:`SynthConfig` from its ``to_dict()`` (as saved in ``gt/info.json``; lists -> tuples,
    unknown keys ignored)."""
    from uvatar.capture.synth.config import SynthConfig

    def build(cls, values):
        kw = {}
        for f in fields(cls):
            if f.name not in values:
                continue
            v = values[f.name]
            sub = f.default_factory if callable(getattr(f, "default_factory", None)) else None
            if isinstance(v, dict) and sub is not None:
                v = build(type(sub()), v)
            elif isinstance(v, list):
                v = tuple(v)
            kw[f.name] = v
        return cls(**kw)

    data = dict(data or {})
    if data and "bending_length" not in (data.get("clothing") or {"bending_length": None}):
        # captures made before the drape and drift: cloth along the body normal, no bridging or drift
        data["clothing"] = dict(data["clothing"], bending_length=0.0, drift_elbow=0.0, drift_knee=0.0)
    if data and "light" not in data:  # captures made before the studio light: unlit
        data["light"] = "none"
    return build(SynthConfig, data)


class GtRenderer:
    """True texture / clothed surface of a synthetic capture's frames at ``resolution`` texels.

    ``render(frame)`` -> dict texture (R, R, 3) float32 [0, 1], surface (R, R, 3) float64 world
    metres, normal (R, R, 3) unit offset directions there (the garment normal, :mod:`.drape`), mask (R, R) bool
    (all in the body UV layout, row 0 = v 1), or None when the frame has no gt file.
    """

    def __init__(self, capture_root, resolution: int):
        from uvatar.capture.synth.frame import Studio

        self.root = Path(capture_root)
        info = read_gt_info(self.root)
        cfg = config_from_dict(info.config).replace(gt_texels=int(resolution), workers=1)
        if info.body_shapes is not None:  # the true shape (capture.json holds the fits', e.g. after `uvatar fit`)
            shape = np.asarray(info.body_shapes, dtype=np.float32)
        else:  # captures made before gt/info.json recorded it
            capture = json.loads((self.root / "capture.json").read_text())
            shape = np.asarray(capture.get("body_model", {}).get("shapes", []), dtype=np.float32)
        plan = {"shape": shape, "frames": [], "poses": None, "Rh": None, "Th": None}
        self.cfg = cfg
        self.studio = Studio(cfg, self.root, plan)
        self.resolution = int(resolution)

    def render(self, frame: str) -> dict | None:
        from uvatar.capture.synth.gt import scatter_texels

        path = self.root / "gt" / "frames" / f"{frame}.npz"
        if not path.is_file():
            return None
        with np.load(path) as z:
            pose, Rh, Th = (np.asarray(z[k]) for k in ("pose", "Rh", "Th"))
        st = self.studio
        posed = st.posed(pose, Rh, Th)   # bends recomputed in float64, exactly as when the frame was made
        g, R = st.gt, self.resolution
        points, dirs = st.clothed(g, posed)
        texture = scatter_texels(st.texture(g, posed, points=points, dirs=dirs)[0], st.gt_flat, R)
        surface = np.zeros((R * R, 3))
        surface[st.gt_flat] = points
        normal = np.zeros((R * R, 3))
        normal[st.gt_flat] = dirs
        return {"texture": texture, "surface": surface.reshape(R, R, 3), "normal": normal.reshape(R, R, 3),
                "mask": st.gt_mask.copy()}
