"""Feet of a retarget: the target body's sole points, the source's foot clearance, foot contacts
and foot sliding.

- :func:`foot_landmarks` / :func:`sole_points`: a few sole vertices of each foot of the target's
  rest mesh, each riding its main bone, and where they are in a posed frame;
- :func:`foot_clearance`: per source foot and frame, how high the foot is above its own contact
  height (each foot joint's 5th percentile height over the clip), and :func:`source_clearance`,
  the lowest over both feet (the retarget's root height and the report use it);
- :func:`detect_contacts`: per foot, the frames where it stands: clearance below a threshold AND
  a low horizontal speed, with hysteresis (a looser pair of thresholds keeps a contact going) and
  a minimum length; :func:`source_contacts` runs it on a source skeleton, in the target's metres;
- :func:`lowest_point_tracks` and :func:`sliding_speeds`: the measure of foot sliding (the
  horizontal speed of each foot's lowest sole point while it stands), shared by the report and
  the tests.

Arrays: T frames, F = 2 feet (0 left, 1 right), K sole points; metres, seconds, +Y up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uvatar.errors import UvatarError, check_values

SIDES = ("l_", "r_")


@dataclass
class FootContactConfig:
    """height_m / speed_m_s: a foot starts a contact where its clearance (metres, scaled to the
    target) is below ``height_m`` and its lowest joint moves slower than ``speed_m_s``
    horizontally; the contact goes on while both stay below ``release`` times those (hysteresis);
    min_s: shorter contacts are dropped; blend_s: the clean-up fades in and out over this long
    outside each contact; max_drop_m: it lowers the body by at most this much where a leg cannot
    reach (a foot that still cannot is left short of its target: ``info["max_miss_m"]``)."""

    height_m: float = 0.02
    speed_m_s: float = 0.3
    release: float = 1.5
    min_s: float = 0.05
    blend_s: float = 0.1
    max_drop_m: float = 0.1

    def __post_init__(self) -> None:
        check_values([(self.height_m > 0, f"contact height_m must be > 0, got {self.height_m}"),
                      (self.speed_m_s > 0, f"contact speed_m_s must be > 0, got {self.speed_m_s}"),
                      (self.release >= 1, f"contact release must be >= 1, got {self.release}"),
                      (self.min_s >= 0, f"contact min_s must be >= 0, got {self.min_s}"),
                      (self.blend_s >= 0, f"contact blend_s must be >= 0, got {self.blend_s}"),
                      (self.max_drop_m >= 0, f"contact max_drop_m must be >= 0, got {self.max_drop_m}")])


def below(parents, roots) -> np.ndarray:
    """(J,) bool: the joints ``roots`` and every joint under them (:func:`uvatar.body.kinematics.ancestor_matrix`)."""
    from uvatar.body.kinematics import ancestor_matrix

    return ancestor_matrix(parents)[:, list(roots)].any(1)


def foot_landmarks(body, tgt_index: dict[str, int], band: float = 0.02, per_foot: int = 128, rest=None):
    """Sole points of the target's rest mesh (``rest``, a BodyTemplate of ``body`` at some shape;
    None: ``body.template``): (joint index (K,), rest position (K, 3), side (K,) 0 left / 1 right) —
    the vertices within ``band`` metres of each foot's lowest point, each riding its main bone (128 per
    foot put the lowest within ~3 mm of the skinned mesh's lowest vertex on the CMU clip; 24 left it
    up to 17 mm above)."""
    t = body.template if rest is None else rest
    parents = np.asarray(t.joint_parents)
    main = np.asarray(t.skin_weights).argmax(1)
    joints, points, sides = [], [], []
    for k_side, side in enumerate(SIDES):
        if side + "ankle" not in tgt_index:
            continue
        verts = np.flatnonzero(below(parents, [tgt_index[side + "ankle"]])[main])
        if not len(verts):
            continue
        y = t.vertices[verts, 1]
        sole = verts[np.argsort(y)][: int((y < y.min() + band).sum())]  # lowest first
        sole = sole[np.unique(np.linspace(0, len(sole) - 1, min(per_foot, len(sole))).astype(int))]
        joints.append(main[sole])
        points.append(t.vertices[sole].astype(np.float64))
        sides.append(np.full(len(sole), k_side))
    if not joints:
        raise UvatarError(f"body model '{body.name}' has no mapped ankle to put on the floor")
    return np.concatenate(joints), np.concatenate(points), np.concatenate(sides)


def sole_points(G: np.ndarray, positions: np.ndarray, rest_joints: np.ndarray, landmarks) -> np.ndarray:
    """(T, K, 3) the sole landmarks (:func:`foot_landmarks`) in posed frames: G (T, J, 3, 3) world
    rotations relative to the rest pose, positions (T, J, 3) joints (any origin: the points share it)."""
    lj, lp, _ = landmarks
    out = np.empty((len(positions), len(lj), 3))
    for j in np.unique(lj):  # one product per bone, not a (T, K, 3, 3) gather
        sel = lj == j
        out[:, sel] = positions[:, j, None] + (lp[sel] - rest_joints[j]) @ np.swapaxes(G[:, j], -1, -2)
    return out


def foot_clearance(source, src_index: dict[str, int], floor: float = 0.0) -> np.ndarray:
    """(T, F) per source foot (ankle and everything below it; a foot with no mapped ankle is inf)
    the lowest height above its contact height: joint height minus that joint's 5th percentile
    height over the clip, never below 0 (source units)."""
    out = np.full((source.num_frames, len(SIDES)), np.inf)
    for f, side in enumerate(SIDES):
        if side + "ankle" in src_index:
            y = source.positions[:, below(source.parents, [src_index[side + "ankle"]]), 1] - floor
            out[:, f] = np.maximum((y - np.percentile(y, 5, axis=0)).min(1), 0.0)
    return out


def source_clearance(source, plan, floor: float = 0.0) -> np.ndarray:
    """(T,) how high (source units) the source's feet are above their contact heights: the lower
    foot of :func:`foot_clearance`."""
    if not any(s + "ankle" in plan.src_index for s in SIDES):
        raise UvatarError(f"{source.source or 'source skeleton'}: no ankle is mapped")
    return foot_clearance(source, plan.src_index, floor).min(1)


def horizontal_speed(points: np.ndarray, fps: float) -> np.ndarray:
    """(T, ...) horizontal (XZ) speed of points (T, ..., 3) per frame: central differences, one-sided
    at the ends (units per second)."""
    if points.shape[0] < 2:
        return np.zeros(points.shape[:-1])
    return np.linalg.norm(np.gradient(points[..., [0, 2]], axis=0), axis=-1) * fps


def _runs(mask: np.ndarray) -> np.ndarray:
    """(T, F) bool → (T, F) int: 1-based id of the run of True each frame is in (0 outside)."""
    start = mask & ~np.concatenate([np.zeros_like(mask[:1]), mask[:-1]])
    order = np.cumsum(start.T.ravel()).reshape(mask.T.shape).T  # ids count foot by foot
    return np.where(mask, order, 0)


def detect_contacts(clearance: np.ndarray, speed: np.ndarray, fps: float,
                    config: FootContactConfig | None = None) -> np.ndarray:
    """(T, F) bool contacts from clearance (T, F) metres and horizontal speed (T, F) m/s: runs of
    frames below ``release`` times both thresholds that hold a frame below both thresholds and
    last at least ``min_s``."""
    config = config or FootContactConfig()
    strict = (clearance < config.height_m) & (speed < config.speed_m_s)
    loose = (clearance < config.height_m * config.release) & (speed < config.speed_m_s * config.release)
    ids = _runs(loose)
    n = int(ids.max()) + 1
    holds = np.bincount(ids.ravel(), weights=strict.ravel(), minlength=n) > 0
    length = np.bincount(ids.ravel(), minlength=n)
    keep = holds & (length >= max(1, int(round(config.min_s * fps))))
    keep[0] = False
    return keep[ids]


def segments(mask: np.ndarray) -> np.ndarray:
    """(S, 2) [start, end) frame ranges of the runs of True in a (T,) bool mask."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return np.stack([np.flatnonzero(d == 1), np.flatnonzero(d == -1)], 1)


def source_contacts(source, plan, config: FootContactConfig | None = None) -> np.ndarray:
    """(T, F) bool foot contacts of a source skeleton (:func:`detect_contacts`), its clearance and
    speeds scaled to the target by ``plan.scale`` (metres per source unit)."""
    clear = foot_clearance(source, plan.src_index) * plan.scale
    speed = np.full(clear.shape, np.inf)
    for f, side in enumerate(SIDES):
        if side + "ankle" in plan.src_index:
            foot = source.positions[:, below(source.parents, [plan.src_index[side + "ankle"]])]
            low = foot[np.arange(len(foot)), foot[..., 1].argmin(1)]  # (T, 3) the foot's lowest joint
            speed[:, f] = horizontal_speed(low, source.fps) * plan.scale
    return detect_contacts(clear, speed, source.fps, config)


def lowest_point_tracks(sole: np.ndarray, side: np.ndarray) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """Per foot present: (foot, point (T, 3) its lowest sole point, k (T,) which landmark) from sole
    points (T, K, 3) of :func:`sole_points` and the landmarks' sides (K,)."""
    out = []
    for f in range(len(SIDES)):
        mask = side == f
        if mask.any():
            k = sole[:, mask, 1].argmin(1)
            out.append((f, sole[:, mask][np.arange(len(sole)), k], k))
    return out


def sliding_speeds(sole: np.ndarray, side: np.ndarray, down: np.ndarray, fps: float) -> np.ndarray:
    """Foot sliding (m/s): the horizontal speed of each foot's lowest sole point between two frames
    where that foot is down (``down`` (T, F) bool) and the same sole point is the lowest, all feet
    together (N,)."""
    speeds = []
    for f, point, k in lowest_point_tracks(sole, side):
        both = down[1:, f] & down[:-1, f] & (k[1:] == k[:-1])
        step = np.linalg.norm(point[1:, [0, 2]] - point[:-1, [0, 2]], axis=1)
        speeds.append(step[both] * fps)
    return np.concatenate(speeds) if speeds else np.zeros(0)


__all__ = ["FootContactConfig", "below", "foot_landmarks", "sole_points", "foot_clearance", "source_clearance",
           "horizontal_speed", "detect_contacts", "segments", "source_contacts", "lowest_point_tracks",
           "sliding_speeds"]
