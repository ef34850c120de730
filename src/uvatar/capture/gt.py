"""``gt/info.json``: the ground-truth record beside a synthetic capture (written by ``uvatar synth``).

The one reader and writer of that file. Fields (all optional): ``heldout_frames`` and
``broken_frames`` (frame names or int indices), ``heldout_cameras``, ``takes`` ({name: [first, end)
frame indices}), ``texel_resolution`` (older files: ``texels``; else ``config.gt_texels``), ``config``
(the studio's ``SynthConfig.to_dict()``; its ``light`` says whether the gt texture carries the
studio's light, absent in captures made before the light: unlit), ``body_shapes`` (the true body shape; capture.json holds
the fits' shape, which ``uvatar fit`` replaces), plus whatever else the studio records (``broken``,
``segments``, ``seed``: kept in :attr:`GtInfo.raw`). A real capture has no ``gt/``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from uvatar.capture.layout import frame_name
from uvatar.errors import InputError
from uvatar.io_utils import read_json, write_json

__all__ = ["GtInfo", "gt_info_path", "read_gt_info", "write_gt_info"]


def gt_info_path(capture_root) -> Path:
    return Path(capture_root) / "gt" / "info.json"


@dataclass(frozen=True)
class GtInfo:
    """A parsed ``gt/info.json``. Frame names are normalized (int 5 -> "000005"); ``texels`` is 0 when
    the file does not say; ``takes`` maps a take name to its [first, end) frame indices."""

    path: Path
    heldout_frames: tuple[str, ...] = ()
    broken_frames: tuple[str, ...] = ()
    heldout_cameras: tuple[str, ...] = ()
    takes: dict[str, tuple[int, int]] = field(default_factory=dict)
    texels: int = 0
    config: dict = field(default_factory=dict)
    body_shapes: tuple[float, ...] | None = None
    raw: dict = field(default_factory=dict)


def _names(info: dict, key: str, path: Path) -> tuple[str, ...]:
    value = info.get(key) or []
    if not isinstance(value, list) or not all(isinstance(v, (str, int)) and not isinstance(v, bool)
                                              for v in value):
        raise InputError(path, f"{key} must be a list of frame names or indices")
    return tuple(frame_name(v) for v in value)


def read_gt_info(capture_root, required: bool = True) -> GtInfo | None:
    """The capture's ``gt/info.json`` as a :class:`GtInfo`. Missing: InputError when ``required``,
    else None. Bad JSON or a malformed field: InputError naming the file."""
    path = gt_info_path(capture_root)
    if not path.is_file():
        if required:
            raise InputError(path, "not found (only synthetic captures from `uvatar synth` have ground truth)")
        return None
    info = read_json(path)
    takes = info.get("takes") or {}
    try:
        takes = {str(k): (int(v[0]), int(v[1])) for k, v in dict(takes).items()}
        config = dict(info.get("config") or {})
        texels = int(info.get("texel_resolution") or info.get("texels") or config.get("gt_texels") or 0)
    except (TypeError, ValueError, IndexError, KeyError) as exc:
        raise InputError(path, f"malformed takes, config or texel_resolution ({exc})") from None
    shapes = info.get("body_shapes")
    if shapes is not None:
        if not isinstance(shapes, list) or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                   for v in shapes):
            raise InputError(path, "body_shapes must be a list of numbers")
        shapes = tuple(float(v) for v in shapes)
    cameras = info.get("heldout_cameras") or []
    if not isinstance(cameras, list):
        raise InputError(path, "heldout_cameras must be a list of camera names")
    return GtInfo(path=path, heldout_frames=_names(info, "heldout_frames", path),
                  broken_frames=_names(info, "broken_frames", path),
                  heldout_cameras=tuple(str(c) for c in cameras), takes=takes, texels=texels, config=config,
                  body_shapes=shapes, raw=info)


def write_gt_info(root, info: dict) -> None:
    """Write ``root/gt/info.json`` atomically."""
    write_json(gt_info_path(root), info)
