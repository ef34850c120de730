"""Ground-truth appearance: a clothed person's albedo and pose-dependent creases, on body features.

Regions come from rest positions and skinning groups (:mod:`.surface`): a plaid shirt with rolled
sleeves, buttons and a collar; jeans with a belt; shoes with soles; skin; hair; eyes, brows and
lips. Patterns live in body-surface coordinates (height and arc around the torso, length and angle
along each arm), so they are continuous across UV seams. All colours are linear RGB in [0, 1].

Pose dependence (:func:`shade`): ``albedo * prod_k (1 - strength_k * bend_k * crease_k)``, with
crease maps at the inner elbows, the backs of the knees, the groin, the armpits and the belly, and
bends from :func:`.bends.bend_amounts`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uvatar.capture.synth.bends import BENDS, limb_coordinates, smoothstep, value_noise
from uvatar.capture.synth.surface import BodyLandmarks, SurfaceFeatures

__all__ = ["AppearanceConfig", "Regions", "regions", "albedo", "crease_maps", "crease_factor", "shade"]


@dataclass(frozen=True)
class AppearanceConfig:
    """Palette (RGB in [0, 1]) and pattern sizes (metres)."""

    shirt: tuple = (0.70, 0.12, 0.10)
    shirt_band: tuple = (0.08, 0.09, 0.20)
    shirt_line: tuple = (0.95, 0.85, 0.45)
    plaid_period: float = 0.09
    plaid_band: float = 0.03
    plaid_line: float = 0.006
    jeans: tuple = (0.17, 0.26, 0.46)
    belt: tuple = (0.25, 0.14, 0.07)
    shoe: tuple = (0.13, 0.11, 0.10)
    sole: tuple = (0.88, 0.87, 0.84)
    skin: tuple = (0.85, 0.64, 0.52)
    lips: tuple = (0.70, 0.34, 0.34)
    hair: tuple = (0.20, 0.12, 0.07)
    iris: tuple = (0.25, 0.42, 0.55)
    sleeve_fraction: float = 0.55   # rolled sleeves end this far down the forearm
    waist_above_hip: float = 0.07   # waistline height above the hip joints (m)
    crease_strength: tuple = (0.5, 0.5, 0.5, 0.5, 0.4, 0.4, 0.55, 0.55, 0.35)  # per BENDS slot


@dataclass
class Regions:
    """Soft region masks (N,) in [0, 1]: shirt, jeans, belt, shoe, hair, eye, skin (the rest), plus
    the shirt's plaid coordinates (N, 2) in metres."""

    shirt: np.ndarray
    jeans: np.ndarray
    belt: np.ndarray
    shoe: np.ndarray
    hair: np.ndarray
    eye: np.ndarray
    skin: np.ndarray
    plaid_uv: np.ndarray


def _arm_coords(f: SurfaceFeatures, L: BodyLandmarks, side: str):
    along, angle, _ = limb_coordinates(f.p, L[f"{side}_shoulder"], L[f"{side}_wrist"])
    return along, angle


def regions(f: SurfaceFeatures, L: BodyLandmarks, cfg: AppearanceConfig) -> Regions:
    p = f.p
    y = p[:, 1]
    arm = f.g("upperarm_l", "forearm_l", "upperarm_r", "forearm_r")
    hand = f.g("hand_l", "hand_r")
    head = f.g("head")
    eye = f.g("eye")
    leg = f.g("thigh_l", "shin_l", "thigh_r", "shin_r")
    foot = f.g("foot_l", "foot_r")
    waist = 0.5 * (L["l_hip"][1] + L["r_hip"][1]) + cfg.waist_above_hip
    ankle = 0.5 * (L["l_ankle"][1] + L["r_ankle"][1])
    collar = L["neck"][1] - 0.025 - 0.03 * smoothstep(0.0, 0.06, p[:, 2] - L["neck"][2])
    off_neck = np.hypot(p[:, 0] - L["neck"][0], p[:, 2] - L["neck"][2])  # distance from the neck axis

    shoe = np.clip(foot + leg * smoothstep(ankle + 0.075, ankle + 0.055, y), 0, 1)
    lower_body = smoothstep(waist + 0.004, waist - 0.004, y) * np.clip(1 - arm - hand - head - eye, 0, 1)
    jeans = lower_body * (1 - shoe)
    belt = jeans * smoothstep(waist - 0.04, waist - 0.033, y)
    jeans = jeans - belt

    # sleeves: along the arm up to a fraction of the forearm; plaid coordinates per limb
    plaid = np.stack([y, np.arctan2(p[:, 0], p[:, 2]) * 0.15], 1)
    sleeve = np.zeros(len(p))
    for side in ("l", "r"):
        mine = f.g(f"upperarm_{side}", f"forearm_{side}")
        along, angle = _arm_coords(f, L, side)
        elbow_along = limb_coordinates(L[f"{side}_elbow"][None], L[f"{side}_shoulder"], L[f"{side}_wrist"])[0][0]
        wrist_along = np.linalg.norm(L[f"{side}_wrist"] - L[f"{side}_shoulder"])
        end = elbow_along + cfg.sleeve_fraction * (wrist_along - elbow_along)
        sleeve += mine * smoothstep(end + 0.004, end - 0.004, along)
        use = mine > 0.5
        plaid[use] = np.stack([along[use], angle[use] * 0.045], 1)
    torso = f.g("torso", "neck") * smoothstep(waist - 0.004, waist + 0.004, y) * np.maximum(
        smoothstep(collar + 0.004, collar - 0.004, y), smoothstep(0.07, 0.078, off_neck))
    shirt = np.clip(torso + sleeve, 0, 1) * (1 - eye)

    # hair: a skull-centred hairline, low at the back, high at the forehead
    c = L["head"] + np.array([0.0, 0.06, -0.01])
    d = p - c
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    score = d[:, 1] - 0.42 + 0.9 * np.clip(-d[:, 2], 0, None) + 0.25 * np.abs(d[:, 0])
    score = score + 0.06 * (value_noise(p, 90.0) - 0.5)
    hair = head * smoothstep(-0.02, 0.02, score) * (1 - eye)
    skin = np.clip(1 - shirt - jeans - belt - shoe - hair - eye, 0, 1)
    return Regions(shirt=shirt, jeans=jeans, belt=belt, shoe=shoe, hair=hair, eye=eye, skin=skin, plaid_uv=plaid)


def _band(u, period, width, soft=0.0015):
    """1 inside stripes of ``width`` repeating every ``period`` (metres), soft edges."""
    frac = np.mod(u / period, 1.0)
    dist = np.minimum(frac, 1 - frac) * period
    return smoothstep(width / 2 + soft, width / 2 - soft, dist)


def _mix(a, b, t):
    return a + (np.asarray(b, dtype=np.float64) - a) * np.asarray(t)[:, None]


def albedo(f: SurfaceFeatures, L: BodyLandmarks, cfg: AppearanceConfig | None = None,
           reg: Regions | None = None) -> np.ndarray:
    """(N, 3) float32 pose-independent colour of each surface point."""
    cfg = cfg or AppearanceConfig()
    reg = reg or regions(f, L, cfg)
    p = f.p
    n = len(p)
    ones = np.ones((n, 1))

    # shirt: plaid + placket with buttons
    a, b = reg.plaid_uv[:, 0], reg.plaid_uv[:, 1]
    P, W = cfg.plaid_period, cfg.plaid_band
    shirt = ones * np.asarray(cfg.shirt)
    shirt = _mix(shirt, cfg.shirt_band, 0.5 * _band(a, P, W))
    shirt = _mix(shirt, cfg.shirt_band, 0.5 * _band(b, P, W))
    lines = np.maximum(_band(a + P / 2, P, cfg.plaid_line), _band(b + P / 2, P, cfg.plaid_line))
    shirt = _mix(shirt, cfg.shirt_line, 0.75 * lines)
    front = smoothstep(0.0, 0.03, p[:, 2] - L["spine3"][2])
    placket = front * smoothstep(0.0035, 0.0025, np.abs(p[:, 0]))
    button = front * smoothstep(0.0045, 0.0035, np.hypot(p[:, 0], _centred_mod(p[:, 1] - 0.02, 0.08)))
    shirt = _mix(shirt, np.asarray(cfg.shirt) * 0.6, 0.5 * placket)
    shirt = _mix(shirt, (0.92, 0.9, 0.85), button)
    shirt *= (0.93 + 0.1 * value_noise(p, 150.0))[:, None]

    # jeans: mottled denim, faded thigh fronts, orange outer-seam stitching
    denim = ones * np.asarray(cfg.jeans) * (0.85 + 0.25 * value_noise(p, (250.0, 40.0, 250.0)))[:, None]
    for side, outer in (("l", np.pi), ("r", 0.0)):  # limb angle 0 is -X, pi/2 the back (see limb_coordinates)
        along, angle, _ = limb_coordinates(p, L[f"{side}_hip"], L[f"{side}_ankle"])
        leg = f.g(f"thigh_{side}", f"shin_{side}")
        fade = leg * smoothstep(0.5, 1.0, np.cos(angle + np.pi / 2)) * smoothstep(0.05, 0.2, along)
        denim = _mix(denim, np.asarray(cfg.jeans) * 1.5, 0.35 * fade)
        seam = leg * smoothstep(0.05, 0.03, np.abs(_wrap(angle - outer)))
        denim = _mix(denim, (0.85, 0.55, 0.2), 0.6 * seam)
    belt = ones * np.asarray(cfg.belt)
    buckle = smoothstep(0.03, 0.02, np.abs(p[:, 0])) * smoothstep(0.0, 0.03, p[:, 2] - L["spine1"][2])
    belt = _mix(belt, (0.78, 0.72, 0.55), buckle)

    shoe = ones * np.asarray(cfg.shoe)
    shoe = _mix(shoe, cfg.sole, smoothstep(L.floor_y + 0.022, L.floor_y + 0.016, p[:, 1]))

    skin = ones * np.asarray(cfg.skin) * (0.95 + 0.1 * value_noise(p, 60.0))[:, None]
    skin = _mix(skin, cfg.lips, _lips(p, L))
    skin = _mix(skin, cfg.hair, _brows(p, L))
    hair = ones * np.asarray(cfg.hair) * (0.7 + 0.6 * value_noise(p, (500.0, 30.0, 500.0)))[:, None]
    eye = _eyes(p, L, cfg)

    out = (reg.shirt[:, None] * shirt + reg.jeans[:, None] * denim + reg.belt[:, None] * belt
           + reg.shoe[:, None] * shoe + reg.hair[:, None] * hair + reg.eye[:, None] * eye + reg.skin[:, None] * skin)
    return np.clip(out, 0, 1).astype(np.float32)


def _wrap(a):
    return np.mod(a + np.pi, 2 * np.pi) - np.pi


def _centred_mod(x, period):
    return np.mod(x + period / 2, period) - period / 2


def _face_front(p, L, depth=0.03):
    eye_z = 0.5 * (L["l_eye"][2] + L["r_eye"][2])
    return smoothstep(eye_z - depth, eye_z - depth + 0.01, p[:, 2])


def _lips(p, L):
    eye_y = 0.5 * (L["l_eye"][1] + L["r_eye"][1])
    my = eye_y - 0.07
    r = (p[:, 0] / 0.024) ** 2 + ((p[:, 1] - my) / 0.0085) ** 2
    return smoothstep(1.1, 0.9, r) * _face_front(p, L)


def _brows(p, L):
    out = np.zeros(len(p))
    for s in ("l", "r"):
        e = L[f"{s}_eye"]
        dx = (p[:, 0] - e[0]) / 0.022
        dy = p[:, 1] - (e[1] + 0.024 - 0.006 * dx ** 2)
        out = np.maximum(out, smoothstep(1.1, 0.9, np.abs(dx)) * smoothstep(0.0045, 0.003, np.abs(dy)))
    return 0.85 * out * _face_front(p, L)


def _eyes(p, L, cfg):
    out = np.ones((len(p), 3)) * 0.93
    for s in ("l", "r"):
        d = p - L[f"{s}_eye"]
        near = np.linalg.norm(d, axis=1) < 0.03
        cosang = d[:, 2] / np.maximum(np.linalg.norm(d, axis=1), 1e-9)
        iris = near * smoothstep(0.86, 0.9, cosang)
        pupil = near * smoothstep(0.96, 0.975, cosang)
        out = _mix(out, cfg.iris, iris)
        out = _mix(out, (0.03, 0.03, 0.03), pupil)
    return out


def crease_maps(f: SurfaceFeatures, L: BodyLandmarks) -> np.ndarray:
    """(N, K) static crease weights in [0, 1] per ``BENDS`` slot (inner elbow, knee back, groin,
    armpit, belly)."""
    p = f.p
    out = np.zeros((len(p), len(BENDS)))

    def blob(center, sigma):
        return np.exp(-np.sum((p - center) ** 2, 1) / (2 * sigma**2))

    def side_of(center, direction, lo=-0.1, hi=0.6):
        d = p - center
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
        return smoothstep(lo, hi, d @ (direction / np.linalg.norm(direction)))

    for _k, s in enumerate(("l", "r")):
        sign = 1.0 if s == "l" else -1.0
        sh, el, wr = L[f"{s}_shoulder"], L[f"{s}_elbow"], L[f"{s}_wrist"]
        u, fo = (el - sh) / np.linalg.norm(el - sh), (wr - el) / np.linalg.norm(wr - el)
        arm = f.g(f"upperarm_{s}", f"forearm_{s}")
        out[:, BENDS.index(f"{s}_elbow")] = arm * blob(el, 0.045) * side_of(el, -u + fo)
        kn = L[f"{s}_knee"]
        leg = f.g(f"thigh_{s}", f"shin_{s}")
        out[:, BENDS.index(f"{s}_knee")] = leg * blob(kn, 0.05) * side_of(kn, np.array([0, 0, -1.0]))
        hip = L[f"{s}_hip"] + np.array([0.0, -0.03, 0.03])
        out[:, BENDS.index(f"{s}_hip")] = blob(hip, 0.06) * side_of(hip, np.array([-0.3 * sign, 0.2, 1.0]), 0.0, 0.7)
        pit = sh + np.array([-0.025 * sign, -0.075, -0.01])
        out[:, BENDS.index(f"{s}_armpit")] = blob(pit, 0.045) * (1 - f.g("head", "hand_l", "hand_r"))
    belly = L["spine2"] + np.array([0.0, 0.02, 0.1])
    out[:, BENDS.index("spine")] = blob(belly, 0.08) * side_of(L["spine2"], np.array([0, 0, 1.0]), 0.2, 0.8)
    return out.astype(np.float32)


def shade(albedo_rgb: np.ndarray, creases: np.ndarray, bends: np.ndarray,
          cfg: AppearanceConfig | None = None) -> np.ndarray:
    """(N, 3) float32 texture of one pose: albedo (N, 3) darkened by creases (N, K) x bends (K,)."""
    return (albedo_rgb * crease_factor(creases, bends, cfg)[:, None]).astype(np.float32)


def crease_factor(creases: np.ndarray, bends: np.ndarray, cfg: AppearanceConfig | None = None) -> np.ndarray:
    """(N,) float64 darkening of one pose: prod_k (1 - strength_k * bend_k * creases (N, K))."""
    cfg = cfg or AppearanceConfig()
    strength = np.asarray(cfg.crease_strength, dtype=np.float64) * np.asarray(bends, dtype=np.float64)
    return np.prod(1.0 - creases * strength[None, :], axis=1)
