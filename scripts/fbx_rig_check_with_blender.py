"""Pose an exported avatar's skinned FBX (``AVATAR/avatar.fbx``) in Blender and compare Blender's own
skinning with uvatar's reference skinning of the same rig (``engine.skin_reference``, the GLB's).

    python scripts/fbx_rig_check_with_blender.py AVATAR --blender BPY_PYTHON [--poses 3] [--sigma 0.4]
        [--motion MOTION --frames 5]

Each pose: every joint turned by a random rotation vector (``--sigma`` radians a component); Blender
(``scripts/fbx_rig_blender_pose.py``: the FBX imported by Blender's importer, each bone posed by the same
world change in Blender's axes, the mesh evaluated) against the reference. Prints one JSON object: per
pose the largest and median vertex distance (mm) and how far the pose moved the body (mm).

``--motion``: also the motion (any ``uvatar motion`` source) written by ``uvatar motion convert MOTION
OUT.fbx --avatar AVATAR`` and played by Blender (``scripts/fbx_anim_blender_frames.py``), its first
``--frames`` keys against the reference skinning with the motion's global rotation and translation.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import tempfile
from pathlib import Path

import numpy as np


def main() -> None:
    from scipy.spatial.transform import Rotation

    from uvatar.avh.avatar_file import avatar_body, read_avatar_json
    from uvatar.avh.exporters.engine import (
        EngineExportConfig,
        engine_mesh,
        posed_joint_transforms,
        skin_reference,
    )
    from uvatar.body import load_body_model
    from uvatar.capture.mesh_fbx import read_fbx_mesh

    ap = argparse.ArgumentParser()
    ap.add_argument("avatar", type=Path)
    ap.add_argument("--blender", required=True)
    ap.add_argument("--poses", type=int, default=3)
    ap.add_argument("--sigma", type=float, default=0.4)
    ap.add_argument("--motion", default=None)
    ap.add_argument("--frames", type=int, default=5)
    args = ap.parse_args()
    meta = read_avatar_json(args.avatar)
    manifest = json.loads((args.avatar / "manifest.json").read_text())
    name, shape = avatar_body(meta, args.avatar / "avatar.json")
    body = load_body_model(name).rest_template(shape)
    mesh = engine_mesh(body, EngineExportConfig(subdivisions=manifest["mesh"]["subdivisions"]))
    written = read_fbx_mesh(args.avatar / manifest["fbx"])
    out = {"avatar": str(args.avatar), "vertices": len(mesh.positions), "joints": len(mesh.joint_names),
           "fbx_vs_glb_rest_mm": float(np.abs(written.vertices - mesh.positions).max() * 1000), "poses": []}
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(args.poses):
            local = Rotation.from_rotvec(rng.normal(0, args.sigma, (len(mesh.joint_names), 3))).as_matrix()
            world = posed_joint_transforms(mesh.joint_world_rest, mesh.joint_parents, local)
            deltas = Path(tmp) / "deltas.npy"
            np.save(deltas, world @ np.linalg.inv(mesh.joint_world_rest))
            Path(f"{deltas}.names").write_text("\n".join(mesh.joint_names))
            subprocess.run([args.blender, str(Path(__file__).with_name("fbx_rig_blender_pose.py")),
                            str(args.avatar / manifest["fbx"]), str(deltas), str(Path(tmp) / "posed.npy")],
                           check=True, capture_output=True)
            got, want = np.load(Path(tmp) / "posed.npy"), skin_reference(mesh, local)
            d = np.linalg.norm(got - want, axis=1) * 1000
            out["poses"].append({"max_mm": round(float(d.max()), 5), "median_mm": round(float(np.median(d)), 5),
                                 "moved_max_mm": round(float(np.abs(want - mesh.positions).max() * 1000), 1)})
        if args.motion:
            out["motion"] = motion_check(args, mesh, Path(tmp), name)
    print(json.dumps(out, indent=1))


def motion_check(args, mesh, tmp: Path, body_name: str) -> dict:
    """The motion as an animated FBX, played by Blender, against the reference (module doc)."""
    from scipy.spatial.transform import Rotation

    from uvatar.avh.exporters.engine import skin_reference
    from uvatar.avh.exporters.fbx_motion import write_avatar_motion_fbx
    from uvatar.body import load_body_model
    from uvatar.motion.sequences import load_motion

    body = load_body_model(body_name)
    motion = load_motion(args.motion, body=body)
    fbx = write_avatar_motion_fbx(tmp / "motion.fbx", args.avatar, motion, body_model=body)
    subprocess.run([args.blender, str(Path(__file__).with_name("fbx_anim_blender_frames.py")), str(fbx),
                    str(tmp / "frames.npy"), str(args.frames)], check=True, capture_output=True)
    got = np.load(tmp / "frames.npy")
    rows = []
    for t in range(len(got)):
        local = Rotation.from_rotvec(motion.joint_rotvecs[t].astype(np.float64)).as_matrix()
        want = skin_reference(mesh, local) @ Rotation.from_rotvec(motion.Rh[t]).as_matrix().T + motion.Th[t]
        d = np.linalg.norm(got[t] - want, axis=1) * 1000
        rows.append({"frame": t, "max_mm": round(float(d.max()), 5), "median_mm": round(float(np.median(d)), 5)})
    return {"source": str(args.motion), "frames": motion.num_frames, "fps": motion.fps,
            "fbx_mb": round(fbx.stat().st_size / 2**20, 2), "per_frame": rows}



if __name__ == "__main__":
    main()
