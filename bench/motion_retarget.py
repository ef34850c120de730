"""Motion speed and retarget quality: parse the CMU BVH clip, forward kinematics, retarget onto
anny (with and without the foot-contact clean-up: sliding before/after), resample to 25 fps; then the same clip re-expressed (other names, every bone along X,
twisted joint frames, 6 channels per joint) against the CMU retarget, and the retarget report.

    python bench/motion_retarget.py [--quick] [--bvh CLIP]

Prints one JSON object (seconds, degrees, metres). Needs ../shared/data/motions/cmu_01_01.bvh and anny.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

CLIP = Path(__file__).resolve().parents[2] / "shared" / "data" / "motions" / "cmu_01_01.bvh"
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests.fixtures: the re-expression helper


def timed(fn):
    start = time.perf_counter()
    out = fn()
    return out, round(time.perf_counter() - start, 4)


def _medians(report: dict) -> dict:
    return {g: {"direction": r["direction_deg"]["median"], "twist": r["twist_deg"]["median"]}
            for g, r in report["bones"].items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="every 8th frame for the quality part")
    parser.add_argument("--bvh", default=str(CLIP), help="BVH clip")
    args = parser.parse_args()
    from tests.fixtures.motion_reexpress import reexpress, subsample
    from uvatar.body.registry import load_body_model
    from uvatar.motion import read_bvh, resample_motion, retarget, skeleton_motion_from_bvh, write_bvh
    from uvatar.motion.feet import source_contacts
    from uvatar.motion.report import compare_motions, feet_in_contact, retarget_report
    from uvatar.motion.retarget import RetargetConfig, plan_retarget

    body, load_s = timed(lambda: load_body_model("anny"))
    print(f"anny loaded in {load_s} s", file=sys.stderr)
    bvh, parse_s = timed(lambda: read_bvh(args.bvh))
    _, fk_s = timed(bvh.world_transforms)
    skel, skel_s = timed(lambda: skeleton_motion_from_bvh(bvh))
    motion, retarget_s = timed(lambda: retarget(skel, body))
    small, resample_s = timed(lambda: resample_motion(motion, 25.0))
    plan_full = plan_retarget(skel, body)
    clean, clean_s = timed(lambda: retarget(skel, body, RetargetConfig(feet="clean"), plan_full))
    contacts = source_contacts(skel, plan_full)
    feet_clean = {"retarget_clean_s": clean_s, "contact_share_per_foot": contacts.mean(0).round(4).tolist(),
                  "before": feet_in_contact(motion, body, plan_full, contacts),
                  "after": feet_in_contact(clean, body, plan_full, contacts), **clean.info["foot_contacts"]}
    out = {"frames": bvh.num_frames, "source_joints": bvh.skeleton.num_joints, "target_joints": body.num_joints,
           "parse_s": parse_s, "fk_s": fk_s, "skeleton_motion_s": skel_s, "retarget_s": retarget_s,
           "resample_to_25fps_s": resample_s, "frames_at_25fps": small.num_frames,
           "retarget_frames_per_s": round(bvh.num_frames / max(retarget_s, 1e-9), 1), "feet_clean": feet_clean}
    clip = subsample(bvh, 8) if args.quick else bvh
    studio, _, _ = reexpress(clip, twist_deg=80.0)
    with tempfile.TemporaryDirectory() as tmp:
        write_bvh(Path(tmp) / "studio.bvh", studio)
        source = skeleton_motion_from_bvh(read_bvh(Path(tmp) / "studio.bvh"), "studio.bvh")
    reference = retarget(skeleton_motion_from_bvh(clip, "cmu"), body)
    plan = plan_retarget(source, body)
    moved = retarget(source, body, plan=plan)
    moved_clean = retarget(source, body, RetargetConfig(feet="clean"), plan)
    rest_only = retarget(source, body, RetargetConfig(twist="rest"))
    report = retarget_report(source, moved, body, plan)
    report_clean = retarget_report(source, moved_clean, body, plan, before=moved)
    feet = {k: v for k, v in report["lowest_foot_m"].items() if k not in ("per_frame", "frames")}
    out.update({"reexpressed_rig": plan.match.rig, "reexpressed_frames": clip.num_frames,
                "reexpressed_vs_cmu_median_deg": _medians(compare_motions(body, reference, moved)),
                "rest_pose_alignment_vs_cmu_median_deg": _medians(compare_motions(body, reference, rest_only)),
                "report_vs_source_median_deg": _medians(report), "lowest_foot_m": feet,
                "foot_sliding_m_per_s": report["foot_sliding_m_per_s"],
                "clean_feet_vs_cmu_clean_median_deg": _medians(compare_motions(
                    body, retarget(skeleton_motion_from_bvh(clip, "cmu"), body, RetargetConfig(feet="clean")), moved_clean)),
                "clean_feet_lowest_foot_m": {k: v for k, v in report_clean["lowest_foot_m"].items()
                                             if k not in ("per_frame", "frames")},
                "clean_feet_contacts": report_clean["foot_contacts"]})
    print(json.dumps(out))


if __name__ == "__main__":
    main()
