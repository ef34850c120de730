"""Body fits as a capture system would estimate them: the true pose plus per-joint noise.

Per joint (not the root) a random rotation with angle ~ |N(0, noise_deg)| about a random axis is
composed onto the true local rotation; ``Rh`` gets half that noise and ``Th`` a few millimetres. The
shape is shared by all frames. Deterministic for a given ``rng``.

``tracked`` limits the fit to the joints a body-only capture system estimates (SMPL's 23 body joints,
EasyMocap's smpl fits): every other joint (fingers, toes, eyes) is written in its rest rotation,
whatever the performer did. The scan keeps the curled fingers; the fit does not (AVH §3.5: "SMPL ...
does not represent finger joints individually").
"""

from __future__ import annotations

import numpy as np

from uvatar.capture.types import BodyFit

__all__ = ["noisy_fit"]


def _random_rotvecs(rng: np.random.Generator, n: int, std_deg: float) -> np.ndarray:
    axis = rng.normal(size=(n, 3))
    axis /= np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-12)
    return axis * np.radians(rng.normal(0.0, std_deg, (n, 1)))


def noisy_fit(pose: np.ndarray, Rh: np.ndarray, Th: np.ndarray, shape: np.ndarray, noise_deg: float,
              rng: np.random.Generator, translation_noise: float = 0.003, tracked=None) -> BodyFit:
    """pose (J, 3) true local axis-angles, Rh (3,), Th (3,), shape (S,) -> :class:`BodyFit` with
    noise (degrees, metres). The root rotation stays zero (global rotation is Rh). ``tracked``: joint
    indices the fit estimates (None: all); the others are zero (rest)."""
    from scipy.spatial.transform import Rotation

    pose = np.asarray(pose, dtype=np.float64).reshape(-1, 3)
    noisy = pose.copy()
    if noise_deg > 0:
        noise = _random_rotvecs(rng, len(pose), noise_deg)
        noisy = (Rotation.from_rotvec(noise) * Rotation.from_rotvec(pose)).as_rotvec()
        noisy[0] = 0.0
        Rh = (Rotation.from_rotvec(_random_rotvecs(rng, 1, noise_deg / 2)[0]) * Rotation.from_rotvec(Rh)).as_rotvec()
        Th = np.asarray(Th, dtype=np.float64) + rng.normal(0.0, translation_noise, 3)
    if tracked is not None:
        untracked = np.ones(len(noisy), dtype=bool)
        untracked[np.asarray(list(tracked), dtype=np.int64)] = False
        untracked[0] = False
        noisy[untracked] = 0.0
    return BodyFit(poses=noisy.reshape(-1).astype(np.float32), Rh=np.asarray(Rh, np.float32),
                   Th=np.asarray(Th, np.float32), shapes=np.asarray(shape, np.float32))
