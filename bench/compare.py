"""AVH vs DVA on the same frames and cameras: one table (JSON) and optional comparison figures.

Reads the metrics JSON of ``uvatar eval avh ... --frames F --cameras C`` and ``uvatar eval dva``
(both carry the full-image and union-of-masks protocols), plus the two training runs for time and
size, and prints ONE JSON object: per method (AVH, its two baselines, DVA) PSNR/SSIM under both
protocols, training seconds and parameter count. Progress goes to stderr.

``--figures DIR --figure-views 000056:03,000059:07`` also writes, per view, a PNG
``photo | AVH | DVA`` cropped to the person (AVH rendered here with the exported avatar, DVA taken
from the images ``uvatar eval dva`` wrote beside its JSON: photo | render | error).

    python bench/compare.py --avh-json /tmp/cmp/avh_m.json --avh-run /tmp/cmp/run \
        --dva-json /tmp/cmp/dva_m.json --dva-run /tmp/dva_srun2 [--figures docs/results]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

KEYS = ("psnr_db_full", "ssim_full", "psnr_db_union_mask", "ssim_union_mask")


def _load(path) -> dict:
    return json.loads(Path(path).read_text())


def avh_rows(metrics: dict, run_dir, train_seconds: float | None = None) -> dict:
    """Rows for AVH and its baselines from the AVH eval JSON and the AVH run (run.json, history.json,
    done.json when training finished; ``train_seconds`` overrides the run's own count, e.g. the wall
    time over a stop and resume)."""
    run_dir = Path(run_dir) if run_dir else None
    info = _load(run_dir / "run.json") if run_dir else {}
    done = _load(run_dir / "done.json") if run_dir and (run_dir / "done.json").is_file() else {}
    history = _load(run_dir / "history.json") if run_dir and (run_dir / "history.json").is_file() else []
    rows = {"AVH": {**{k: metrics["avh"].get(k) for k in KEYS},
                    "geometry_mm": metrics["avh"].get("geometry_mm"),
                    "train_seconds": train_seconds or done.get("seconds"),
                    "parameters": info.get("parameters") or done.get("parameters"),
                    "epochs": len(history) or done.get("epochs"), "preset": info.get("preset")}}
    for name, m in metrics["baselines"].items():
        rows[f"baseline {name}"] = {**{k: m.get(k) for k in KEYS}, "geometry_mm": m.get("geometry_mm")}
    return rows


def dva_row(metrics: dict, run_dir) -> dict:
    """The DVA row from the DVA eval JSON and the run folder (run.json summary, checkpoint size)."""
    row = {k: metrics.get(k) for k in KEYS}
    if run_dir:
        summary = _load(Path(run_dir) / "run.json").get("summary", {})
        row.update(train_seconds=summary.get("seconds"), steps=summary.get("steps"),
                   parameters=dva_parameters(run_dir))
    return row


def dva_parameters(run_dir) -> int | None:
    import torch

    ckpt = torch.load(Path(run_dir) / "checkpoint.pt", map_location="cpu", weights_only=False)
    state = ckpt.get("model") if isinstance(ckpt, dict) else None
    if not isinstance(state, dict):
        return None
    return int(sum(v.numel() for v in state.values() if hasattr(v, "numel") and v.dtype.is_floating_point))


def figure(avatar, capture_root, dva_metrics: dict, frame: str, camera: str, out_path,
           pose_source: str = "refined") -> dict:
    """Write photo | AVH | DVA for one view, cropped to the person; returns the per-view scores (AVH
    against the photo here; DVA's from its eval JSON, whose union uses alpha > 0.5). The avatar is
    posed from ``pose_source`` as in its eval JSON: "refined" (the fit refined against the frame's
    scan, ``uvatar eval avh``'s default) or "fit" (the capture's fit as it is)."""
    import imageio.v3 as iio

    from uvatar.avh.eval import refined_fit
    from uvatar.avh.eval_metrics import crop_to_masks, image_metrics
    from uvatar.avh.runtime import AvatarRuntime
    from uvatar.capture import Capture
    from uvatar.io_utils import write_image
    from uvatar.render import contact_sheet, render_mesh

    cap = Capture(capture_root)
    cam = cap.cameras()[camera]
    rt = AvatarRuntime(avatar)
    fit = cap.load_fit(frame)
    if pose_source == "refined":
        fit = refined_fit(rt.body, fit, cap.load_scan(frame))
    pose = np.asarray(fit.poses, np.float32).reshape(1, -1)
    Rh = np.asarray(fit.Rh, np.float32).reshape(1, 3)
    shape = np.asarray(fit.shapes, np.float32) if np.size(fit.shapes) else None
    base = rt.posed_vertices(pose, Rh, np.asarray(fit.Th, np.float32).reshape(1, 3),
                             np.array([fit.scale], np.float32), shape)[0]
    tex, disp = rt.generate(pose, Rh=Rh)
    mesh = rt.mesh(base, tex[0], disp[0], Rh[0], pose=pose[0])
    avh = render_mesh(mesh.vertices, mesh.faces, cam, mesh.uvs, mesh.uv_faces, mesh.texture)
    strip = iio.imread(Path(dva_metrics["images"]) / f"{frame}_{camera}.png").astype(np.float32) / 255.0
    w = strip.shape[1] // 3
    dva = strip[:, w:2 * w, :3]
    photo = np.asarray(cap.load_image(camera, frame), np.float32)
    photo = photo / 255.0 if photo.max() > 1.5 else photo
    photo_mask = np.asarray(cap.load_mask(camera, frame)) > 0.5
    dva_mask = np.abs(dva - 1.0).max(-1) > 2 / 255  # for the crop only
    s_dva = next(r for r in dva_metrics["per_image"] if r["frame"] == frame and r["camera"] == camera)
    s_avh = image_metrics(avh.rgb, avh.mask, photo, photo_mask)
    crops = crop_to_masks([photo, avh.rgb, dva], [photo_mask, avh.mask, dva_mask], height=256)
    labels = ["photo", f"AVH {s_avh['psnr_db_full']:.1f}/{s_avh['psnr_db_union_mask']:.1f} dB",
              f"DVA {s_dva['psnr_db_full']:.1f}/{s_dva['psnr_db_union_mask']:.1f} dB"]
    write_image(out_path, contact_sheet(crops, cols=3, labels=labels))
    return {"frame": frame, "camera": camera, "avh": s_avh, "dva": s_dva, "path": str(out_path)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--avh-json", required=True)
    ap.add_argument("--dva-json", required=True)
    ap.add_argument("--avh-run", default=None, help="AVH training run (done.json: seconds, parameters)")
    ap.add_argument("--avh-train-seconds", type=float, default=None, help="AVH training wall time")
    ap.add_argument("--dva-run", default=None, help="DVA run (run.json, checkpoint.pt)")
    ap.add_argument("--figures", default=None, help="write comparison PNGs here")
    ap.add_argument("--figure-views", default="000056:03,000059:07", help="frame:camera list")
    ap.add_argument("--avatar", default=None, help="exported avatar (default: the AVH JSON's)")
    ap.add_argument("--capture", default=None, help="capture (default: the AVH JSON's)")
    ap.add_argument("--quick", action="store_true", help="no figures")
    args = ap.parse_args(argv)
    avh, dva = _load(args.avh_json), _load(args.dva_json)
    same = {"frames": avh.get("frames") == dva.get("frames"),
            "cameras": (avh.get("camera_names") or []) == dva.get("cameras")}
    if not all(same.values()):
        print(f"warning: AVH and DVA were not evaluated on the same views: {same}", file=sys.stderr)
    out = {"frames": dva.get("frames"), "cameras": dva.get("cameras"), "same_views": same,
           "methods": {**avh_rows(avh, args.avh_run, args.avh_train_seconds), "DVA": dva_row(dva, args.dva_run)},
           "protocol": {"avh": avh.get("protocol"), "dva": dva.get("protocol")}}
    if args.figures and not args.quick:
        views = [v.split(":") for v in args.figure_views.split(",") if v]
        out["figures"] = []
        for frame, cam in views:
            print(f"figure {frame} camera {cam}", file=sys.stderr)
            out["figures"].append(figure(args.avatar or avh["avatar"], args.capture or avh["capture"],
                                         dva, frame, cam, Path(args.figures) / f"{frame}_{cam}.png",
                                         avh.get("pose_source", "fit")))
    print(json.dumps(out, indent=2, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
