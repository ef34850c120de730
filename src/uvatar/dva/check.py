"""``uvatar capture check`` for the multi-view layouts DVA reads besides uvatar's own capture folder:
an EasyMocap folder (intri.yml at its root) and a ZJU-MoCap subject (annots.npy).

The summary has the keys of :func:`uvatar.capture.validate.validate_capture` (so one formatter prints
both) plus ``layout``; the warnings are the same kinds: frames without fits, cameras without images,
images without masks, and images or masks whose size differs from the intrinsics.
"""

from __future__ import annotations

from pathlib import Path

from uvatar.capture.meshio import check_texture
from uvatar.capture.validate import ValidateConfig, size_warning
from uvatar.errors import InputError


def open_layout(root: Path):
    """The EasyMocap / ZJU-MoCap source of ``root`` (fits not required), or None for other folders."""
    from uvatar.dva.data import EasyMocapSource, ZjuMocapSource

    if (root / "annots.npy").is_file():
        return "zju-mocap", ZjuMocapSource(root)
    if (root / "intri.yml").is_file():
        return "easymocap", EasyMocapSource(root, require_fits=False)
    return None


def _scaled(size: tuple[int, int], scale: float) -> tuple[int, int]:
    return (int(round(size[0] * scale)), int(round(size[1] * scale))) if scale != 1.0 else tuple(size)


def check_layout(root, config: ValidateConfig | None = None) -> dict:
    """Check an EasyMocap or ZJU-MoCap folder → summary dict (see the module docstring)."""
    config = config or ValidateConfig()
    root = Path(root)
    found = open_layout(root)
    if found is None:
        raise InputError(root, "not a capture, EasyMocap or ZJU-MoCap folder (no capture.json, intri.yml "
                               "or annots.npy)")
    layout, src = found
    frames = list(src.frames)
    if not frames:
        raise InputError(root, "no frames (no fits and no images)")
    warnings = []
    fitted = [f for f in frames if src.has_fit(f)]
    if len(fitted) < len(frames):
        warnings.append(f"{len(frames) - len(fitted)} of {len(frames)} frames have no fit (`uvatar fit` makes them)")
    unfitted = sorted(set(getattr(src, "image_frames", [])) - set(frames))
    if unfitted:
        warnings.append(f"{len(unfitted)} image frames have no fit (first {unfitted[0]})")
    images, masks, missing = {}, {}, {}
    for name, cam in src.cameras.items():
        have = [f for f in frames if src.image_path(name, f).is_file()]
        masked = [f for f in have if src.mask_path(name, f).is_file()]
        images[name], masks[name], missing[name] = len(have), len(masked), len(frames) - len(have)
        if not have:
            warnings.append(f"camera {name} has no images ({src.image_path(name, frames[0]).parent})")
            continue
        if missing[name]:
            warnings.append(f"camera {name}: {missing[name]} of {len(frames)} frames have no image")
        if len(masked) < len(have):
            warnings.append(f"camera {name}: {len(have) - len(masked)} of {len(have)} images have no mask "
                            f"({src.mask_path(name, have[0]).parent})")
        for kind, path_of, files in (("images", src.image_path, have), ("masks", src.mask_path, masked)):
            for frame in files[: None if config.deep else 1]:
                path = path_of(name, frame)
                warning = size_warning(kind, cam, path, _scaled(check_texture(path, kind[:-1]), src.image_scale))
                if warning:
                    warnings.append(warning)
                    break
    if warnings and config.strict:
        more = f" (+{len(warnings) - 1} more warnings)" if len(warnings) > 1 else ""
        raise InputError(root, f"strict check: {warnings[0]}{more}")
    return {"root": str(root), "layout": layout, "frames": len(frames), "frame_names": [frames[0], frames[-1]],
            "fps": None, "body_model": src.body_model, "scans": 0, "topologies": [], "fits": len(fitted),
            "pose_values": None, "shape_values": None, "cameras": list(src.cameras), "images": images,
            "masks": masks, "frames_without_image": missing, "gt": False, "warnings": warnings}
