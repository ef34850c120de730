"""A tiny synthetic baked dataset (the `uvatar bake` layout) for tests and benchmarks.

Texture and displacement depend smoothly on the pose, so a generator can learn them; a few
displacement texels are 20 cm outliers; displacements are stored in world axes of the posed frame
(rotated by a random global rotation Rh about +Y), as the bake writes them. ``body_model`` is "none"
and ``dataset.json`` lists ``conditioning_joints`` so no body model is needed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.avh.data import body_to_world
from uvatar.io_utils import write_json, write_npz


def fake_maps(pose: np.ndarray, resolution: int, conditioning_joints) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free (texture (R,R,3) in [0,1], body-frame displacement (R,R,3) metres) for one pose (J*3,)."""
    R = resolution
    v, u = np.meshgrid(1.0 - (np.arange(R) + 0.5) / R, (np.arange(R) + 0.5) / R, indexing="ij")
    angles = pose.reshape(-1, 3)[list(conditioning_joints)].reshape(-1)
    base = np.stack([0.5 + 0.3 * np.sin(6 * u), 0.5 + 0.3 * np.cos(5 * v), 0.5 + 0.2 * np.sin(4 * (u + v))], -1)
    tex = base.copy()
    disp = np.zeros((R, R, 3))
    for k, a in enumerate(angles[:6]):
        bump = np.exp(-((u - (0.2 + 0.12 * k)) ** 2 + (v - 0.5) ** 2) / 0.02)
        tex[..., k % 3] += 0.15 * np.sin(a) * bump
        disp[..., (k + 1) % 3] += 0.02 * np.sin(a) * bump
    return np.clip(tex, 0, 1).astype(np.float32), disp.astype(np.float32)


def make_fake_baked_dataset(out_dir: str | Path, num_frames: int = 12, resolution: int = 32,
                            num_joints: int = 5, num_val: int = 2, seed: int = 0,
                            conditioning_joints: list[int] | None = None, body_model: str = "none") -> Path:
    """Write BAKED/dataset.json and BAKED/frames/*.npz; returns ``out_dir``.

    Joint 0 is the root (zero); the conditioning joints default to 1..num_joints-1. ``body_model`` is
    the name written to dataset.json ("none": no body model needed; pass one to train_avh instead).
    """
    out = Path(out_dir)
    rng = np.random.default_rng(seed)
    cond = list(conditioning_joints) if conditioning_joints is not None else list(range(1, num_joints))
    R = resolution
    yy, xx = np.mgrid[:R, :R]
    valid = ((yy - R / 2 + 0.5) ** 2 + (xx - R / 2 + 0.5) ** 2) < (0.45 * R) ** 2
    names = [f"{i:06d}" for i in range(num_frames)]
    for name in names:
        pose = np.zeros((num_joints, 3), np.float32)
        pose[1:] = rng.uniform(-1.2, 1.2, (num_joints - 1, 3))
        tex, disp = fake_maps(pose.reshape(-1), R, cond)
        outliers = rng.random((R, R)) < 0.01
        disp[outliers] = 0.2
        Rh = np.array([0.0, rng.uniform(-np.pi, np.pi), 0.0], np.float32)
        kappa = (0.5 + 0.5 * rng.random((R, R))).astype(np.float32) * valid
        w = np.where(valid, 0.9, 0.0).astype(np.float32)
        write_npz(out / "frames" / f"{name}.npz", texture=tex.astype(np.float16),
                  displacement=body_to_world(disp, Rh).astype(np.float32), kappa=kappa, w=w, valid=valid,
                  pose=pose.reshape(-1), Rh=Rh, Th=rng.normal(0, 0.1, 3).astype(np.float32))
    write_json(out / "dataset.json", {
        "texels": R, "body_model": {"name": body_model, "shapes": None}, "frames_baked": names, "rejected": {},
        "conditioning_joints": cond, "joint_names": [f"joint{j}" for j in range(num_joints)],
        "selection": {"train": names[: num_frames - num_val], "val": names[num_frames - num_val:]},
    })
    return out
