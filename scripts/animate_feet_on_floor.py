"""Where a retargeted clip puts an avatar's soles: the clip retargeted at the body model's default shape
(what ``uvatar animate`` and ``motion convert --avatar`` did before session 25), at the avatar's own
shape, and at it with the avatar's surface (its shoes' displacements) put on the floor (what ``uvatar
animate`` does now), all played on the avatar (its shape, its displacements). Writes a JSON of the
lowest vertex a frame where the source stands, and a side-view sheet with the floor line.

    python scripts/animate_feet_on_floor.py AVATAR CLIP.bvh OUT_DIR [--every 40]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("avatar")
    p.add_argument("clip")
    p.add_argument("out")
    p.add_argument("--every", type=int, default=40, help="every n-th frame of the clip")
    p.add_argument("--size", type=int, default=384)
    args = p.parse_args()
    import cv2

    from uvatar.avh.poses import as_pose_sequence
    from uvatar.avh.runtime import AvatarRuntime
    from uvatar.io_utils import write_image, write_json
    from uvatar.motion.sequences import load_motion, read_skeleton_motion
    from uvatar.render import look_at_camera, render_mesh
    from uvatar.render.cameras import project_points

    out = Path(args.out)
    runtime = AvatarRuntime(args.avatar, levels=1)
    body = runtime.body
    source = read_skeleton_motion(Path(args.clip))
    frames = np.arange(0, source.num_frames, args.every)
    feet = [i for i, n in enumerate(source.names) if n.lower() in ("leftfoot", "rightfoot")]
    ankles = source.positions[frames][:, feet, 1].min(1)
    standing = ankles < np.percentile(ankles, 50)
    report, rows = {"avatar": str(args.avatar), "clip": str(args.clip), "frames": frames.tolist(),
                    "standing": standing.tolist(), "avatar_shape": runtime.shape.tolist()}, []
    offset = runtime.sole_offset()
    report["sole_offset_mm"] = round(offset * 1000, 2)
    for label, shape, lift in (("default_shape_retarget", None, 0.0), ("avatar_shape_retarget", runtime.shape, 0.0),
                               ("avatar_shape_retarget_surface_on_floor", runtime.shape, -offset)):
        seq = as_pose_sequence(load_motion(args.clip, body, shape=shape), body.num_joints, args.clip)
        seq.Th = seq.Th + np.array([0.0, lift, 0.0], np.float32)  # the third: what `uvatar animate` does
        meshes = list(runtime.meshes(seq.poses[frames], seq.Rh[frames], seq.Th[frames], seq.scale[frames]))
        lowest = np.array([m.vertices[:, 1].min() for m in meshes])
        report[label] = {"lowest_vertex_mm_standing": np.round(lowest[standing] * 1000, 1).tolist(),
                         "median_mm": round(float(np.median(lowest[standing]) * 1000), 1),
                         "p90_abs_mm": round(float(np.percentile(np.abs(lowest[standing]), 90) * 1000), 1)}
        row = []
        for k in np.flatnonzero(standing)[:6]:
            m = meshes[k]
            centre = 0.5 * (m.vertices.min(0) + m.vertices.max(0))
            target = np.array([centre[0], 0.35, centre[2]])  # the legs and the floor, from the side
            cam = look_at_camera(target + [1.8, 0.0, 0.0], target, (0, 1, 0), 40.0, args.size, args.size)
            rgb = render_mesh(m.vertices, m.faces, cam, m.uvs, m.uv_faces, m.texture, background=1.0).rgb
            img = (np.clip(rgb, 0, 1) * 255).astype(np.uint8).copy()
            ends, _ = project_points(cam, np.array([[centre[0], 0, centre[2] - 1.0], [centre[0], 0, centre[2] + 1.0]]))
            cv2.line(img, tuple(int(v) for v in ends[0]), tuple(int(v) for v in ends[1]), (220, 30, 30), 2)
            cv2.putText(img, f"{lowest[k] * 1000:+.0f} mm", (8, args.size - 12), cv2.FONT_HERSHEY_SIMPLEX, 0.6,
                        (0, 0, 0), 1, cv2.LINE_AA)
            row.append(img)
        rows.append(np.concatenate(row, 1))
    write_json(out / "feet_on_floor.json", report)
    write_image(out / "feet_on_floor.jpg", np.concatenate(rows, 0))
    print({k: (v["median_mm"], v["p90_abs_mm"]) for k, v in report.items() if isinstance(v, dict)})


if __name__ == "__main__":
    main()
