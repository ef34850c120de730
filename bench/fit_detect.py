"""Seconds for the detection half of `uvatar fit`: BlazePose keypoints on a studio 256^2 image
(upsampled to 512) and on a 1088x1920 portrait frame (the shared real recording's cam01 when present,
else a studio image padded to that size), rendering + detecting a scan's 8 virtual views, the
person segmenter, and triangulation (one frame of 8 views x 33 keypoints; 60 frames batched).
Prints one JSON object.

python bench/fit_detect.py [--repeats 5] [--capture CAP]
The issue's goal for the whole fit is <= 3 s per frame on this 2-core CPU.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

SHARED_VIDEO = Path(__file__).resolve().parents[2] / "shared" / "data" / "pose2sim_single" / "videos" / "cam01.mp4"


def per_call(fn, repeats: int) -> float:
    """Median wall seconds of ``fn()`` over ``repeats`` calls after one warm-up call."""
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def portrait_frame(studio_image: np.ndarray) -> tuple[np.ndarray, str]:
    if SHARED_VIDEO.is_file():
        import imageio.v3 as iio

        frame = next(iter(iio.imiter(SHARED_VIDEO)))
        return frame.astype(np.float32) / 255.0, str(SHARED_VIDEO.name)
    import cv2

    big = cv2.resize(studio_image, (1088, 1088), interpolation=cv2.INTER_CUBIC)
    out = np.ones((1920, 1088, 3), np.float32)
    out[416:1504] = big
    return out, "studio image padded to 1088x1920"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--capture", help="an existing `uvatar synth` capture (default: make a 2-frame one)")
    args = ap.parse_args(argv)

    from uvatar.capture import Capture
    from uvatar.fit import (
        ScanViewsConfig,
        load_detector,
        load_segmenter,
        render_scan_views,
        scan_cameras,
        triangulate,
    )

    tmp = None
    if args.capture:
        root = Path(args.capture)
    else:
        from uvatar.capture.synth.config import preset
        from uvatar.capture.synth.pipeline import synthesize

        tmp = tempfile.TemporaryDirectory()
        root = Path(tmp.name) / "cap"
        synthesize(root, preset("quick", frames=2, cameras=4, image_size=256, seed=0, preview=False),
                   progress=False)
    cap = Capture(root)
    frame = cap.frames[0]
    cam = sorted(cap.cameras())[0]
    studio = cap.load_image(cam, frame)
    portrait, portrait_source = portrait_frame(studio)
    det = load_detector("mediapipe")
    seg = load_segmenter("mediapipe")
    result = {"bench": "fit_detect", "studio_image": list(studio.shape[:2]),
              "detector": det.version, "portrait_source": portrait_source}
    result["detect_s_256_upsampled_512"] = per_call(lambda: det.detect(studio), args.repeats)
    result["detect_s_1088x1920"] = per_call(lambda: det.detect(portrait), args.repeats)
    result["segment_s_256"] = per_call(lambda: seg.segment(studio), args.repeats)
    result["segment_s_1088x1920"] = per_call(lambda: seg.segment(portrait), args.repeats)

    mesh = cap.load_scan(frame)
    cfg = ScanViewsConfig()
    cams = scan_cameras(mesh.vertices, cfg)
    t0 = time.perf_counter()
    views = render_scan_views(mesh, cams, cfg)
    result["scan_views_render_s_per_frame"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    kps = [det.detect(v) for v in views]
    result["scan_views_detect_s_per_frame"] = time.perf_counter() - t0
    result["scan_views"] = {"count": cfg.count, "image_size": cfg.image_size,
                            "detected": int(sum(k.detected for k in kps))}
    xy = np.stack([k.xy for k in kps])
    conf = np.stack([k.conf for k in kps])
    result["triangulate_s_per_frame"] = per_call(lambda: triangulate(xy, conf, cams), args.repeats)
    xy60, conf60 = np.broadcast_to(xy, (60, *xy.shape)), np.broadcast_to(conf, (60, *conf.shape))
    result["triangulate_s_per_frame_batched_60"] = per_call(lambda: triangulate(xy60, conf60, cams), 1) / 60
    det.close()
    seg.close()
    if tmp is not None:
        tmp.cleanup()
    print(json.dumps({k: round(v, 5) if isinstance(v, float) else v for k, v in result.items()}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
