"""Benchmark: seconds per baked frame (AVH stage 1) at 1024^2 texels on a ~110k-face scan.

The scan is the posed anny body (small random pose, fit with 1.5 deg of per-joint noise) subdivided
once (27k -> 110k faces), pushed out along its normals by a clothing-like offset (8-15 mm with folds),
textured with a 1024^2 pattern in the body's UV layout. Prints ONE JSON object to stdout:
seconds_per_frame (mean over the timed frames, excluding the one-off UV raster of the layout and
the registration's normal-smoothing matrix and the surface-texel mask, built once per body) and
a per-stage breakdown; colour_round_seconds_per_frame: one round of the cross-frame colour
refinement on one frame (``uvatar.avh.bake.refine_together``; the bake runs one round per
``photometric_radii`` before baking), and seconds_per_frame_with_colour_rounds the two together;
progress goes to stderr.

    python bench/bake.py [--quick] [--frames 2] [--texels 1024]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np


def make_scan(model, fit, rng):
    from uvatar.avh.bake.frame import shadow_vertices
    from uvatar.capture import TexturedMesh
    from uvatar.geometry import subdivide_midpoint, vertex_normals

    tpl = model.template
    v, f, uv, uvf = subdivide_midpoint(shadow_vertices(model, fit), tpl.faces, tpl.uvs, tpl.uv_faces)
    v = v.astype(np.float64)
    n = vertex_normals(v, f)
    offset = 0.008 + 0.004 * (1 + np.sin(40 * v[:, 1]) * np.cos(25 * v[:, 0])) + rng.normal(0, 0.0003, len(v))
    size = 1024
    y, x = np.mgrid[0:size, 0:size] / size
    tex = np.stack([0.5 + 0.4 * np.sin(40 * x), 0.5 + 0.4 * np.sin(40 * y), 0.4 + 0.2 * x], -1).astype(np.float32)
    return TexturedMesh(v + offset[:, None] * n, f, uv, uvf, tex)


def _colour_round_seconds(model, fit, truth, scan, config) -> float:
    """Seconds of one colour round on one frame: refine ``fit`` against colours sampled at ``truth``."""
    from uvatar.avh.bake.photometric import PhotoTarget
    from uvatar.avh.bake.refine import fit_colours, refine_fit
    from uvatar.avh.bake.register import ScanSurface

    surface = ScanSurface.build(scan.vertices, scan.faces)
    radius = config.pose_refine.photometric_radii[-1]
    reference = fit_colours(model, truth, surface, scan, config.pose_refine, radius)
    target = PhotoTarget(np.nan_to_num(reference), np.isfinite(reference).all(1), radius)
    t0 = time.perf_counter()
    refine_fit(model, fit, surface, config.pose_refine, photo=target, scan_mesh=scan)
    return time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="256 texels, 1 frame")
    ap.add_argument("--frames", type=int, default=2)
    ap.add_argument("--texels", type=int, default=1024)
    ap.add_argument("--device", default="cpu", help="only cpu: the bake has no GPU path")
    args = ap.parse_args(argv)
    texels = 256 if args.quick else args.texels
    frames = 1 if args.quick else args.frames

    from uvatar.avh.bake.config import BakeConfig
    from uvatar.avh.bake.frame import BodyLayout, bake_fit
    from uvatar.body import load_body_model
    from uvatar.capture import BodyFit

    model = load_body_model("anny")
    t0 = time.perf_counter()
    layout = BodyLayout.from_template(model.template, texels)
    layout_seconds = time.perf_counter() - t0
    config = BakeConfig(texels=texels)
    t0 = time.perf_counter()
    layout.normal_smoothing_matrix(config.registration.normal_smoothing)  # once per body, like the raster
    layout.surface_texels(config.interior_visibility, config.visibility_rays)
    per_body_seconds = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    joints = list(model.conditioning_joints)
    totals, stages, kappa, faces = [], {}, [], 0
    for i in range(frames):
        pose = np.zeros((model.num_joints, 3), np.float32)
        pose[joints] = rng.normal(0, 0.1, (len(joints), 3))
        truth = BodyFit(poses=pose.reshape(-1), Rh=[0.0, 0.3 * i, 0.0])
        scan = make_scan(model, truth, rng)
        faces = scan.num_faces
        noise = np.zeros_like(pose)
        noise[joints] = rng.normal(0, np.radians(1.5), (len(joints), 3))
        fit = BodyFit(poses=(pose + noise).reshape(-1), Rh=truth.Rh, Th=truth.Th)
        t0 = time.perf_counter()
        baked, _ = bake_fit(model, fit, layout, scan, config)
        totals.append(time.perf_counter() - t0)
        kappa.append(baked.kappa_mean)
        for k, v in baked.stats["seconds"].items():
            stages.setdefault(k, []).append(v)
        print(f"frame {i}: {totals[-1]:.2f} s, kappa mean {kappa[-1]:.3f}", file=sys.stderr)
    colour_round = _colour_round_seconds(model, fit, truth, scan, config)
    rounds = len(config.pose_refine.photometric_radii)
    print(json.dumps({
        "seconds_per_frame": round(float(np.mean(totals)), 3),
        "colour_round_seconds_per_frame": round(colour_round, 3),
        "colour_rounds": rounds,
        "seconds_per_frame_with_colour_rounds": round(float(np.mean(totals)) + rounds * colour_round, 3),
        "texels": texels,
        "scan_faces": int(faces),
        "frames": frames,
        "stages": {k: round(float(np.mean(v)), 3) for k, v in stages.items()},
        "layout_raster_seconds_once": round(layout_seconds, 3),
        "normal_smoothing_and_surface_texels_seconds_once": round(per_body_seconds, 3),
        "kappa_mean": round(float(np.mean(kappa)), 3),
        "visibility_rays": config.visibility_rays,
        "load_average_1min": round(os.getloadavg()[0], 2),   # the machine is shared: read timings with it
    }))
    return 0


if __name__ == "__main__":
    sys.exit(main())
