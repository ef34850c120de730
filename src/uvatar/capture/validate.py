"""Check a capture folder and summarize it; the first problem raises one-line InputError.

Fast by default: mesh headers are read without parsing numbers (vertex/face counts, texture name),
textures are checked with PIL ``verify`` (no decoding), fits are fully validated (they are small).
``deep=True`` loads every mesh and texture completely.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uvatar.capture.fits import read_fit
from uvatar.capture.layout import Capture
from uvatar.capture.meshio import IMAGE_SUFFIXES, MESH_FORMATS, check_texture, read_mesh, read_mesh_header
from uvatar.errors import InputError, UvatarError

# poses values per fit for body models whose joint count is fixed (others: consistent across frames)
POSE_VALUES = {"anny": 312, "smpl": 72}


@dataclass
class ValidateConfig:
    """deep: fully load every mesh and texture (and check every image's size, not each camera's
    first); require_scans: fail on frames without a scan even when the capture has no scans at all
    (image-only DVA captures normally have none); strict: fail on the first warning (frames without
    fits, cameras without images, images without masks, images or masks whose size differs from
    the intrinsics) instead of listing them."""

    deep: bool = False
    require_scans: bool = False
    strict: bool = False


def _check_scan(path: Path, deep: bool, checked_textures: set) -> tuple[int, int]:
    if deep:
        mesh = read_mesh(path)
        if not np.all(np.isfinite(mesh.vertices)):
            raise InputError(path, "vertices contain NaN or infinite values")
        if mesh.faces.size and mesh.faces.max() >= mesh.num_vertices:
            raise InputError(path, "face index out of range")
        if not mesh.has_uvs:
            raise InputError(path, "scan has no UV coordinates")
        if mesh.texture is None:
            raise InputError(path, "scan names no texture image")
        return mesh.num_vertices, mesh.num_faces
    header = read_mesh_header(path)
    if not header["has_uvs"]:
        raise InputError(path, "scan has no UV coordinates")
    texture = header["texture"]
    if texture is None:
        raise InputError(path, "scan names no texture image")
    if isinstance(texture, Path) and texture not in checked_textures:
        check_texture(texture)
        checked_textures.add(texture)
    return header["num_vertices"], header["num_faces"]


def _segments(frames: list[str], keys: list[tuple[int, int]]) -> list[dict]:
    """Distinct (V, F) with their frame count and runs of consecutive frames."""
    out: dict[tuple[int, int], dict] = {}
    previous = None
    for frame, key in zip(frames, keys, strict=True):
        entry = out.setdefault(key, {"vertices": key[0], "faces": key[1], "frames": 0, "segments": []})
        entry["frames"] += 1
        if key != previous:
            entry["segments"].append([frame, frame])
        entry["segments"][-1][1] = frame
        previous = key
    return list(out.values())


def _image_stems(folder: Path) -> set[str]:
    return {p.stem for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES} if folder.is_dir() else set()


def validate_capture(root: str | Path, config: ValidateConfig | None = None,
                     progress: Callable | None = None) -> dict:
    """Validate a capture folder → summary dict, or raise :class:`InputError` at the first problem.

    Summary keys: ``root``, ``frames`` (count), ``frame_names`` (first, last), ``fps``,
    ``body_model``, ``scans`` (count), ``topologies`` (list of {vertices, faces, frames,
    segments}), ``fits`` (count), ``pose_values``, ``cameras`` (names), ``images`` and ``masks``
    ({camera: count}), ``frames_without_image`` ({camera: count}), ``gt`` (bool), ``warnings``
    (one line each; with ``config.strict`` the first one raises instead). ``progress(iterable, total, desc)`` wraps the frame loop
    (e.g. tqdm).
    """
    config = config or ValidateConfig()
    cap = Capture(root)
    frames = cap.frames
    if not frames:
        raise InputError(cap.root / "capture.json", "no frames listed and no scans/ or fits/ files found")
    if len(set(frames)) != len(frames):
        raise InputError(cap.root / "capture.json", "'frames' lists a frame more than once")
    scan_dir_has_files = cap.scans_dir.is_dir() and any(
        p.suffix.lower() in MESH_FORMATS for p in cap.scans_dir.iterdir())
    want_scans = scan_dir_has_files or config.require_scans
    expected_poses = cap.info["body_model"].get("num_joints")
    expected_poses = 3 * int(expected_poses) if expected_poses else POSE_VALUES.get(cap.body_model.lower())
    npz_fits = cap._fits_npz
    keys, checked_textures = [], set()
    pose_values = shape_values = None
    iterator = progress(frames, len(frames), "checking frames") if progress else frames
    no_fit: list[str] = []
    for frame in iterator:
        if want_scans:
            scan = cap.scan_path(frame)
            if not cap.has_scan(frame):
                raise InputError(scan, f"frame {frame} has no scan (.obj/.ply/.glb)")
            keys.append(_check_scan(scan, config.deep, checked_textures))
        fit_path = cap.fit_path(frame)
        if fit_path.is_file():
            fit = read_fit(fit_path, num_pose_values=expected_poses)
        elif npz_fits is not None and frame in npz_fits:
            fit, fit_path = npz_fits[frame], cap.root / "fits.npz"
        else:
            no_fit.append(frame)
            continue
        if expected_poses is not None and fit.poses.size != expected_poses:
            raise InputError(fit_path, f"poses has {fit.poses.size} values, expected {expected_poses} "
                                       f"for body model '{cap.body_model}'")
        if pose_values is None:
            pose_values, shape_values = fit.poses.size, fit.shapes.size
        elif fit.poses.size != pose_values:
            raise InputError(fit_path, f"poses has {fit.poses.size} values, other frames have {pose_values}")
        elif fit.shapes.size != shape_values:
            raise InputError(fit_path, f"shapes has {fit.shapes.size} values, other frames have {shape_values}")
    warnings = []
    if no_fit:
        warnings.append(f"{len(no_fit)} of {len(frames)} frames have no fit "
                        f"({cap.fit_path(no_fit[0])}{' ...' if len(no_fit) > 1 else ''}; `uvatar fit` makes them)")
    images, masks, missing, cameras = {}, {}, {}, []
    if cap.cameras_dir.is_dir() and any(cap.cameras_dir.iterdir()):
        cams = cap.cameras()
        cameras = list(cams)
        for name in cameras:
            warnings += _check_camera_images(cap, cams[name], frames, config.deep, images, masks, missing)
    elif (cap.root / "images").is_dir():
        raise InputError(cap.cameras_dir / "intri.yml", "images/ exists but the cameras are missing")
    warnings += fit_warnings(cap.root)
    if warnings and config.strict:
        more = f" (+{len(warnings) - 1} more warnings)" if len(warnings) > 1 else ""
        raise InputError(cap.root, f"strict check: {warnings[0]}{more}")
    return {"root": str(cap.root), "frames": len(frames), "frame_names": [frames[0], frames[-1]],
            "fps": cap.fps, "body_model": cap.body_model, "scans": len(keys),
            "topologies": _segments(frames, keys) if keys else [], "fits": len(frames) - len(no_fit),
            "pose_values": pose_values, "shape_values": shape_values, "cameras": cameras,
            "images": images, "masks": masks, "frames_without_image": missing, "gt": cap.gt_dir.is_dir(),
            "warnings": warnings}


def fit_warnings(root: Path) -> list[str]:
    """Warnings from ``fitting/summary.json`` (written by ``uvatar fit``): frames whose views disagree
    with the subject (named with their cameras; left out of the fit)."""
    from uvatar.io_utils import read_json

    path = Path(root) / "fitting" / "summary.json"
    if not path.is_file():
        return []
    try:
        disagree = read_json(path).get("views_disagree") or {}
    except UvatarError:
        return [f"{path}: unreadable, the fit's report is not checked"]
    if not disagree:
        return []
    listed = "; ".join(f"{f} {','.join(c)}" for f, c in sorted(disagree.items())[:8])
    more = f" (+{len(disagree) - 8} more)" if len(disagree) > 8 else ""
    return [f"{len(disagree)} frame(s) have views that disagree with the fitted subject, left out of the fit "
            f"({path}): {listed}{more}"]


def size_warning(what: str, camera, path: Path, size: tuple[int, int]) -> str | None:
    """A warning when an image of ``size`` (width, height) does not match the camera's intrinsics."""
    if camera.width and camera.height and tuple(size) != (camera.width, camera.height):
        return (f"camera {camera.name}: {what} are {size[0]}x{size[1]} but the intrinsics say "
                f"{camera.width}x{camera.height} ({path})")
    return None


def _check_camera_images(cap: Capture, camera, frames: list[str], deep: bool, images: dict, masks: dict,
                         missing: dict) -> list[str]:
    """Fill the per-camera counts; return this camera's warnings (no images, frames without an image,
    images without a mask, image/mask sizes that differ from the intrinsics)."""
    name = camera.name
    folder = cap.root / "images" / name
    stems, mask_stems = _image_stems(folder), _image_stems(cap.root / "masks" / name)
    images[name], masks[name] = len(stems), len(mask_stems)
    missing[name] = len(set(frames) - stems)
    if not stems:
        return [f"camera {name} has no images ({folder})"]
    out = []
    if missing[name]:
        out.append(f"camera {name}: {missing[name]} of {len(frames)} frames have no image ({folder})")
    unmasked = sorted(set(frames) & stems - mask_stems)
    if unmasked:
        out.append(f"camera {name}: {len(unmasked)} of {len(set(frames) & stems)} images have no mask "
                    f"({cap.root / 'masks' / name}; `uvatar capture masks` makes them)")
    checked = [f for f in frames if f in stems]
    for kind, path_of, have in (("images", cap.image_path, stems), ("masks", cap.mask_path, mask_stems)):
        sizes = []  # deep: every file is verified; one warning per camera and kind
        for frame in [f for f in checked if f in have][: None if deep else 1]:
            path = path_of(name, frame)
            warning = size_warning(kind, camera, path, check_texture(path, what=kind[:-1]))
            if warning and not sizes:
                sizes.append(warning)
        out += sizes
    return out


def format_summary(summary: dict) -> str:
    """Human-readable multi-line summary of :func:`validate_capture`'s result."""
    first, last = summary["frame_names"]
    fps = f"at {summary['fps']:g} fps" if summary.get("fps") else "fps unknown"
    layout = f" ({summary['layout']} layout)" if summary.get("layout") else ""
    lines = [f"capture {summary['root']}{layout}: OK",
             f"  frames      {summary['frames']} ({first} .. {last}) {fps}, body model {summary['body_model']}"]
    if summary["scans"]:
        tops = summary["topologies"]
        lines.append(f"  scans       {summary['scans']} in {len(tops)} topolog{'y' if len(tops) == 1 else 'ies'}")
        for t in tops[:8]:
            segs = ", ".join(f"{a}..{b}" if a != b else a for a, b in t["segments"][:4])
            more = f" (+{len(t['segments']) - 4} more runs)" if len(t["segments"]) > 4 else ""
            lines.append(f"    {t['vertices']} vertices / {t['faces']} faces: {t['frames']} frames [{segs}{more}]")
        if len(tops) > 8:
            lines.append(f"    ... {len(tops) - 8} more topologies")
    else:
        lines.append("  scans       none")
    values = (f" ({summary['pose_values']} pose values, {summary['shape_values']} shape values)"
              if summary.get("pose_values") is not None else "")
    lines.append(f"  fits        {summary['fits']}{values}" if summary["fits"] else "  fits        none")
    if summary["cameras"]:
        lines.append(f"  cameras     {len(summary['cameras'])}")
        for name in summary["cameras"]:
            gap = summary["frames_without_image"].get(name, 0)
            lines.append(f"    {name}: {summary['images'][name]} images, {summary['masks'][name]} masks"
                         + (f" ({gap} frames without an image)" if gap else ""))
    else:
        lines.append("  cameras     none")
    lines.append(f"  ground truth {'yes' if summary['gt'] else 'no'}")
    warnings = summary.get("warnings", [])
    if warnings:
        lines[0] = f"capture {summary['root']}{layout}: OK with {len(warnings)} warning{'s' if len(warnings) > 1 else ''}"
        lines += [f"  warning: {w}" for w in warnings]
    return "\n".join(lines)
