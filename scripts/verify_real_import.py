"""Check an imported real capture's cameras against the images (ad hoc; needs mediapipe).

    PYTHONPATH=src python scripts/verify_real_import.py CAPTURE [--frames 0,50,99] [--out docs/real_import.png]

1. Geometry: camera centres, the point nearest to all optical axes and each axis' distance to it,
   the world origin (a floor point for a floor-based calibration) projected into every view.
2. MediaPipe pose (``mediapipe.solutions.pose``) on each camera's image of each frame; the 33
   landmarks triangulated by DLT from the undistorted pixels of every camera that sees them, and
   reprojected (with distortion): the mean / median pixel error per camera, and for the hips.
   Variants of the calibration (distortion as imported, /64 as Pose2Sim reads it, none; cam01/02's
   1080-vs-1088 taken as a crop or as a scale) are scored the same way.
Prints one JSON object and writes a picture of the views with the reprojected keypoints.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from uvatar.capture.layout import Capture
from uvatar.capture.types import Camera
from uvatar.geometry.camera import undistort


def detect(images: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """{cam: (33, 3) pixels x, y and visibility} (NaN rows where no person was found)."""
    import mediapipe as mp

    out = {}
    with mp.solutions.pose.Pose(static_image_mode=True, model_complexity=1) as pose:
        for cam, img in images.items():
            res = pose.process(np.ascontiguousarray((img * 255).astype(np.uint8)))
            h, w = img.shape[:2]
            if res.pose_landmarks is None:
                out[cam] = np.full((33, 3), np.nan)
                continue
            lm = res.pose_landmarks.landmark
            out[cam] = np.array([[p.x * w, p.y * h, p.visibility] for p in lm])
    return out


def triangulate(cams: list[Camera], pix: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """DLT: cams (C,), pix (C, J, 2) distorted pixels, weight (C, J) → (J, 3) world points."""
    rows = []
    for cam, p, w in zip(cams, pix, weight, strict=True):
        Kinv = np.linalg.inv(cam.K)
        und = undistort(p @ Kinv[:2, :2].T + Kinv[:2, 2], cam.dist)
        P = np.hstack([cam.R, cam.T[:, None]])  # normalized camera
        w = np.where(np.isfinite(w), w, 0.0)[:, None]
        und = np.nan_to_num(und)
        rows.append(w * (und[:, :1] * P[2] - P[0]))
        rows.append(w * (und[:, 1:2] * P[2] - P[1]))
    A = np.stack(rows, axis=1)  # (J, 2C, 4)
    X = np.linalg.svd(A)[2][:, -1]
    return X[:, :3] / X[:, 3:]


def reproject(cam: Camera, X: np.ndarray) -> np.ndarray:
    return cam.project(X.reshape(-1, 3))


# MediaPipe's left/right landmark pairs: seen from behind it may label them the other way round
_LEFT = [1, 2, 3, 7, 9, 11, 13, 15, 17, 19, 21, 23, 25, 27, 29, 31]
_RIGHT = [4, 5, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30, 32]
_SWAP = np.arange(33)
_SWAP[_LEFT], _SWAP[_RIGHT] = _RIGHT, _LEFT


def solve_frame(cams: list[Camera], pix: np.ndarray, weight: np.ndarray):
    """Triangulate with each camera's left/right labels kept or swapped (2^C choices), keeping the
    labelling whose median reprojection error is lowest → (X (J, 3), pix, weight) as labelled."""
    import itertools

    best = None
    for flips in itertools.product((False, True), repeat=len(cams) - 1):
        flips = (False,) + flips  # the first camera fixes the labelling
        p = np.stack([q[_SWAP] if f else q for q, f in zip(pix, flips, strict=True)])
        w = np.stack([q[_SWAP] if f else q for q, f in zip(weight, flips, strict=True)])
        X = triangulate(cams, p, w)
        e = np.stack([np.linalg.norm(reproject(c, X) - q, axis=1) for c, q in zip(cams, p, strict=True)])
        med = float(np.median(e[w > 0]))
        if best is None or med < best[0]:
            best = (med, X, p, w)
    return best[1:]


def score(cams: dict[str, Camera], dets: list[dict[str, np.ndarray]], min_vis: float = 0.5) -> dict:
    names = list(cams)
    errs = {n: [] for n in names}
    hips = []
    for det in dets:
        pix = np.stack([det[n][:, :2] for n in names])
        vis = np.stack([det[n][:, 2] for n in names])
        weight = np.where(vis > min_vis, 1.0, 0.0)
        ok = weight.sum(0) >= 2
        X, pix, weight = solve_frame([cams[n] for n in names], pix, weight)
        for c, n in enumerate(names):
            e = np.linalg.norm(reproject(cams[n], X) - pix[c], axis=1)
            sel = ok & (weight[c] > 0)
            errs[n].extend(e[sel].tolist())
            hips.extend(e[[23, 24]][sel[[23, 24]]].tolist())
    allv = np.concatenate([np.asarray(v) for v in errs.values()])
    return {"mean_px": round(float(allv.mean()), 2), "p90_px": round(float(np.percentile(allv, 90)), 2), "median_px": round(float(np.median(allv)), 2),
            "hips_mean_px": round(float(np.mean(hips)), 2),
            "per_camera_mean_px": {n: round(float(np.mean(v)), 2) for n, v in errs.items()},
            "observations": int(allv.size)}


def geometry(cams: dict[str, Camera]) -> dict:
    centres = np.stack([c.center for c in cams.values()])
    axes = np.stack([c.R[2] for c in cams.values()])
    # least-squares point nearest to all optical axes
    A = sum(np.eye(3) - np.outer(a, a) for a in axes)
    b = sum((np.eye(3) - np.outer(a, a)) @ c for a, c in zip(axes, centres, strict=True))
    p = np.linalg.solve(A, b)
    dist = [float(np.linalg.norm((np.eye(3) - np.outer(a, a)) @ (p - c))) for a, c in zip(axes, centres, strict=True)]
    origin = {n: [round(float(v), 1) for v in reproject(c, np.zeros((1, 3)))[0]] for n, c in cams.items()}
    return {"centres_m": {n: np.round(c.center, 3).tolist() for n, c in cams.items()},
            "axes_meet_near_m": np.round(p, 3).tolist(), "axis_distance_m": [round(d, 3) for d in dist],
            "looks_toward_meeting_point": [bool(c.R[2] @ (p - c.center) > 0) for c in cams.values()],
            "world_origin_px": origin}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("capture")
    ap.add_argument("--frames", default="0,25,50,75,99")
    ap.add_argument("--out", default="docs/real_import.png")
    args = ap.parse_args()
    cap = Capture(args.capture)
    cams = cap.cameras()
    frames = [f"{int(f):06d}" for f in args.frames.split(",")]
    frames = [f for f in frames if f in cap.frames]
    images = {f: {n: cap.load_image(n, f) for n in cams} for f in frames}
    dets = [detect(images[f]) for f in frames]
    variants = {"as imported": cams,
                "distortion / 64 (Pose2Sim)": {n: Camera(n, c.K, c.R, c.T, c.width, c.height, c.dist / 64)
                                               for n, c in cams.items()},
                "no distortion": {n: Camera(n, c.K, c.R, c.T, c.width, c.height) for n, c in cams.items()}}
    scaled = {}
    for n, c in cams.items():
        if c.width == 1080:  # calibrated 1088 wide: try "resized" instead of "cropped"
            K = c.K.copy()
            K[0] *= 1080 / 1088
            scaled[n] = Camera(n, K, c.R, c.T, c.width, c.height, c.dist)
        else:
            scaled[n] = c
    variants["1080 as a scale of 1088"] = scaled
    report = {"frames": frames, "geometry": geometry(cams),
              "reprojection": {k: score(v, dets) for k, v in variants.items()}}
    print(json.dumps(report, indent=1))
    # picture: first frame, every view, detected (green) and reprojected (red) keypoints + world axes
    det = dets[0]
    names = list(cams)
    weight = np.stack([np.where(det[n][:, 2] > 0.5, 1.0, 0.0) for n in names])
    X = solve_frame([cams[n] for n in names], np.stack([det[n][:, :2] for n in names]), weight)[0]
    tiles = []
    for n in names:
        img = (images[frames[0]][n] * 255).astype(np.uint8).copy()
        for p in det[n][:, :2]:
            if np.all(np.isfinite(p)):
                cv2.circle(img, tuple(int(v) for v in p), 9, (0, 255, 0), 3)
        for p in reproject(cams[n], X):
            cv2.drawMarker(img, tuple(int(v) for v in p), (255, 0, 0), cv2.MARKER_CROSS, 22, 4)
        o = reproject(cams[n], np.array([[0, 0, 0], [0.5, 0, 0], [0, 0.5, 0], [0, 0, 0.5]], float))
        for k, col in ((1, (255, 0, 0)), (2, (0, 255, 0)), (3, (0, 0, 255))):
            cv2.line(img, tuple(int(v) for v in o[0]), tuple(int(v) for v in o[k]), col, 6)
        cv2.putText(img, n, (20, 70), cv2.FONT_HERSHEY_SIMPLEX, 2.2, (255, 255, 0), 5)
        tiles.append(cv2.resize(img, (img.shape[1] * 640 // img.shape[0], 640), interpolation=cv2.INTER_AREA))
    sheet = np.concatenate(tiles, axis=1)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(args.out, cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    # the world origin (a floor landmark of the calibration) up close: 300 px around it, x2
    crops = []
    for n, c in cams.items():
        img = (images[frames[0]][n] * 255).astype(np.uint8)
        o = reproject(c, np.array([[0, 0, 0], [0.6, 0, 0], [0, 0, -0.6]], float))
        x, y = np.round(o[0]).astype(int)
        pad = np.pad(img, ((150, 150), (150, 150), (0, 0)))
        crop = pad[y:y + 300, x:x + 300].copy()
        for k, col in ((1, (255, 0, 0)), (2, (0, 0, 255))):
            end = np.round(o[k] - o[0] + 150).astype(int)
            cv2.line(crop, (150, 150), (int(end[0]), int(end[1])), col, 1)
        cv2.drawMarker(crop, (150, 150), (255, 0, 0), cv2.MARKER_CROSS, 30, 2)
        crops.append(cv2.resize(crop, (600, 600), interpolation=cv2.INTER_NEAREST))
    cv2.imwrite(str(Path(args.out).with_name(Path(args.out).stem + "_origin.png")),
                cv2.cvtColor(np.concatenate(crops, axis=1), cv2.COLOR_RGB2BGR))


if __name__ == "__main__":
    main()
