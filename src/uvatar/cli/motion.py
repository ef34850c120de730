"""``uvatar motion info FILE``, ``uvatar motion convert IN OUT.npz [--body anny] [--fps 25] [--map FILE]
[--feet clean] [--report R.json]`` and ``uvatar motion compare A.npz B.npz``.

``motion convert``'s retargeting flags are generated from :class:`uvatar.motion.retarget.RetargetConfig`."""

from __future__ import annotations

from uvatar.cli.flags import ConfigFlags


def _retarget_flags() -> ConfigFlags:
    from uvatar.motion.retarget import RetargetConfig

    return ConfigFlags(RetargetConfig, fields=("twist", "feet"),
                       choices={"twist": ("auto", "motion", "rest"), "feet": ("floor", "clean")},
                       help={"twist": "where the source's bone frames come from: the clip (motion), the rest pose "
                                      "(rest), or the clip where it has evidence (auto)",
                             "feet": "floor: root height alone; clean: also pin the feet in the source's contacts "
                                     "by leg IK"})


def register(cli) -> None:
    p = cli.command("motion info", help="describe a motion file (.bvh, .fbx, .gltf/.glb, AMASS/uvatar .npz, fits or "
                                        "capture folder)")
    p.add_argument("path", help="motion file or folder")
    p.add_argument("--map", dest="name_map", default=None, metavar="FILE",
                   help="joint map (JSON/YAML {source joint: semantic joint})")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_info)
    p = cli.command("motion convert", help="convert (and retarget) a motion to a uvatar motion .npz for a body model")
    p.add_argument("input", help=".bvh, .fbx, .gltf/.glb, AMASS .npz, uvatar .npz, EasyMocap fits folder or capture "
                                  "folder")
    p.add_argument("output", help="output .npz, or .fbx with --avatar: the motion as an FBX animation of the avatar's "
                                  "rig (its avatar.fbx)")
    p.add_argument("--body", default="anny", choices=("anny", "smpl", "smplx"), help="target body model")
    p.add_argument("--avatar", default=None, metavar="DIR",
                   help="an exported avatar (uvatar export): retarget to its body model and shape (over --body); "
                        "an .fbx output is the motion playing on its rig")
    p.add_argument("--model-dir", default=None, help="SMPL/SMPL-X model folder (none: $UVATAR_SMPL_DIR)")
    p.add_argument("--fps", type=float, default=None, help="resample to this frame rate")
    p.add_argument("--fits", default=None, metavar="DIR", help="also write EasyMocap fits (one JSON per frame) here")
    p.add_argument("--map", dest="name_map", default=None, metavar="FILE",
                   help="joint map (JSON/YAML {source joint: semantic or body joint, or null}) over the automatic match")
    _retarget_flags().add_to(p)
    p.add_argument("--report", default=None, metavar="JSON",
                   help="write per-bone direction/twist errors, lowest foot height and foot sliding here")
    p.set_defaults(func=_convert)
    p = cli.command("motion compare", help="per-bone direction and twist differences of two motions of one body")
    p.add_argument("a", help="uvatar motion .npz")
    p.add_argument("b", help="uvatar motion .npz")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_compare)


def _user_map(path):
    from uvatar.motion.rigs import read_joint_map

    return read_joint_map(path) if path else None


def describe_motion_file(path, joint_map: dict | None = None) -> dict:
    """A summary dict of any supported motion source (without retargeting); for skeletons, which
    rig was recognised and which joints map."""
    from pathlib import Path

    from uvatar.errors import InputError
    from uvatar.io_utils import read_npz

    path = Path(path)
    if not path.exists():
        raise InputError(path, "motion file or folder is missing")
    if path.suffix.lower() == ".bvh":
        from uvatar.motion.bvh import read_bvh
        from uvatar.motion.rigs import match_rig
        from uvatar.motion.skeleton import clean_fps, guess_bvh_units

        m = read_bvh(path)
        try:
            rig = match_rig(m.skeleton.names, m.skeleton.parents, joint_map).summary()
        except ValueError as exc:
            raise InputError(path, str(exc)) from None
        return {"path": str(path), "kind": "bvh", "frames": m.num_frames, "fps": clean_fps(m.fps),
                "duration_s": round((m.num_frames - 1) / m.fps, 3), "joints": m.skeleton.num_joints,
                "joint_names": list(m.skeleton.names), "channels": int(m.channel_values.shape[1]),
                "absolute_position_channels": [n for n, a in zip(m.skeleton.names, m.skeleton.absolute_positions,
                                                                 strict=True) if a],
                "units_to_metres_guess": guess_bvh_units(m), **rig}
    if path.suffix.lower() in (".fbx", ".gltf", ".glb"):
        from uvatar.motion.rigs import match_rig
        from uvatar.motion.sequences import read_skeleton_motion

        sk = read_skeleton_motion(path)
        try:
            rig = match_rig(sk.names, sk.parents, joint_map).summary()
        except ValueError as exc:
            raise InputError(path, str(exc)) from None
        return {"path": str(path), "kind": "fbx" if path.suffix.lower() == ".fbx" else "gltf",
                "frames": sk.num_frames, "fps": sk.fps, "duration_s": round((sk.num_frames - 1) / sk.fps, 3),
                "joints": len(sk.names), "joint_names": list(sk.names), "units": "m", **rig}
    if path.suffix.lower() == ".npz":
        keys = set(read_npz(path))
        from uvatar.motion.amass import is_amass_npz, read_amass

        if is_amass_npz(keys):
            a = read_amass(path)
            return {"path": str(path), "kind": "amass", "model": a.model, "frames": a.num_frames, "fps": a.fps,
                    "duration_s": round((a.num_frames - 1) / a.fps, 3), "joints": len(a.names), "gender": a.gender,
                    "betas": int(a.betas.size), "rig": "smpl"}
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

    info = describe_motion_file(args.path, _user_map(args.name_map))
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    for key, value in info.items():
        if key == "mapped":
            value = ", ".join(f"{k}→{v}" for k, v in value.items())
        elif isinstance(value, list):
            value = ", ".join(map(str, value)) or "-"
        print(f"{key:>26}: {value}")
    return 0


def _convert(args) -> int:
    import sys
    from pathlib import Path

    from uvatar.errors import InputError, options_as_input_error
    from uvatar.motion.sequences import load_motion, save_motion

    as_fbx = Path(args.output).suffix.lower() == ".fbx"
    if not as_fbx and Path(args.output).suffix.lower() != ".npz":
        raise InputError(args.output, "output must be a .npz file, or an .fbx file with --avatar")
    if as_fbx and args.avatar is None:
        raise InputError(args.output, "an .fbx output is the motion on an avatar's rig: give --avatar DIR (an "
                                      "exported avatar)")
    if args.fps is not None and not args.fps > 0:
        raise InputError("--fps", f"must be > 0, got {args.fps}")
    with options_as_input_error("uvatar motion convert options"):
        config = _retarget_flags().config(args, name_map=_user_map(args.name_map))
    from uvatar.body.registry import load_body_model

    body_name, shape = args.body, None
    if args.avatar is not None:
        from uvatar.avh.avatar_file import avatar_body, read_avatar_json

        body_name, shape = avatar_body(read_avatar_json(Path(args.avatar)), Path(args.avatar) / "avatar.json")
    print(f"loading {args.input} for body model '{body_name}'" + (" at the avatar's shape" if shape is not None else "")
          + " ...", file=sys.stderr)
    body = load_body_model(body_name, model_dir=args.model_dir)
    motion = load_motion(args.input, body=body, config=config, shape=shape)
    if args.report:
        _write_report(args, motion, config, body, shape)
    if args.fps:
        from uvatar.motion.sequences import resample_motion

        motion = resample_motion(motion, args.fps)
    if as_fbx:
        from uvatar.avh.exporters.fbx_motion import write_avatar_motion_fbx

        write_avatar_motion_fbx(args.output, args.avatar, motion, body_model=body)
    else:
        save_motion(args.output, motion)
    if args.fits:
        from tqdm import tqdm

        from uvatar.capture.fits import write_fit

        for t, fit in enumerate(tqdm(motion.to_fits(), desc="writing fits", unit="frame", file=sys.stderr)):
            write_fit(Path(args.fits) / f"{t:06d}.json", fit)
    print(f"{args.output}: {motion.num_frames} frames at {motion.fps:g} fps, {motion.num_joints} joints, "
          f"body {motion.body}" + (f", rig {motion.info['rig']}" if "rig" in motion.info else ""))
    return 0


def _write_report(args, motion, config, body, shape=None) -> None:
    from dataclasses import replace
    from pathlib import Path

    from uvatar.errors import InputError
    from uvatar.io_utils import write_json
    from uvatar.motion.report import retarget_report, summary_lines
    from uvatar.motion.retarget import plan_retarget, retarget
    from uvatar.motion.sequences import SKELETON_READERS, read_skeleton_motion

    path = Path(args.input)
    if path.suffix.lower() not in SKELETON_READERS:
        raise InputError(path, f"--report measures a skeleton retarget: give a {', '.join(SKELETON_READERS)} input")
    source = read_skeleton_motion(path)
    plan = plan_retarget(source, body, config, shape)
    before = retarget(source, body, replace(config, feet="floor"), plan) if config.feet == "clean" else None
    report = retarget_report(source, motion, body, plan, contacts_config=config.contacts, before=before)
    write_json(args.report, report)
    for line in summary_lines(report):
        print(line)


def _compare(args) -> int:
    import json

    from uvatar.body.registry import load_body_model
    from uvatar.errors import InputError
    from uvatar.motion.report import compare_motions, summary_lines
    from uvatar.motion.sequences import load_motion

    a = load_motion(args.a)
    b = load_motion(args.b)
    if a.body != b.body or a.num_frames != b.num_frames:
        raise InputError(args.b, f"{b.num_frames} frames of '{b.body}', {args.a} has {a.num_frames} of '{a.body}'")
    report = compare_motions(load_body_model(a.body), a, b)
    print(json.dumps(report, indent=2) if args.json else "\n".join(summary_lines(report)))
    return 0
