"""Pose an exported avatar's skinned FBX (``AVATAR/avatar.fbx``) in Blender and compare Blender's own
skinning with uvatar's reference skinning of the same rig (``engine.skin_reference``, the GLB's).

    python scripts/fbx_rig_check_with_blender.py AVATAR --blender BPY_PYTHON [--poses 3] [--sigma 0.4]

Each pose: every joint turned by a random rotation vector (``--sigma`` radians a component); Blender
(``scripts/fbx_rig_blender_pose.py``: the FBX imported by Blender's importer, each bone posed by the same
world change in Blender's axes, the mesh evaluated) against the reference. Prints one JSON object: per
pose the largest and median vertex distance (mm) and how far the pose moved the body (mm).
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

    from uvatar.avh.exporters.engine import (
        EngineExportConfig,
        engine_mesh,
        posed_joint_transforms,
        read_avatar_json,
        rest_body_from_model,
        skin_reference,
    )
    from uvatar.body import load_body_model
    from uvatar.capture.mesh_fbx import read_fbx_mesh

    ap = argparse.ArgumentParser()
    ap.add_argument("avatar", type=Path)
    ap.add_argument("--blender", required=True)
    ap.add_argument("--poses", type=int, default=3)
    ap.add_argument("--sigma", type=float, default=0.4)
    args = ap.parse_args()
    meta = read_avatar_json(args.avatar)
    manifest = json.loads((args.avatar / "manifest.json").read_text())
    body_meta = meta.get("body_model", {})
    name = body_meta.get("name", body_meta) if isinstance(body_meta, dict) else body_meta
    shape = meta.get("shape", body_meta.get("shapes") if isinstance(body_meta, dict) else None)   # as the export
    body = rest_body_from_model(load_body_model(str(name)), shape)
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
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
