"""Ground-truth clothing geometry: a scalar offset along the posed body normal per surface point.

``offset = base + static wrinkles + sum_k amplitude_k * bend_k * fold_k`` (metres): shirt about
1 cm, trousers about 1.5 cm, belt, shoes, and hair (thicker on top); skin and eyes 0. Folds are
rings around the limb at the elbows and knees (stronger on the inner side), diagonal folds at the
groin, bunching at the armpits when the arm hangs, and horizontal belly folds when the chest bends;
each follows its joint's bend (:func:`.bends.bend_amounts`). The clothed surface point is
``posed body point + offset * garment normal``, where the garment normal is the posed body normal
averaged over the cloth's bending length, and cloth (shirt, trousers, belt) is thicker by the
bridged depth of body creases (:mod:`.drape`); the offset vector in world space is
``offset * garment normal``, plus the tangential drift of sleeves and trouser legs toward bending
elbows and knees (:mod:`.drift`). Offsets stay below ``ClothingConfig.max_offset``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uvatar.capture.synth.appearance import Regions
from uvatar.capture.synth.bends import BENDS, limb_coordinates, smoothstep, value_noise
from uvatar.capture.synth.surface import BodyLandmarks, SurfaceFeatures

__all__ = ["ClothingConfig", "base_offset", "cloth_weight", "fold_maps", "offset_amount"]


@dataclass(frozen=True)
class ClothingConfig:
    """Thicknesses and fold amplitudes in metres; fold wavelength in metres.

    Drape (:mod:`.drape`): bending_length (m, sigma of the garment-normal averaging; 0 = the body
    normal and no bridging, as in captures made before the drape); drape_normal_dot: neighbours
    with less rest-normal agreement are not averaged; bridge: fraction of a crease's depth the cloth
    spans; max_bridge (m): cap on the bridged extra thickness.

    Drift (:mod:`.drift`): drift_elbow, drift_knee (m): peak slide of the sleeve / trouser fabric
    toward a fully bent elbow / knee on its convex side; drift_length (m): distance from the joint
    of the peak. 0 amplitudes: no drift (captures made before the drift)."""

    shirt: float = 0.010
    trousers: float = 0.015
    belt: float = 0.017
    shoes: float = 0.006
    hair: float = 0.012
    hair_top: float = 0.012       # extra hair volume on the crown
    wrinkle: float = 0.003        # static cloth wrinkles
    fold_amplitude: tuple = (0.010, 0.010, 0.011, 0.011, 0.008, 0.008, 0.007, 0.007, 0.009)  # per BENDS
    fold_wavelength: float = 0.028
    max_offset: float = 0.045
    bending_length: float = 0.03
    drape_normal_dot: float = 0.3
    bridge: float = 0.8
    max_bridge: float = 0.02
    drift_elbow: float = 0.005
    drift_knee: float = 0.006
    drift_length: float = 0.04


def base_offset(f: SurfaceFeatures, L: BodyLandmarks, reg: Regions, cfg: ClothingConfig | None = None) -> np.ndarray:
    """(N,) float32 pose-independent offset (metres): garment thickness plus static wrinkles."""
    cfg = cfg or ClothingConfig()
    crown = L["head"][1] + 0.06
    hair = reg.hair * (cfg.hair + cfg.hair_top * smoothstep(crown, crown + 0.07, f.p[:, 1]))
    cloth = reg.shirt + reg.jeans + reg.belt
    wrinkles = cfg.wrinkle * (value_noise(f.p, (30.0, 12.0, 30.0), seed=3) - 0.5) * 2 * cloth
    out = (reg.shirt * cfg.shirt + reg.jeans * cfg.trousers + reg.belt * cfg.belt + reg.shoe * cfg.shoes
           + hair + wrinkles)
    return np.clip(out, 0, None).astype(np.float32)


def fold_maps(f: SurfaceFeatures, L: BodyLandmarks, reg: Regions, cfg: ClothingConfig | None = None) -> np.ndarray:
    """(N, K) float32 static fold shapes in [0, 1] per ``BENDS`` slot (multiplied by the bend
    amount and amplitude in :func:`offset_amount`)."""
    cfg = cfg or ClothingConfig()
    p = f.p
    lam = cfg.fold_wavelength
    out = np.zeros((len(p), len(BENDS)))

    def ripple(u, phase=0.0):
        return 0.5 + 0.5 * np.cos(2 * np.pi * u / lam + phase)

    def blob(center, sigma):
        return np.exp(-np.sum((p - center) ** 2, 1) / (2 * sigma**2))

    for s in ("l", "r"):
        sign = 1.0 if s == "l" else -1.0
        sh, el, wr = L[f"{s}_shoulder"], L[f"{s}_elbow"], L[f"{s}_wrist"]
        along, angle, _ = limb_coordinates(p, sh, wr)
        el_along = limb_coordinates(el[None], sh, wr)[0][0]
        inner = (p - el) @ (-(el - sh) / np.linalg.norm(el - sh) + (wr - el) / np.linalg.norm(wr - el))
        weight = np.exp(-((along - el_along) ** 2) / (2 * 0.06**2)) * (0.4 + 0.6 * smoothstep(-0.02, 0.03, inner))
        weight = weight * f.g(f"upperarm_{s}", f"forearm_{s}")
        out[:, BENDS.index(f"{s}_elbow")] = reg.shirt * weight * ripple(along - el_along + 0.01 * np.sin(2 * angle))
        hip, kn, an = L[f"{s}_hip"], L[f"{s}_knee"], L[f"{s}_ankle"]
        along, angle, _ = limb_coordinates(p, hip, an)
        kn_along = limb_coordinates(kn[None], hip, an)[0][0]
        back = smoothstep(-0.3, 0.8, np.sin(angle))  # limb angle pi/2 is the back of the leg
        weight = np.exp(-((along - kn_along) ** 2) / (2 * 0.07**2)) * (0.35 + 0.65 * back)
        weight = weight * f.g(f"thigh_{s}", f"shin_{s}")
        out[:, BENDS.index(f"{s}_knee")] = reg.jeans * weight * ripple(along - kn_along + 0.012 * np.cos(angle))
        groin = hip + np.array([0.0, -0.04, 0.05])
        diag = p[:, 1] + 0.6 * sign * (p[:, 0] - hip[0])
        mine = smoothstep(-0.02, 0.01, sign * p[:, 0])  # this side of the body
        out[:, BENDS.index(f"{s}_hip")] = (reg.jeans * mine * blob(groin, 0.07) * smoothstep(-0.01, 0.03, p[:, 2] - hip[2])
                                           * ripple(diag))
        pit = sh + np.array([-0.02 * sign, -0.09, 0.0])
        radial = np.arctan2(p[:, 2] - pit[2], sign * (p[:, 0] - pit[0]))
        out[:, BENDS.index(f"{s}_armpit")] = reg.shirt * blob(pit, 0.06) * (0.5 + 0.5 * np.cos(5 * radial))
    chest = L["spine2"]
    out[:, BENDS.index("spine")] = (reg.shirt * np.exp(-((p[:, 1] - chest[1] - 0.03) ** 2) / (2 * 0.08**2))
                                    * smoothstep(0.0, 0.05, p[:, 2] - chest[2]) * ripple(p[:, 1]))
    return out.astype(np.float32)


def offset_amount(base: np.ndarray, folds: np.ndarray, bends: np.ndarray,
                  cfg: ClothingConfig | None = None, bridged: np.ndarray | None = None) -> np.ndarray:
    """(N,) float64 offset in metres of one pose: base (N,) + folds (N, K) @ (amplitude * bends) (K,)
    + bridged (N,) (cloth weight x bridged crease depth, :mod:`.drape`), clipped to [0, max_offset]."""
    cfg = cfg or ClothingConfig()
    amp = np.asarray(cfg.fold_amplitude, dtype=np.float64) * np.asarray(bends, dtype=np.float64)
    out = base.astype(np.float64) + folds.astype(np.float64) @ amp
    if bridged is not None:
        out = out + bridged
    return np.clip(out, 0.0, cfg.max_offset)


def cloth_weight(reg: Regions) -> np.ndarray:
    """(N,) float32 in [0, 1]: how much a point is garment (shirt, trousers, belt), which bridges creases."""
    return np.clip(reg.shirt + reg.jeans + reg.belt, 0.0, 1.0).astype(np.float32)
