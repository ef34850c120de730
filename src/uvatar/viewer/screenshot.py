"""Headless screenshot of the viewer: ``python -m uvatar.viewer.screenshot AVATAR OUT.png [--pose ...]``.

Serves AVATAR on a free port, opens the page in headless Chromium, sets the pose, waits until the
generator's maps for it are drawn, saves the page as PNG and prints one JSON object: the viewer's
reported inference time for that pose and a short benchmark (mean/median over random poses).

Poses: ``--pose FILE`` (JSON list of J*3 local axis-angles, ``{"poses": [...]}`` with ``--frame``, or an
EasyMocap fit ``[{"poses": [[...]]}]``) and/or ``--joint NAME=X,Y,Z`` (repeatable; a joint name or a
semantic name such as ``l_shoulder``; local axis-angle in radians, added on top of ``--pose``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from uvatar.errors import InputError, UvatarError


def load_pose(path: str | Path, num_joints: int, frame: int = 0) -> np.ndarray:
    """A (J*3,) pose from a JSON file (flat list, {"poses": [[...]]} or an EasyMocap fit)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(path, f"cannot read pose JSON ({exc})") from None
    if isinstance(data, dict) and "annots" in data:
        data = data["annots"]
    if isinstance(data, list) and data and isinstance(data[0], dict):
        data = data[0]
    if isinstance(data, dict):
        data = data.get("poses", data.get("pose"))
    arr = np.asarray(data, np.float32)
    if arr.ndim == 2:
        if not 0 <= frame < len(arr):
            raise InputError(path, f"frame {frame} out of range (0..{len(arr) - 1})")
        arr = arr[frame]
    if arr.size != 3 * num_joints:
        raise InputError(path, f"pose has {arr.size} values, expected {3 * num_joints} (J*3)")
    return arr.reshape(-1)


def apply_joint_specs(pose: np.ndarray, specs: list[str], manifest: dict) -> np.ndarray:
    """Apply ``NAME=X,Y,Z`` specs (joint or semantic names, radians) to a copy of ``pose``."""
    pose = pose.copy()
    names = {n: i for i, n in enumerate(manifest["joint_names"])}
    names.update(manifest.get("semantic_joints", {}))
    for spec in specs:
        try:
            name, values = spec.split("=", 1)
            xyz = [float(v) for v in values.split(",")]
            assert len(xyz) == 3
        except (ValueError, AssertionError):
            raise InputError("--joint", f"{spec!r}: expected NAME=X,Y,Z (radians)") from None
        if name not in names:
            raise InputError("--joint", f"unknown joint {name!r}")
        pose[3 * names[name]:3 * names[name] + 3] = xyz
    return pose


def screenshot(avatar_dir: str | Path, out_png: str | Path, pose: np.ndarray | None = None,
               width: int = 960, height: int = 720, bench_runs: int = 10, hide_panel: bool = False) -> dict:
    """Shoot the viewer showing ``pose``; return {"inference_ms", "benchmark", "backend", "texels", ...}."""
    from uvatar.io_utils import atomic_path
    from uvatar.viewer.browser import call_page, set_pose, viewer_page, wait_idle
    from uvatar.viewer.server import ViewerConfig, ViewerServer

    with ViewerServer(avatar_dir, ViewerConfig(port=0, open_browser=False)) as server, \
            viewer_page(server.url, width, height) as page:
        manifest = page.evaluate("window.uvatar.manifest")
        if pose is not None:
            set_pose(page, pose)
        bench = (call_page(page, "n => window.uvatar.benchmark(n)", int(bench_runs), 60 + 10 * bench_runs,
                           "benchmark") if bench_runs > 0 else None)
        if pose is not None:  # redraw the requested pose after the benchmark and report its inference time
            call_page(page, "() => window.uvatar.setPose(window.uvatar.getPose().map(v => v))", what="setPose")
            wait_idle(page)
        page.wait_for_timeout(1200)  # let the fps counter settle over one interval
        stats = page.evaluate("window.uvatar.stats")
        if hide_panel:
            page.evaluate("document.getElementById('panel').hidden = true")
        with atomic_path(out_png, suffix=".png") as tmp:
            page.screenshot(path=str(tmp))
    return {"screenshot": str(out_png), "texels": manifest["texels"], "backend": stats["backend"],
            "inference_ms": stats["inferenceMs"], "fps": stats["fps"], "benchmark": bench,
            "pose_nonzero_joints": [manifest["joint_names"][j] for j in
                                    np.flatnonzero(np.abs(np.asarray(pose).reshape(-1, 3)).sum(1))]
            if pose is not None else []}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m uvatar.viewer.screenshot", description=__doc__.split("\n\n")[0])
    p.add_argument("avatar", help="avatar folder (manifest.json, avatar.glb, model.onnx)")
    p.add_argument("out", help="output PNG")
    p.add_argument("--pose", help="pose JSON (J*3 list, {'poses': [...]}, or an EasyMocap fit)")
    p.add_argument("--frame", type=int, default=0, help="frame of a multi-frame --pose file")
    p.add_argument("--joint", action="append", default=[], metavar="NAME=X,Y,Z",
                   help="set a joint's local axis-angle (radians); repeatable")
    p.add_argument("--width", type=int, default=960)
    p.add_argument("--height", type=int, default=720)
    p.add_argument("--bench", type=int, default=10, help="random-pose inference runs to time (0: none)")
    p.add_argument("--hide-panel", action="store_true", help="hide the control panel in the picture")
    args = p.parse_args(argv)
    try:
        from uvatar.viewer.server import check_avatar_dir

        manifest = json.loads((check_avatar_dir(args.avatar) / "manifest.json").read_text())
        J = len(manifest["joint_names"])
        pose = load_pose(args.pose, J, args.frame) if args.pose else np.zeros(3 * J, np.float32)
        pose = apply_joint_specs(pose, args.joint, manifest)
        result = screenshot(args.avatar, args.out, pose, args.width, args.height, args.bench, args.hide_panel)
    except UvatarError as exc:
        print(f"uvatar: error: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
