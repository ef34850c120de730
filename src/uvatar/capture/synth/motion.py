"""Synthetic motion: four takes like the AVH paper's, plus held-out poses, as splined keyframes.

Takes (``TAKE_NAMES``): upper body, arm and head rotations; lower body and walking (a gait cycle on
a circle, then squats, lunges and leg raises); grabbing, pointing and waving; talking with hand
gestures. Each is a set of keyframes over the anatomical DOFs of :mod:`.dofs`, interpolated with a
clamped cubic spline at ``fps`` and clipped to the joint limits, over a slow idle sway. Global
motion: ``Rh`` turns about +Y, ``Th`` moves in the floor plane, and ``Th[1]`` puts the lowest
vertex of every frame on the floor y = 0.

>>> takes = make_takes(load_body_model("anny"), 100, seed=0)   # doctest: +SKIP
>>> takes.poses.shape, takes.ranges()["talking"]              # doctest: +SKIP
((100, 104, 3), (75, 100))
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from uvatar.capture.synth.dofs import Dof, build_dofs, dofs_to_local_rotvecs, neutral_vector

__all__ = ["MotionConfig", "Takes", "TAKE_NAMES", "make_takes", "make_heldout", "concat_takes",
           "ground_translations"]

TAKE_NAMES = ("upper_body", "lower_body", "gestures", "talking")


@dataclass(frozen=True)
class MotionConfig:
    """fps: frames per second; idle_deg: std of the slow sway on every DOF (degrees);
    walk_speed: m/s; walk_radius: radius of the walking circle (m) -- keeps the person inside the
    capture volume; wander: max distance of the idle drift from the origin (m)."""

    fps: float = 25.0
    idle_deg: float = 2.0
    walk_speed: float = 0.6
    walk_radius: float = 0.5
    wander: float = 0.15
    gait_period_s: float = 1.1


@dataclass
class Takes:
    """A motion: poses (N, J, 3) float32 local axis-angles (root zero), Rh (N, 3) axis-angle,
    Th (N, 3) metres; names: take names; take_of_frame (N,) int index into names;
    angles (N, D) the DOF angles in degrees (see :func:`.dofs.build_dofs`)."""

    poses: np.ndarray
    Rh: np.ndarray
    Th: np.ndarray
    names: tuple[str, ...]
    take_of_frame: np.ndarray
    angles: np.ndarray = field(repr=False, default=None)

    def __len__(self) -> int:
        return int(self.poses.shape[0])

    def ranges(self) -> dict[str, tuple[int, int]]:
        """{take name: (first frame, end frame)} (end exclusive; takes are contiguous)."""
        out = {}
        for i, name in enumerate(self.names):
            idx = np.flatnonzero(self.take_of_frame == i)
            if len(idx):
                out[name] = (int(idx[0]), int(idx[-1]) + 1)
        return out


# ---------------------------------------------------------------------------------------------
# keyframe machinery


class _Keys:
    """Keyframes over all DOFs: time (frames) -> {dof index: degrees}; unspecified = neutral."""

    def __init__(self, dofs: list[Dof]):
        self.dofs = dofs
        self.index = {d.name: i for i, d in enumerate(dofs)}
        self.times: list[float] = []
        self.values: list[np.ndarray] = []

    def sel(self, *, group: str | None = None, side: str | None = None) -> list[int]:
        return [i for i, d in enumerate(self.dofs)
                if (group is None or d.group == group)
                and (side is None or d.name.startswith(side + "_"))]

    def add(self, t: float, values: dict[int, float]) -> None:
        row = np.full(len(self.dofs), np.nan)
        for i, v in values.items():
            row[i] = v
        self.times.append(float(t))
        self.values.append(row)

    def evaluate(self, n: int, base: np.ndarray) -> np.ndarray:
        """(n, D) degrees: per DOF a clamped cubic spline through its keys (missing keys: 0 offset
        from ``base``), clipped to the joint limits."""
        from scipy.interpolate import CubicSpline

        order = np.argsort(self.times, kind="stable")
        t = np.asarray(self.times)[order]
        v = np.asarray(self.values)[order]
        t, keep = np.unique(t, return_index=True)
        v = v[keep]
        v = np.where(np.isnan(v), base[None], v)
        frames = np.arange(n, dtype=np.float64)
        if len(t) == 1:
            out = np.repeat(v, n, axis=0)
        else:
            out = CubicSpline(t, v, axis=0, bc_type="clamped")(np.clip(frames, t[0], t[-1]))
        lo = np.array([d.lo for d in self.dofs])
        hi = np.array([d.hi for d in self.dofs])
        return np.clip(out, lo, hi)


def _key_times(n: int, interval: float, rng: np.random.Generator) -> np.ndarray:
    """Keyframe times 0 .. n-1 about ``interval`` frames apart (jittered), at least two."""
    end = max(n - 1, 1)
    count = max(2, int(round(end / max(interval, 1.0))) + 1)
    t = np.linspace(0.0, end, count)
    if count > 2:
        t[1:-1] += rng.uniform(-0.25, 0.25, count - 2) * (end / (count - 1))
    return t


def _uniform(rng, dofs, idx, shrink=0.85, base=None):
    """Uniform angles within each DOF's limits, shrunk toward ``base`` by ``shrink``."""
    out = {}
    for i in idx:
        d = dofs[i]
        b = 0.0 if base is None else float(np.clip(base[i], d.lo, d.hi))
        out[i] = b + shrink * (rng.uniform(d.lo, d.hi) - b)
    return out


def _smooth_noise(rng, n, dims, interval, std):
    """(n, dims) smooth random curves: cubic spline through N(0, std) keys every ``interval``."""
    from scipy.interpolate import CubicSpline

    t = _key_times(n, interval, rng)
    keys = rng.normal(0.0, std, (len(t), dims))
    if n == 1:
        return keys[:1]
    return CubicSpline(t, keys, axis=0, bc_type="clamped")(np.arange(n, dtype=np.float64))


# ---------------------------------------------------------------------------------------------
# the four takes (each returns DOF keyframes; global motion is added separately)


def _take_upper_body(k: _Keys, n, rng, fps, base):
    idx = k.sel(group="spine") + k.sel(group="head") + k.sel(group="arm") + k.sel(group="hand")
    for t in _key_times(n, 0.75 * fps, rng):
        vals = _uniform(rng, k.dofs, idx, 0.85, base)
        for side in ("l", "r"):
            curl = rng.uniform(0, 45)
            vals.update({i: curl + rng.normal(0, 4) for i in k.sel(group="finger", side=side)})
        k.add(t, vals)


def _walk(k: _Keys, n_walk, fps, cfg: MotionConfig, phase0):
    """Procedural gait angles (n_walk, D) in degrees, offsets from the base posture."""
    t = np.arange(n_walk) / fps
    phi = 2 * np.pi * t / cfg.gait_period_s + phase0
    out = np.zeros((n_walk, len(k.dofs)))
    for side, shift in (("l", 0.0), ("r", np.pi)):
        p = phi + shift
        out[:, k.index[f"{side}_hip_fwd"]] = 5 + 22 * np.sin(p)
        out[:, k.index[f"{side}_knee_flex"]] = 8 + 52 * np.clip(np.cos(p), 0, None) ** 2
        out[:, k.index[f"{side}_ankle_flex"]] = 8 * np.sin(p + 0.6)
        out[:, k.index[f"{side}_shoulder_fwd"]] = -18 * np.sin(p)
        out[:, k.index[f"{side}_elbow_flex"]] = 12 + 8 * np.cos(p)
    out[:, k.index["spine2_twist"]] = 4 * np.sin(phi)
    return out


def _take_lower_body(k: _Keys, n, rng, fps, base):
    idx = k.sel(group="leg")
    recipes = ("squat", "lunge_l", "lunge_r", "raise_l", "raise_r", "side_l", "side_r")
    for j, t in enumerate(_key_times(n, 0.8 * fps, rng)):
        if j % 2 == 0:
            k.add(t, {i: rng.normal(0, 3) for i in idx})  # back toward standing
            continue
        kind = recipes[rng.integers(len(recipes))]
        v: dict[int, float] = {}
        if kind == "squat":
            hip, knee = rng.uniform(55, 90), rng.uniform(75, 115)
            for s in ("l", "r"):
                v.update({k.index[f"{s}_hip_fwd"]: hip, k.index[f"{s}_knee_flex"]: knee,
                          k.index[f"{s}_ankle_flex"]: 18, k.index[f"{s}_hip_out"]: rng.uniform(5, 15)})
            v[k.index["spine1_fwd"]] = rng.uniform(10, 20)
            for s in ("l", "r"):
                v[k.index[f"{s}_shoulder_fwd"]] = rng.uniform(40, 80)
        elif kind.startswith("lunge"):
            s, o = kind[-1], "r" if kind[-1] == "l" else "l"
            v.update({k.index[f"{s}_hip_fwd"]: rng.uniform(50, 75), k.index[f"{s}_knee_flex"]: rng.uniform(60, 90),
                      k.index[f"{o}_hip_fwd"]: -rng.uniform(10, 22), k.index[f"{o}_knee_flex"]: rng.uniform(20, 50)})
        elif kind.startswith("raise"):
            s = kind[-1]
            v.update({k.index[f"{s}_hip_fwd"]: rng.uniform(40, 85), k.index[f"{s}_knee_flex"]: rng.uniform(0, 100),
                      k.index[f"{s}_ankle_flex"]: rng.uniform(-25, 20)})
        else:
            s = kind[-1]
            v.update({k.index[f"{s}_hip_out"]: rng.uniform(20, 38), k.index[f"{s}_knee_flex"]: rng.uniform(0, 25)})
        k.add(t, v)


def _finger_sets(k: _Keys, side):
    names = [k.dofs[i].name for i in k.sel(group="finger", side=side)]
    fingers = k.sel(group="finger", side=side)
    # the index finger: anny/MakeHuman "finger2-*", SMPL-X "index*"
    body_names = getattr(k, "joint_names", ())
    index = [i for i, nm in zip(fingers, names, strict=True) if body_names and (
        "finger2" in body_names[k.dofs[i].joint].lower() or "index" in body_names[k.dofs[i].joint].lower())]
    return fingers, index, k.sel(group="thumb", side=side)


def _take_gestures(k: _Keys, n, rng, fps, base):
    span = 1.6 * fps
    starts = np.arange(0.0, max(n - 1, 1), span)
    for g0 in starts:
        kind = ("grab", "point", "wave")[rng.integers(3)]
        s = "l" if rng.random() < 0.5 else "r"
        fingers, index, thumb = _finger_sets(k, s)
        I = k.index
        def rel(f, g0=g0):
            return g0 + f * span
        k.add(rel(0.0), {})
        if kind == "grab":
            reach = {I[f"{s}_shoulder_fwd"]: rng.uniform(55, 80), I[f"{s}_shoulder_raise"]: rng.uniform(-5, 15),
                     I[f"{s}_elbow_flex"]: rng.uniform(-35, -15), **{i: -3.0 for i in fingers + thumb}}
            k.add(rel(0.3), reach)
            k.add(rel(0.55), {**reach, **{i: 78.0 for i in fingers}, **{i: 35.0 for i in thumb}})
            k.add(rel(0.85), {I[f"{s}_shoulder_fwd"]: rng.uniform(15, 35), I[f"{s}_elbow_flex"]: rng.uniform(45, 75),
                              **{i: 78.0 for i in fingers}, **{i: 35.0 for i in thumb}})
        elif kind == "point":
            pose = {I[f"{s}_shoulder_fwd"]: rng.uniform(65, 90), I[f"{s}_shoulder_raise"]: rng.uniform(0, 25),
                    I[f"{s}_elbow_flex"]: -30.0, **{i: 80.0 for i in fingers}, **{i: 0.0 for i in index},
                    **{i: 35.0 for i in thumb}, I["head_turn"]: (1 if s == "l" else -1) * rng.uniform(10, 25)}
            k.add(rel(0.35), pose)
            k.add(rel(0.75), {**pose, I[f"{s}_shoulder_raise"]: pose[I[f"{s}_shoulder_raise"]] + 10})
        else:
            up = {I[f"{s}_shoulder_raise"]: rng.uniform(60, 80), I[f"{s}_shoulder_fwd"]: rng.uniform(5, 20),
                  I[f"{s}_shoulder_twist"]: -55.0, I[f"{s}_elbow_flex"]: rng.uniform(15, 40),
                  **{i: 0.0 for i in fingers + thumb}}
            k.add(rel(0.25), up)
            for j, f in enumerate((0.4, 0.55, 0.7, 0.85)):  # the forearm swings side to side
                sign = 1 if j % 2 == 0 else -1
                k.add(rel(f), {**up, I[f"{s}_shoulder_twist"]: -55.0 + 13.0 * sign, I[f"{s}_wrist_dev"]: 15.0 * sign})
    k.add(float(max(n - 1, 1)), {})


def _take_talking(k: _Keys, n, rng, fps, base):
    I = k.index
    for t in _key_times(n, 0.45 * fps, rng):
        v = {I["head_nod"]: rng.uniform(-8, 12), I["head_turn"]: rng.uniform(-20, 20),
             I["head_tilt"]: rng.uniform(-8, 8), I["neck_nod"]: rng.uniform(-5, 8),
             I["spine3_twist"]: rng.uniform(-6, 6), I["spine2_fwd"]: rng.uniform(-3, 6)}
        active = [("l", "r"), ("l",), ("r",)][rng.integers(3)]
        for s in active:
            v.update({I[f"{s}_shoulder_raise"]: rng.uniform(-28, -8), I[f"{s}_shoulder_fwd"]: rng.uniform(5, 40),
                      I[f"{s}_elbow_flex"]: rng.uniform(25, 75), I[f"{s}_elbow_twist"]: rng.uniform(-40, 40),
                      I[f"{s}_wrist_flex"]: rng.uniform(-25, 25)})
            curl = rng.uniform(0, 55)
            v.update({i: curl + rng.normal(0, 6) for i in k.sel(group="finger", side=s)})
        k.add(t, v)


_RECIPES = {"upper_body": _take_upper_body, "lower_body": _take_lower_body,
            "gestures": _take_gestures, "talking": _take_talking}


def _take_heldout(k: _Keys, n, rng, fps, base):
    idx = [i for i, d in enumerate(k.dofs) if d.group in ("spine", "head", "arm", "hand", "leg")]
    for t in _key_times(n, 0.6 * fps, rng):
        vals = _uniform(rng, k.dofs, idx, 0.75, base)
        for side in ("l", "r"):
            curl = rng.uniform(0, 70)
            vals.update({i: curl for i in k.sel(group="finger", side=side)})
        k.add(t, vals)


# ---------------------------------------------------------------------------------------------


def _global_motion(n, rng, fps, cfg: MotionConfig, walking: int):
    """yaw (n,) radians about +Y and floor position (n, 2) (x, z) metres; the first ``walking``
    frames follow a circle, facing along it."""
    yaw0 = rng.uniform(-np.pi, np.pi)
    yaw = yaw0 + np.radians(_smooth_noise(rng, n, 1, 2.0 * fps, 60.0)[:, 0])
    xz = np.clip(_smooth_noise(rng, n, 2, 2.0 * fps, cfg.wander / 2), -cfg.wander, cfg.wander)
    if walking:
        psi0 = rng.uniform(-np.pi, np.pi)
        direction = 1.0 if rng.random() < 0.5 else -1.0
        psi = psi0 + direction * cfg.walk_speed / cfg.walk_radius * np.arange(walking) / fps
        pos = cfg.walk_radius * np.stack([np.cos(psi), np.sin(psi)], 1)
        vel = direction * np.stack([-np.sin(psi), np.cos(psi)], 1)
        xz[:walking] = pos
        yaw[:walking] = np.arctan2(vel[:, 0], vel[:, 1])
        if walking < n:  # continue smoothly from where the walk ended
            xz[walking:] = pos[-1] + (xz[walking:] - xz[walking])
            yaw[walking:] = yaw[walking - 1] + (yaw[walking:] - yaw[walking])
    return yaw, xz


def _make(body, names, sizes, seed, cfg, shape, recipes):
    dofs = build_dofs(body)
    base = neutral_vector(dofs)
    joint_names = body.template.joint_names
    angles, yaw, xz, take_of_frame = [], [], [], []
    for ti, (name, n) in enumerate(zip(names, sizes, strict=True)):
        if n <= 0:
            continue
        rng = np.random.default_rng([int(seed), 7919, ti, len(names)])
        keys = _Keys(dofs)
        keys.joint_names = joint_names
        recipes[name](keys, n, rng, cfg.fps, base)
        walking = 0
        if name == "lower_body":
            walking = int(round(0.55 * n))
        a = keys.evaluate(n, base)
        if walking:
            gait = _walk(keys, walking, cfg.fps, cfg, rng.uniform(0, 2 * np.pi))
            leg_arm = [i for i, d in enumerate(dofs) if np.any(gait[:, i] != 0)]
            a[:walking, leg_arm] = np.clip(base[leg_arm] + gait[:, leg_arm],
                                           [dofs[i].lo for i in leg_arm], [dofs[i].hi for i in leg_arm])
        a = a + _smooth_noise(rng, n, len(dofs), 1.0 * cfg.fps, cfg.idle_deg)
        a = np.clip(a, [d.lo for d in dofs], [d.hi for d in dofs])
        y, p = _global_motion(n, rng, cfg.fps, cfg, walking)
        angles.append(a)
        yaw.append(y)
        xz.append(p)
        take_of_frame.append(np.full(n, ti))
    angles = np.concatenate(angles)
    yaw = np.concatenate(yaw)
    xz = np.concatenate(xz)
    poses = dofs_to_local_rotvecs(body, dofs, angles)
    Rh = np.zeros((len(yaw), 3), np.float32)
    Rh[:, 1] = yaw
    Th = np.zeros((len(yaw), 3), np.float32)
    Th[:, 0], Th[:, 2] = xz[:, 0], xz[:, 1]
    Th[:, 1] = ground_translations(body, poses, Rh, Th, shape)
    return Takes(poses=poses, Rh=Rh, Th=Th, names=tuple(names), take_of_frame=np.concatenate(take_of_frame),
                 angles=angles.astype(np.float32))


def _split(n: int, parts: int) -> list[int]:
    base, extra = divmod(int(n), parts)
    return [base + (1 if i < extra else 0) for i in range(parts)]


def make_takes(body, n_frames: int, seed: int = 0, config: MotionConfig | None = None, shape=None) -> Takes:
    """The four synthetic takes over ``n_frames`` frames in total (split evenly, in TAKE_NAMES order).

    body: a :class:`uvatar.body.BodyModel`; shape: (S,) body shape (default: the body's default);
    deterministic for a given ``seed``. Returns :class:`Takes`.
    """
    if int(n_frames) < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    cfg = config or MotionConfig()
    return _make(body, TAKE_NAMES, _split(n_frames, len(TAKE_NAMES)), seed, cfg, shape, _RECIPES)


def make_heldout(body, n_frames: int, seed: int = 0, config: MotionConfig | None = None, shape=None) -> Takes:
    """``n_frames`` held-out frames: random full-body keyframe combinations that no take uses
    (one take named "heldout", its own random stream)."""
    cfg = config or MotionConfig()
    return _make(body, ("heldout",), [int(n_frames)], int(seed) + 104729, cfg, shape,
                 {"heldout": _take_heldout})


def concat_takes(a: Takes, b: Takes) -> Takes:
    """``a`` then ``b`` as one motion (take names concatenated)."""
    return Takes(poses=np.concatenate([a.poses, b.poses]), Rh=np.concatenate([a.Rh, b.Rh]),
                 Th=np.concatenate([a.Th, b.Th]), names=a.names + b.names,
                 take_of_frame=np.concatenate([a.take_of_frame, b.take_of_frame + len(a.names)]),
                 angles=np.concatenate([a.angles, b.angles]))


def ground_translations(body, poses, Rh, Th, shape=None, floor_y: float = 0.0, batch: int = 32) -> np.ndarray:
    """(N,) Th[:, 1] values that put each frame's lowest vertex at ``floor_y`` (metres)."""
    import torch

    out = np.zeros(len(poses), np.float32)
    Th0 = np.array(Th, dtype=np.float32, copy=True)
    Th0[:, 1] = 0.0
    with torch.no_grad():
        for s in range(0, len(poses), batch):
            sl = slice(s, s + batch)
            posed = body.pose(torch.as_tensor(poses[sl]), Rh=torch.as_tensor(Rh[sl]), Th=torch.as_tensor(Th0[sl]),
                              shape=None if shape is None else torch.as_tensor(shape, dtype=torch.float32))
            out[sl] = floor_y - posed.vertices[..., 1].amin(-1).cpu().numpy()
    return out
