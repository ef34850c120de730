"""Benchmark: seconds per baked frame (AVH stage 1) at 1024^2 texels on a ~110k-face scan.

The scan is the posed anny body (small random pose, fit with 1.5 deg of per-joint noise) subdivided
once (27k -> 110k faces), pushed out along its normals by a clothing-like offset (8-15 mm with folds),
textured with a 1024^2 pattern in the body's UV layout. Prints ONE JSON object to stdout:
seconds_per_frame (mean over the timed frames, excluding the one-off UV raster of the layout and
the registration's normal-smoothing matrix and the surface-texel mask, built once per body), a
per-stage breakdown of seconds and of rays cast (``stages``, ``rays``; ``rays_per_second`` of the ray
stages); colour_round_seconds_per_frame: one round of the cross-frame colour refinement on one frame
as the bake runs it (:func:`uvatar.avh.bake.refine_together._refine_task`: refine against the
reference, then sample the colours for the next round; the bake runs one round per
``photometric_radii``), and seconds_per_frame_with_colour_rounds the two together;
frames_per_hour (one process) from it. progress goes to stderr.

``--reference`` also times, in the same run, what the bake did before issue 27 for the stages that
changed: the scan's visibility cast for every matched texel's faces (now only where kappa's other
factors are not zero), and each colour round reading the scan file and preparing it again (now kept
by the worker, :func:`uvatar.avh.bake.inputs.prepared_scan`); ``reference`` holds those seconds and
the old total, and ``speedup`` the ratio (the machine may be shared: compare within one run).
``--device cuda`` runs the ray stages through Warp on the GPU.

    python bench/bake.py [--quick] [--frames 2] [--texels 1024] [--reference] [--device cpu|cuda]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

RAY_STAGES = ("correspond", "visibility_registered", "visibility_scan")   # stages whose time is mostly rays


class Clock:
    """Wall and this process's CPU seconds of a block (the machine may be shared with other jobs:
    the CPU seconds of a single-threaded bake are what it costs on an idle core)."""

    def __enter__(self):
        self.t0, self.c0 = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        self.wall, self.cpu = time.perf_counter() - self.t0, time.process_time() - self.c0


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


def _colour_round(model, fit, truth, scan, surface, config) -> tuple[Clock, int]:
    """(Clock, rays) of one colour round on one frame as the bake runs it: refine ``fit`` against
    colours sampled at ``truth``, then sample the colours at the refined fit for the next round."""
    from uvatar.avh.bake.photometric import PhotoTarget
    from uvatar.avh.bake.refine import fit_colours, refine_fit
    from uvatar.geometry import rays_cast
    from uvatar.threads import single_threaded

    radius = config.pose_refine.photometric_radii[-1]
    with single_threaded():
        reference = fit_colours(model, truth, surface, scan, config.pose_refine, radius)
        target = PhotoTarget(np.nan_to_num(reference), np.isfinite(reference).all(1), radius)
        r0 = rays_cast()
        with Clock() as clock:
            refined, _ = refine_fit(model, fit, surface, config.pose_refine, photo=target, scan_mesh=scan)
            fit_colours(model, refined, surface, scan, config.pose_refine, radius)
        return clock, rays_cast() - r0


def _reference_seconds(scan, surface, baked_matches, config) -> dict:
    """Clocks of the pre-issue-27 computations of the changed stages, in this process."""
    from uvatar.avh.bake.confidence import vertex_visibility
    from uvatar.avh.bake.register import ScanSurface
    from uvatar.capture import read_mesh, write_mesh
    from uvatar.threads import single_threaded

    face, hit = baked_matches
    with single_threaded():
        with Clock() as visibility:
            vertex_visibility(surface.vertices, surface.faces, surface.caster, config.visibility_rays,
                              config.ray_epsilon, needed=surface.faces[face[hit]].ravel())
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "scan.obj"
            write_mesh(path, scan)
            with Clock() as reload:
                again = read_mesh(path)
                ScanSurface.build(again.vertices, again.faces, config.device, config.ray_backend)
    return {"visibility_scan": visibility, "scan_read_and_prepare_per_round": reload}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="256 texels, 1 frame")
    ap.add_argument("--frames", type=int, default=2, help="frames timed (frames_per_hour comes from their mean)")
    ap.add_argument("--texels", type=int, default=1024)
    ap.add_argument("--device", default="cpu", help="cpu (Embree) or cuda[:N] (the ray stages through Warp)")
    ap.add_argument("--reference", action="store_true",
                    help="also time the changed stages as they ran before issue 27 (same process)")
    args = ap.parse_args(argv)
    texels = 256 if args.quick else args.texels
    frames = 1 if args.quick else args.frames

    from uvatar.avh.bake.config import BakeConfig
    from uvatar.avh.bake.correspond import match_texels
    from uvatar.avh.bake.frame import BodyLayout, bake_fit
    from uvatar.avh.bake.register import ScanSurface
    from uvatar.body import load_body_model
    from uvatar.capture import BodyFit

    model = load_body_model("anny")
    t0 = time.perf_counter()
    layout = BodyLayout.from_template(model.template, texels)
    layout_seconds = time.perf_counter() - t0
    config = BakeConfig(texels=texels, device=args.device)
    t0 = time.perf_counter()
    layout.normal_smoothing_matrix(config.registration.normal_smoothing)  # once per body, like the raster
    layout.surface_texels(config.interior_visibility, config.visibility_rays)
    per_body_seconds = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    joints = list(model.conditioning_joints)
    totals, cpu_totals, stages, cpu_stages, rays, kappa, faces, rounds, rounds_r, refs = [], [], {}, {}, {}, [], 0, [], [], []
    for i in range(frames):
        pose = np.zeros((model.num_joints, 3), np.float32)
        pose[joints] = rng.normal(0, 0.1, (len(joints), 3))
        truth = BodyFit(poses=pose.reshape(-1), Rh=[0.0, 0.3 * i, 0.0])
        scan = make_scan(model, truth, rng)
        faces = scan.num_faces
        noise = np.zeros_like(pose)
        noise[joints] = rng.normal(0, np.radians(1.5), (len(joints), 3))
        fit = BodyFit(poses=(pose + noise).reshape(-1), Rh=truth.Rh, Th=truth.Th)
        with Clock() as clock:
            baked, used = bake_fit(model, fit, layout, scan, config)
        totals.append(clock.wall)
        cpu_totals.append(clock.cpu)
        kappa.append(baked.kappa_mean)
        for k, v in baked.stats["seconds"].items():
            stages.setdefault(k, []).append(v)
        for k, v in baked.stats["cpu_seconds"].items():
            cpu_stages.setdefault(k, []).append(v)
        for k, v in baked.stats["rays"].items():
            rays.setdefault(k, []).append(v)
        surface = ScanSurface.build(scan.vertices, scan.faces, config.device, config.ray_backend)  # kept by the worker
        round_clock, cast = _colour_round(model, fit, truth, scan, surface, config)
        rounds.append(round_clock)
        rounds_r.append(cast)
        if args.reference:
            from uvatar.avh.bake.frame import shadow_vertices
            from uvatar.geometry import vertex_normals

            # the texel matches of the baked frame, for the old visibility's face set
            reg = shadow_vertices(model, used)
            r = layout.at_texels(reg)
            n = layout.at_texels(vertex_normals(reg, layout.faces))
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
            m = match_texels(r, n, surface, config.polarity_rule, config.polarity_ratio, config.max_match_distance,
                             config.ray_epsilon)
            refs.append(_reference_seconds(scan, surface, (m.face, m.hit), config))
        print(f"frame {i}: {totals[-1]:.2f} s ({cpu_totals[-1]:.2f} s CPU) + colour round {round_clock.wall:.2f} s "
              f"({round_clock.cpu:.2f} s CPU), kappa mean {kappa[-1]:.3f}", file=sys.stderr)
    n_rounds = len(config.pose_refine.photometric_radii)
    per_frame, cpu_frame = float(np.mean(totals)), float(np.mean(cpu_totals))
    colour_round = float(np.mean([c.wall for c in rounds]))
    cpu_round = float(np.mean([c.cpu for c in rounds]))
    with_rounds = per_frame + n_rounds * colour_round
    cpu_with_rounds = cpu_frame + n_rounds * cpu_round
    stage_mean = {k: float(np.mean(v)) for k, v in stages.items()}
    cpu_stage = {k: float(np.mean(v)) for k, v in cpu_stages.items()}
    ray_mean = {k: int(np.mean(v)) for k, v in rays.items() if np.mean(v)}
    out = {
        "seconds_per_frame": round(per_frame, 3),
        "colour_round_seconds_per_frame": round(colour_round, 3),
        "colour_rounds": n_rounds,
        "seconds_per_frame_with_colour_rounds": round(with_rounds, 3),
        "frames_per_hour": round(3600.0 / with_rounds, 1),
        "cpu_seconds_per_frame_with_colour_rounds": round(cpu_with_rounds, 3),
        "frames_per_hour_per_idle_core": round(3600.0 / cpu_with_rounds, 1),
        "device": args.device,
        "texels": texels,
        "scan_faces": int(faces),
        "frames": frames,
        "stages": {k: round(v, 3) for k, v in stage_mean.items()},
        "cpu_stages": {k: round(v, 3) for k, v in cpu_stage.items()} | {"colour_round": round(cpu_round, 3)},
        "rays": {**ray_mean, "colour_round": int(np.mean(rounds_r))},
        "rays_per_frame_with_colour_rounds": int(sum(ray_mean.values()) + n_rounds * np.mean(rounds_r)),
        "million_rays_per_cpu_second": {k: round(ray_mean[k] / cpu_stage[k] / 1e6, 2) for k in RAY_STAGES
                                        if ray_mean.get(k) and cpu_stage.get(k)},
        "layout_raster_seconds_once": round(layout_seconds, 3),
        "normal_smoothing_and_surface_texels_seconds_once": round(per_body_seconds, 3),
        "kappa_mean": round(float(np.mean(kappa)), 3),
        "visibility_rays": config.visibility_rays,
        "load_average_1min": round(os.getloadavg()[0], 2),   # the machine is shared: read timings with it
    }
    if refs:
        ref = {k: (float(np.mean([r[k].wall for r in refs])), float(np.mean([r[k].cpu for r in refs])))
               for k in refs[0]}
        vis, reload = ref["visibility_scan"], ref["scan_read_and_prepare_per_round"]
        old = per_frame - stage_mean["visibility_scan"] + vis[0] + n_rounds * (colour_round + reload[0])
        old_cpu = cpu_frame - cpu_stage["visibility_scan"] + vis[1] + n_rounds * (cpu_round + reload[1])
        out["reference"] = {"visibility_scan": round(vis[0], 3), "cpu_visibility_scan": round(vis[1], 3),
                            "scan_read_and_prepare_per_round": round(reload[0], 3),
                            "cpu_scan_read_and_prepare_per_round": round(reload[1], 3),
                            "seconds_per_frame_with_colour_rounds": round(old, 3),
                            "cpu_seconds_per_frame_with_colour_rounds": round(old_cpu, 3)}
        out["speedup"] = round(old / with_rounds, 3)
        out["cpu_speedup"] = round(old_cpu / cpu_with_rounds, 3)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
