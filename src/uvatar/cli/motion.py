"""``uvatar motion info FILE`` and ``uvatar motion convert IN OUT.npz [--body anny] [--fps 25]``."""

from __future__ import annotations


def register(cli) -> None:
    p = cli.command("motion info", help="describe a motion file (.bvh, AMASS/uvatar .npz, fits or capture folder)")
    p.add_argument("path", help="motion file or folder")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_info)
    p = cli.command("motion convert", help="convert (and retarget) a motion to a uvatar motion .npz for a body model")
    p.add_argument("input", help=".bvh, AMASS .npz, uvatar .npz, EasyMocap fits folder or capture folder")
    p.add_argument("output", help="output .npz")
    p.add_argument("--body", default="anny", choices=("anny", "smpl", "smplx"), help="target body model")
    p.add_argument("--fps", type=float, default=None, help="resample to this frame rate")
    p.add_argument("--fits", default=None, metavar="DIR", help="also write EasyMocap fits (one JSON per frame) here")
    p.set_defaults(func=_convert)


def describe_motion_file(path) -> dict:
    """A summary dict of any supported motion source (without retargeting)."""
    from pathlib import Path

    import numpy as np

    from uvatar.errors import InputError

    path = Path(path)
    if not path.exists():
        raise InputError(path, "motion file or folder is missing")
    if path.suffix.lower() == ".bvh":
        from uvatar.motion.bvh import read_bvh
        from uvatar.motion.skeleton import clean_fps, guess_bvh_units

        m = read_bvh(path)
        unit = guess_bvh_units(m)
        return {"path": str(path), "kind": "bvh", "frames": m.num_frames, "fps": clean_fps(m.fps),
                "duration_s": round((m.num_frames - 1) / m.fps, 3), "joints": m.skeleton.num_joints,
                "joint_names": list(m.skeleton.names), "channels": int(m.channel_values.shape[1]),
                "units_to_metres_guess": unit}
    if path.suffix.lower() == ".npz":
        with np.load(path, allow_pickle=False) as npz:
            keys = set(npz.files)
        from uvatar.motion.amass import is_amass_npz, read_amass

        if is_amass_npz(keys):
            a = read_amass(path)
            return {"path": str(path), "kind": "amass", "model": a.model, "frames": a.num_frames, "fps": a.fps,
                    "duration_s": round((a.num_frames - 1) / a.fps, 3), "joints": len(a.names), "gender": a.gender,
                    "betas": int(a.betas.size)}
    from uvatar.motion.sequences import load_motion

    m = load_motion(path)
    if path.is_dir():
        kind = "capture" if (path / "capture.json").is_file() else "fits folder"
    else:
        kind = "uvatar motion" if "joint_rotvecs" in keys else "fits sequence"
    return {"path": str(path), "kind": kind,
            "frames": m.num_frames, "fps": m.fps, "duration_s": round(m.duration, 3), "joints": m.num_joints,
            "body": m.body, "source": m.source}


def _info(args) -> int:
    import json

    info = describe_motion_file(args.path)
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    for key, value in info.items():
        if key == "joint_names":
            value = ", ".join(value[:12]) + (" ..." if len(value) > 12 else "")
        print(f"{key:>22}: {value}")
    return 0


def _convert(args) -> int:
    import sys
    from pathlib import Path

    from uvatar.errors import InputError
    from uvatar.motion.sequences import load_motion, save_motion

    if Path(args.output).suffix.lower() != ".npz":
        raise InputError(args.output, "output must be a .npz file")
    if args.fps is not None and args.fps <= 0:
        raise InputError("--fps", f"must be > 0, got {args.fps}")
    print(f"loading {args.input} for body model '{args.body}' ...", file=sys.stderr)
    motion = load_motion(args.input, body=args.body, fps=args.fps)
    save_motion(args.output, motion)
    if args.fits:
        from tqdm import tqdm

        from uvatar.capture.fits import write_fit

        for t, fit in enumerate(tqdm(motion.to_fits(), desc="writing fits", unit="frame", file=sys.stderr)):
            write_fit(Path(args.fits) / f"{t:06d}.json", fit)
    print(f"{args.output}: {motion.num_frames} frames at {motion.fps:g} fps, {motion.num_joints} joints, "
          f"body {motion.body}")
    return 0
