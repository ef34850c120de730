"""Benchmark: seconds per frame of ``uvatar fit`` — detection, triangulation and the body fit — from
scans (8 virtual views per scan) and from a capture's 4 calibrated images.

Runs on a studio capture (``uvatar synth``; made in a temporary folder when none is given) with
the MediaPipe detector (``uvatar[fit]``). Prints ONE JSON object to stdout; progress on stderr.

    python bench/fit.py [--capture CAP] [--frames 8] [--device cpu]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

import numpy as np


def _timed_source(capture, frames, source, views_cfg, detector, tri_cfg, body, body_cfg):
    from dataclasses import replace

    from uvatar.fit.body_fit import FitObservations, fit_body_sequence
    from uvatar.fit.people import frame_views
    from uvatar.fit.pipeline import FitConfig, FitStages
    from uvatar.fit.triangulate import triangulate
    from uvatar.fit.views import scan_photo_views
    from uvatar.geometry.sampling import sample_surface

    stages = FitStages(views=views_cfg)
    t_views = t_detect = t_tri = t_photo = 0.0
    k3, c3, scans, photo = [], [], [], []
    photo_cfg = replace(views_cfg, image_size=FitConfig().photo_size)
    views = 0
    for frame in frames:
        t0 = time.perf_counter()
        images, cameras = frame_views(capture, frame, source, stages)
        t1 = time.perf_counter()
        dets = [detector.detect(img) for img in images]
        t2 = time.perf_counter()
        xy = np.stack([d.xy for d in dets])
        conf = np.stack([d.conf for d in dets])
        tri = triangulate(xy, conf, cameras, tri_cfg)
        t3 = time.perf_counter()
        t_views += t1 - t0
        t_detect += t2 - t1
        t_tri += t3 - t2
        views = len(cameras)
        k3.append(tri.points)
        c3.append(tri.conf)
        if source == "scans":  # images alone is what a video capture has
            mesh = capture.load_scan(frame)
            scans.append(sample_surface(mesh.vertices, mesh.faces, 3000))
            t0 = time.perf_counter()
            photo.append(scan_photo_views(mesh, photo_cfg))   # the texture stage's unshaded views
            t_photo += time.perf_counter() - t0
    obs = FitObservations(keypoints3d=np.stack(k3), keypoints3d_conf=np.stack(c3), scans=scans or None,
                          photo=photo or None)
    t0 = time.perf_counter()
    fit_body_sequence(body, obs, body_cfg)
    t_fit = time.perf_counter() - t0
    n = len(frames)
    return {"views": views, "render_views_s_per_frame": t_views / n, "detection_s_per_frame": t_detect / n,
            "detection_s_per_image": t_detect / (n * views), "triangulation_s_per_frame": t_tri / n,
            "photo_views_s_per_frame": t_photo / n, "fit_s_per_frame": t_fit / n,
            "total_s_per_frame": (t_views + t_detect + t_tri + t_photo + t_fit) / n}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--capture", default=None, help="a uvatar capture with scans and images (default: synth)")
    ap.add_argument("--frames", type=int, default=8, help="frames timed (the fit is batched over them)")
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args(argv)

    from uvatar.body.registry import load_body_model
    from uvatar.capture.layout import Capture
    from uvatar.fit.body_fit import BodyFitConfig
    from uvatar.fit.keypoints import DetectorConfig, load_detector
    from uvatar.fit.triangulate import TriangulateConfig
    from uvatar.fit.views import ScanViewsConfig

    tmp = None
    root = args.capture
    if root is None:
        tmp = tempfile.TemporaryDirectory()
        root = os.path.join(tmp.name, "cap")
        from uvatar.capture.synth.config import preset
        from uvatar.capture.synth.pipeline import synthesize

        print("making a studio capture ...", file=sys.stderr)
        synthesize(root, preset("default", frames=args.frames + 1, heldout=0, cameras=4, image_size=256,
                                preview=False), progress=False)
    capture = Capture(root)
    frames = [f for f in capture.frames if capture.has_scan(f)][: args.frames]
    body = load_body_model("anny", device=args.device)
    detector = load_detector("mediapipe", DetectorConfig())
    tri_cfg, body_cfg = TriangulateConfig(), BodyFitConfig()
    detector.detect(np.zeros((64, 64, 3), np.float32))  # model load outside the timing
    out = {"benchmark": "fit", "device": args.device, "frames": len(frames), "torch_threads": None,
           "scans": _timed_source(capture, frames, "scans", ScanViewsConfig(), detector, tri_cfg, body, body_cfg)}
    if capture.has_cameras():
        out["images"] = _timed_source(capture, frames, "images", ScanViewsConfig(), detector, tri_cfg, body,
                                      body_cfg)
    import torch

    out["torch_threads"] = torch.get_num_threads()
    out["goal_s_per_frame"] = 3.0
    print(json.dumps(out, indent=2))
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
