"""Body fit on a `uvatar synth` capture from simulated detections; prints one JSON object.

Keypoints: the TRUE body keypoints (``BodyKeypoints`` on the true pose and shape) projected into the
capture's cameras (with distortion), plus Gaussian pixel noise, undistorted and triangulated by a
plain DLT here (the real detector and triangulation live in uvatar.fit.keypoints / triangulate).
Modes: ``images`` (3D keypoints + 2D keypoints + masks) and ``scans`` (3D keypoints + scans).

    PYTHONPATH=src python bench/fit_body.py /tmp/cap --mode scans --noise-px 7
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch


def dlt(xy: np.ndarray, cameras) -> np.ndarray:
    """xy (T, C, K, 2) undistorted pixels -> (T, K, 3) least-squares DLT points."""
    P = np.stack([c.K @ np.concatenate([c.R, c.T[:, None]], 1) for c in cameras])      # (C, 3, 4)
    rows = np.concatenate([xy[..., 0:1, None] * P[None, :, None, 2:3] - P[None, :, None, 0:1],
                           xy[..., 1:2, None] * P[None, :, None, 2:3] - P[None, :, None, 1:2]], -2)
    T, C, K = xy.shape[:3]
    A = rows.transpose(0, 2, 1, 3, 4).reshape(T, K, 2 * C, 4)
    _, _, vt = np.linalg.svd(A)
    X = vt[..., -1, :]
    return X[..., :3] / X[..., 3:4]


def main(argv=None) -> int:
    import cv2

    from uvatar.body import load_body_model
    from uvatar.capture.layout import Capture
    from uvatar.capture.types import BodyFit
    from uvatar.fit.body_fit import BodyFitConfig, FitObservations, fit_body_sequence
    from uvatar.fit.body_keypoints import BodyKeypoints
    from uvatar.fit.evaluate import evaluate_fits
    from uvatar.fit.projection import camera_tensors, project_cameras
    from uvatar.geometry.frames import vertex_normals
    from uvatar.io_utils import read_npz

    ap = argparse.ArgumentParser()
    ap.add_argument("capture")
    ap.add_argument("--mode", choices=("scans", "images"), default="scans")
    ap.add_argument("--noise-px", type=float, default=7.0)
    ap.add_argument("--frames", type=int, default=0, help="first N frames (0: all)")
    ap.add_argument("--iterations", default="")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", nargs="*", default=[], help="config overrides key=value")
    args = ap.parse_args(argv)

    torch.set_num_threads(max(1, torch.get_num_threads()))
    cap = Capture(args.capture)
    body = load_body_model(cap.body_model)
    frames = cap.frames[: args.frames or None]
    cams = list(cap.cameras().values())
    kp = BodyKeypoints(body)
    gts = [read_npz(cap.gt_dir / "frames" / f"{f}.npz") for f in frames]
    true = [BodyFit(poses=g["pose"], Rh=g["Rh"], Th=g["Th"]) for g in gts]
    shape = torch.as_tensor(cap.body_shapes)
    with torch.no_grad():
        posed = body.pose(torch.as_tensor(np.stack([body.joint_rotvecs_from_fit(f) for f in true])),
                          Rh=torch.as_tensor(np.stack([f.Rh for f in true])),
                          Th=torch.as_tensor(np.stack([f.Th for f in true])), shape=shape)
        k3 = kp(posed)
        px, z = project_cameras(k3.double(), camera_tensors(cams, dtype=torch.float64))   # (T, C, K, 2)
    rng = np.random.default_rng(args.seed)
    px = px.numpy() + rng.normal(0, args.noise_px, px.shape)
    T, C, K = px.shape[:3]
    und = np.stack([cv2.undistortPoints(px[:, c].reshape(-1, 1, 2), cams[c].K, cams[c].dist, P=cams[c].K)
                    .reshape(T, K, 2) for c in range(C)], 1)
    t0 = time.time()
    tri = dlt(und, cams)
    t_tri = time.time() - t0
    conf = np.tile((kp.weights > 0).astype(np.float32), (T, 1))
    obs = FitObservations(keypoints3d=tri.astype(np.float32), keypoints3d_conf=conf)
    if args.mode == "images":
        obs.keypoints2d = px.astype(np.float32)
        obs.keypoints2d_conf = np.tile(conf[:, None], (1, C, 1))
        obs.cameras = cams
        obs.masks = [[cap.load_mask(c.name, f) > 0.5 for c in cams] for f in frames]
    else:
        scans = []
        for f in frames:
            m = cap.load_scan(f)
            scans.append((m.vertices, vertex_normals(m.vertices.astype(np.float64), m.faces)))
        obs.scans = scans
    overrides = {}
    for kv in args.set:
        k, v = kv.split("=")
        overrides[k] = type(getattr(BodyFitConfig(), k))(float(v)) if not isinstance(getattr(BodyFitConfig(), k), bool) \
            else v.lower() in ("1", "true")
    if args.iterations:
        overrides["iterations"] = tuple(int(x) for x in args.iterations.split(","))
    cfg = BodyFitConfig(**overrides)
    t0 = time.time()
    import sys

    fit = fit_body_sequence(body, obs, cfg, progress=lambda d, n, info: print(
        f"{d}/{n} {info['stage']} loss {info['loss']:.3g} {time.time() - t0:.0f}s", file=sys.stderr))
    t_fit = time.time() - t0
    fits = dict(zip(frames, fit.body_fits(), strict=True))
    ev = evaluate_fits(body, cap, fits, fit.shape)
    studio = evaluate_fits(body, cap, {f: cap.load_fit(f) for f in frames}, None)
    kp_err = float(np.linalg.norm(tri - k3.numpy(), axis=-1).mean() * 1000)
    print(json.dumps({
        "mode": args.mode, "frames": T, "noise_px": args.noise_px, "triangulation_error_mm": kp_err,
        "mpjpe_mm": ev["mpjpe_mm"], "angle_error_deg": ev["angle_error_deg"],
        "scan_to_body_median_mm": ev.get("scan_to_body_median_mm"), "scan_to_body_p90_mm": ev.get("scan_to_body_p90_mm"),
        "shape_error_mm": ev["shape_error_mm"], "shape": ev["shape"],
        "studio_fits": {"mpjpe_mm": studio["mpjpe_mm"], "scan_to_body_median_mm": studio.get("scan_to_body_median_mm"),
                        "scan_to_body_p90_mm": studio.get("scan_to_body_p90_mm")},
        "seconds_per_frame_fit": t_fit / T, "seconds_per_frame_triangulation": t_tri / T,
        "losses": fit.losses, "config": overrides,
        "worst_joints_mm": dict(sorted(ev["per_joint_mpjpe_mm"].items(), key=lambda x: -x[1])[:6]),
    }, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
