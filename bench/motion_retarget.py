"""Motion speed: parse the CMU BVH clip, forward kinematics, retarget onto anny, resample to 25 fps.

    python bench/motion_retarget.py [--quick]

Prints one JSON object (seconds). Needs ../shared/data/motions/cmu_01_01.bvh and anny.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

CLIP = Path(__file__).resolve().parents[2] / "shared" / "data" / "motions" / "cmu_01_01.bvh"


def timed(fn):
    start = time.perf_counter()
    out = fn()
    return out, round(time.perf_counter() - start, 4)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="(same work; the clip is small)")
    parser.add_argument("--bvh", default=str(CLIP), help="BVH clip")
    args = parser.parse_args()
    from uvatar.body.registry import load_body_model
    from uvatar.motion import read_bvh, resample_motion, retarget, skeleton_motion_from_bvh

    body, load_s = timed(lambda: load_body_model("anny"))
    print(f"anny loaded in {load_s} s", file=sys.stderr)
    bvh, parse_s = timed(lambda: read_bvh(args.bvh))
    _, fk_s = timed(bvh.world_transforms)
    skel, skel_s = timed(lambda: skeleton_motion_from_bvh(bvh))
    motion, retarget_s = timed(lambda: retarget(skel, body))
    small, resample_s = timed(lambda: resample_motion(motion, 25.0))
    print(json.dumps({"frames": bvh.num_frames, "source_joints": bvh.skeleton.num_joints,
                      "target_joints": body.num_joints, "parse_s": parse_s, "fk_s": fk_s,
                      "skeleton_motion_s": skel_s, "retarget_s": retarget_s, "resample_to_25fps_s": resample_s,
                      "frames_at_25fps": small.num_frames,
                      "retarget_frames_per_s": round(bvh.num_frames / max(retarget_s, 1e-9), 1)}))


if __name__ == "__main__":
    main()
