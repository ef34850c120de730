"""How much pose-dependent displacement a synthetic capture holds, and how much of it a map can (issue 38)

    python bench/avh_displacement_signal.py CAP [--texels 64,128,256] [--avatar AVATAR] [--json OUT.json]
                                            [--picture OUT.png]

CAP: a synthetic capture (``uvatar synth`` / ``uvatar demo``'s capture) with ``gt/frames/*.npz``. Reads
only the studio's truth, no bake or avatar: per texel the length of the true clothing offset
(``offset``: garment thickness, static wrinkles, the pose's folds and drape, metres) on the texels
every frame covers. Over the held-out frames (``gt/info.json`` heldout_frames) against the mean map of
the other frames (what an avatar's training frames give):

- ``signal_rms_mm``: the true pose-dependent offset, rms of (held-out frame - mean map) at the gt's
  own resolution: what a displacement R² measures the explained share of;
- per map resolution R (``--texels``): ``perfect_map_error_rms_mm``, the error of each held-out frame's
  own true offset stored at R texels (area-averaged down, bilinear back up, as an avatar's maps are
  compared with the gt); ``mean_map_error_rms_mm``, the mean map stored the same way; and
  ``perfect_map_r2`` = 1 - (perfect map error)² / (mean map error)², the displacement R² (in the offset's
  length) of a generator that predicted every held-out frame's map exactly at that resolution. Static
  detail a map of R texels cannot hold is in both errors, as in ``uvatar eval``'s R².

A bake adds its own noise to each frame's map (the scans' noise along the normal, ``scan_noise`` in the
capture's config, is printed beside); the ceiling ``uvatar eval`` reports (``bake_ceiling``) is below
``perfect_map_r2``. ``--avatar AVATAR`` (exported from a bake of CAP that also baked the held-out frames,
as the demo's does) adds ``own_bake_error``: on the body's cloth texels (hands, head, feet and
uncovered texels left out) the rms 3D error of the frames' own baked maps and of the training mean map
against the true surface, split along the true offset's direction and across it, the frames posed by
their fit refined against the scan as ``uvatar eval`` poses them. ``--picture``: for the first held-out
frame, in UV space (blue below, green 0, red above, ±2 mm): its true pose-dependent offset (frame - mean map), what a
perfect map of the middle ``--texels`` resolution keeps of it, and that map's error (the static detail and
folds it cannot hold). Prints JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass
class Offsets:
    """A synthetic capture's true offset lengths: ``maps`` {frame: (G, G) float32 metres}, ``mask`` (G, G)
    bool the texels every frame covers, the ``held`` out frames, the other (``rest``) frames and their
    ``mean`` map (what an avatar's training frames give)."""

    maps: dict
    mask: np.ndarray
    held: list
    rest: list
    mean: np.ndarray

    @property
    def texels(self) -> int:
        return self.mask.shape[0]

    def stored(self, x: np.ndarray, R: int) -> np.ndarray:
        """A map of R texels compared at the gt's resolution, as ``uvatar eval`` does."""
        from uvatar.avh.data import resample_map

        return resample_map(resample_map(x, R), self.texels) if R != self.texels else x


def load_offsets(capture_root: str | Path) -> Offsets:
    """Read ``gt/frames/*.npz`` once (SystemExit naming the capture when it is not a synthetic one with
    held-out frames)."""
    from uvatar.avh.poses import heldout_frames
    from uvatar.io_utils import read_npz

    root = Path(capture_root)
    maps, mask = {}, None
    for path in sorted((root / "gt" / "frames").glob("*.npz")):
        z = read_npz(path)
        maps[path.stem] = np.linalg.norm(np.asarray(z["offset"], np.float64), axis=-1).astype(np.float32)
        m = np.asarray(z["mask"], bool)
        mask = m if mask is None else mask & m
    if not maps:
        raise SystemExit(f"{root}: no gt/frames/*.npz (a synthetic capture is needed)")
    held = [f for f in heldout_frames(root) if f in maps]
    rest = [f for f in maps if f not in set(held)]
    if not held or not rest:
        raise SystemExit(f"{root}: needs held-out frames and other frames with gt maps")
    return Offsets(maps, mask, held, rest, np.mean([maps[f] for f in rest], axis=0))


def measure(capture_root: str | Path, texels=(64, 128, 256), offsets: Offsets | None = None) -> dict:
    from uvatar.capture.gt import read_gt_info

    root = Path(capture_root)
    o = offsets or load_offsets(root)
    maps, mask, held, mean = o.maps, o.mask, o.held, o.mean
    n = mask.sum() * len(held)
    signal = sum(float(((maps[f] - mean)[mask] ** 2).sum()) for f in held)
    out = {"capture": str(root), "gt_texels": o.texels, "heldout_frames": held, "reference_frames": len(o.rest),
           "texels_scored": int(mask.sum()), "signal_rms_mm": 1000 * np.sqrt(signal / n),
           "scan_noise_mm": 1000 * float((read_gt_info(root).config or {}).get("scan_noise", float("nan"))),
           "resolutions": {}}
    for R in texels:
        perfect = sum(float(((o.stored(maps[f], R) - maps[f])[mask] ** 2).sum()) for f in held)
        mean_err = sum(float(((o.stored(mean, R) - maps[f])[mask] ** 2).sum()) for f in held)
        out["resolutions"][str(R)] = {"perfect_map_error_rms_mm": 1000 * np.sqrt(perfect / n),
                                      "mean_map_error_rms_mm": 1000 * np.sqrt(mean_err / n),
                                      "perfect_map_r2": 1 - perfect / mean_err if mean_err > 0 else None}
    return out


def own_bake_error(capture_root: str | Path, avatar: str | Path, texels: int) -> dict:
    """rms error (mm) along / across the true offset of the own bakes and the training mean map, at the
    gt's ``texels``."""
    from uvatar.avh.data import resample_map
    from uvatar.avh.eval import Baselines, refined_fit
    from uvatar.avh.eval_metrics import predicted_surface
    from uvatar.avh.own_bake import OwnBakes
    from uvatar.avh.poses import heldout_frames
    from uvatar.avh.runtime import AvatarRuntime
    from uvatar.body import part_masks
    from uvatar.capture import Capture
    from uvatar.io_utils import read_npz

    rt = AvatarRuntime(avatar)
    tr = rt.meta["training"]
    base_maps = Baselines(tr["baked"], tr["train_frames"], rt.resolution, rt.conditioning, body=rt.body,
                          displacement_frame=rt.displacement_frame, shape=rt.shape,
                          orientation_root=rt.conditioning[-1])
    own = OwnBakes(tr["baked"], rt.resolution, rt.displacement_frame, rt.body, rt.shape)
    capture = Capture(capture_root)
    sums = {m: np.zeros(3) for m in ("own_bake", "mean_map")}
    count, frames = 0, []
    G = texels
    part = {k: resample_map(v.astype(np.float32), G) > 0.5 for k, v in part_masks(rt.body, rt.resolution).items()}
    static = ((resample_map(base_maps.mean_kappa, G) > 0.5) & ~(part["hands"] | part["feet"] | part["head"])
              & (resample_map((~rt.fingers_toes_mask()).astype(np.float32), G) > 0.5))
    for f in heldout_frames(capture.root):
        bake = own.get(f)
        if bake is None:
            continue
        gt = read_npz(capture.gt_dir / "frames" / f"{f}.npz")
        fit = refined_fit(rt.body, capture.load_fit(f), capture.load_scan(f))
        pose = np.asarray(fit.poses, np.float32).reshape(1, -1)
        Rh = np.asarray(fit.Rh, np.float32).reshape(3)
        shape = np.asarray(fit.shapes, np.float32) if np.size(fit.shapes) else None
        base = rt.posed_vertices(pose, Rh[None], np.asarray(fit.Th, np.float32).reshape(1, 3),
                                 np.array([fit.scale], np.float32), shape)[0]
        rot = rt.skinning_rotations(pose)[0]
        offset = np.asarray(gt["offset"], np.float64)
        length = np.linalg.norm(offset, axis=-1)
        normal = offset / np.maximum(length, 1e-9)[..., None]
        mean_pos, covered = predicted_surface(rt, base, base_maps.mean_displacement, Rh, G, rot)
        own_pos = predicted_surface(rt, base, bake.displacement, Rh, G, rot)[0]
        scored = static & covered & np.asarray(gt["mask"], bool) & (length > 1e-3)
        for m, pos in (("own_bake", own_pos), ("mean_map", mean_pos)):
            e = (pos - np.asarray(gt["surface"], np.float64))[scored]
            along = (e * normal[scored]).sum(-1)
            sums[m] += [float((along ** 2).sum()), float((e ** 2).sum() - (along ** 2).sum()), float((e ** 2).sum())]
        count += int(scored.sum())
        frames.append(f)
    if not count:
        raise SystemExit(f"{avatar}: none of the held-out frames of {capture_root} has its own bake")
    return {"frames": frames, "texels": count, "poses": "each frame's fit refined against its scan",
            **{m: {k: 1000 * float(np.sqrt(v / count)) for k, v in zip(("along_normal_rms_mm", "across_rms_mm",
                                                                            "all_rms_mm"), s, strict=True)}
               for m, s in sums.items()}}


def write_picture(offsets: Offsets, resolution: int, path: str | Path, span_mm: float = 2.0) -> None:
    """Three UV panels of the first held-out frame (see the module docstring), labelled."""
    import cv2

    o = offsets
    frame = o.held[0]
    panels = [("true pose-dependent offset", o.maps[frame] - o.mean),
              (f"a perfect {resolution}^2 map keeps", o.stored(o.maps[frame], resolution) - o.stored(o.mean, resolution)),
              (f"its error at {resolution}^2", o.stored(o.maps[frame], resolution) - o.maps[frame])]
    tiles = []
    for label, x in panels:
        t = np.clip(0.5 + 0.5 * x * 1000 / span_mm, 0, 1)
        rgb = np.stack([t, 1 - np.abs(2 * t - 1), 1 - t], -1)                    # blue - green (0) - red
        rgb = np.where(o.mask[..., None], rgb, 0.15)
        tile = cv2.resize((rgb * 255).astype(np.uint8), (384, 384), interpolation=cv2.INTER_NEAREST)
        tile = np.concatenate([np.full((28, 384, 3), 255, np.uint8), tile])
        cv2.putText(tile, label, (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        tiles.append(tile)
    cv2.imwrite(str(path), np.concatenate(tiles, 1)[..., ::-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture")
    ap.add_argument("--texels", default="64,128,256", help="comma-separated map resolutions")
    ap.add_argument("--avatar", help="an avatar trained on a bake of CAP that baked the held-out frames too")
    ap.add_argument("--json", help="also write the JSON here")
    ap.add_argument("--picture", help="a PNG of the first held-out frame's offsets in UV space")
    args = ap.parse_args(argv)
    sizes = [int(t) for t in args.texels.split(",")]
    offsets = load_offsets(args.capture)
    result = measure(args.capture, sizes, offsets)
    if args.avatar:
        result["own_bake_error"] = own_bake_error(args.capture, args.avatar, offsets.texels)
    if args.picture:
        write_picture(offsets, sizes[len(sizes) // 2], args.picture)
    text = json.dumps(result, indent=1)
    print(text)
    if args.json:
        Path(args.json).write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
