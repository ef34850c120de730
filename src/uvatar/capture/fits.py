"""EasyMocap body fits: per-frame JSON and a compact per-sequence NPZ.

Per-frame JSON (``fits/000000.json``) is a list of people ``[{"id", "Rh", "Th", "poses", "shapes",
"scale"?}]`` or ``{"annots": [...]}``; ``Rh``/``Th`` may be ``[[3]]`` or ``[3]``, ``poses`` ``[[J*3]]``
or ``[J*3]``. ``V = R(Rh) @ LBS(poses with zero root, shapes) * scale + Th`` (metres, radians).

The NPZ holds a whole sequence: ``frames`` (T,) str, ``poses`` (T, N), ``Rh`` (T, 3), ``Th`` (T, 3),
``shapes`` (T, S), ``scale`` (T,), ``ids`` (T,).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from uvatar.capture.types import BodyFit
from uvatar.errors import InputError
from uvatar.io_utils import read_json, read_npz, write_json, write_npz

REQUIRED_KEYS = ("Rh", "Th", "poses")


def _vector(path: Path, person: dict, key: str, size: int | None) -> np.ndarray:
    value = person[key]
    if not isinstance(value, list | tuple | int | float | np.ndarray) or isinstance(value, bool):
        raise InputError(path, f"{key} is not a numeric array")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(path, f"{key} is not a numeric array") from None
    if arr.ndim == 2 and arr.shape[0] == 1:
        arr = arr[0]
    if arr.ndim != 1 or (size is not None and arr.shape[0] != size):
        want = f"({size},) or (1, {size})" if size is not None else "(N,) or (1, N)"
        raise InputError(path, f"{key} has shape {tuple(np.shape(person[key]))}, expected {want}")
    with np.errstate(over="ignore"):
        if not np.all(np.isfinite(arr.astype(np.float32))):  # fits are kept as float32
            raise InputError(path, f"{key} contains NaN, infinite or out-of-range (> 3.4e38) values")
    return arr


def fit_from_dict(path: str | Path, person: dict, num_pose_values: int | None = None) -> BodyFit:
    """Validate one EasyMocap person record → BodyFit (errors name ``path`` and the field)."""
    path = Path(path)
    if not isinstance(person, dict):
        raise InputError(path, "a person record is not a JSON object")
    missing = [k for k in REQUIRED_KEYS if k not in person]
    if missing:
        raise InputError(path, f"missing key(s) {', '.join(missing)}")
    poses = _vector(path, person, "poses", num_pose_values)
    if poses.size == 0 or poses.size % 3:
        raise InputError(path, f"poses has {poses.size} values, expected a positive multiple of 3")
    shapes = _vector(path, person, "shapes", None) if "shapes" in person else np.zeros(0)
    scale = 1.0
    if "scale" in person:
        value = person["scale"]
        if isinstance(value, list) and len(value) == 1:
            value = value[0]
        if (isinstance(value, bool) or not isinstance(value, int | float) or not 0 < value < 3.4e38
                or not np.isfinite(value)):
            raise InputError(path, f"scale must be one positive number, got {str(person['scale'])[:40]!r}")
        scale = float(value)
    person_id = person.get("id", 0)
    if isinstance(person_id, str) and person_id.strip().lstrip("-").isdigit():
        person_id = int(person_id)
    if isinstance(person_id, bool) or not isinstance(person_id, int | float) or person_id != int(person_id):
        raise InputError(path, f"id must be an integer, got {str(person.get('id'))[:40]!r}")
    return BodyFit(poses=poses, Rh=_vector(path, person, "Rh", 3), Th=_vector(path, person, "Th", 3),
                   shapes=shapes, scale=scale, id=int(person_id))


def read_fits(path: str | Path, num_pose_values: int | None = None) -> list[BodyFit]:
    """Every person in an EasyMocap per-frame JSON (bare list or ``{"annots": [...]}``)."""
    path = Path(path)
    data = read_json(path, "fit file is missing", expect_object=False)
    if isinstance(data, dict):
        data = data.get("annots", [data] if "poses" in data else None)
    if not isinstance(data, list):
        raise InputError(path, "expected a list of people or {\"annots\": [...]}")
    if not data:
        raise InputError(path, "no person in the fit file")
    return [fit_from_dict(path, person, num_pose_values) for person in data]


def read_fit(path: str | Path, person_id: int | None = None, num_pose_values: int | None = None) -> BodyFit:
    """One person's fit (the first, or the one with ``id == person_id``)."""
    fits = read_fits(path, num_pose_values)
    if person_id is None:
        return fits[0]
    for fit in fits:
        if fit.id == person_id:
            return fit
    raise InputError(path, f"no person with id {person_id}")


def fit_to_dict(fit: BodyFit) -> dict:
    """BodyFit → EasyMocap person record (``[[...]]`` nesting as EasyMocap writes it)."""
    record = {"id": int(fit.id), "Rh": [fit.Rh.tolist()], "Th": [fit.Th.tolist()],
              "poses": [fit.poses.tolist()], "shapes": [fit.shapes.tolist()]}
    if fit.scale != 1.0:
        record["scale"] = float(fit.scale)
    return record


def write_fit(path: str | Path, fit: BodyFit | list[BodyFit]) -> None:
    """Write one or several people as an EasyMocap bare list, atomically."""
    fits = fit if isinstance(fit, list) else [fit]
    write_json(path, [fit_to_dict(f) for f in fits])


def read_fits_dir(folder: str | Path, person_id: int | None = None) -> dict[str, BodyFit]:
    """All ``*.json`` fits in a folder → {frame name (file stem): BodyFit}, sorted by name."""
    folder = Path(folder)
    files = sorted(folder.glob("*.json"))
    if not files:
        raise InputError(folder, "no fit files (*.json)")
    return {f.stem: read_fit(f, person_id) for f in files}


def write_fits_npz(path: str | Path, fits: Mapping[str, BodyFit]) -> None:
    """Write a sequence {frame: BodyFit} as one compressed NPZ (all fits must share sizes)."""
    frames = list(fits)
    items = [fits[f] for f in frames]
    if not items:
        raise InputError(path, "no fits to write")
    for name in ("poses", "shapes"):
        sizes = {getattr(f, name).size for f in items}
        if len(sizes) > 1:
            raise InputError(path, f"fits have different {name} sizes {sorted(sizes)}")
    write_npz(path, frames=np.array(frames, dtype=str),
              poses=np.stack([f.poses for f in items]).astype(np.float32),
              Rh=np.stack([f.Rh for f in items]).astype(np.float32),
              Th=np.stack([f.Th for f in items]).astype(np.float32),
              shapes=np.stack([f.shapes for f in items]).astype(np.float32),
              scale=np.array([f.scale for f in items], np.float32),
              ids=np.array([f.id for f in items], np.int64))


def read_fits_npz(path: str | Path) -> dict[str, BodyFit]:
    """Read a sequence NPZ written by :func:`write_fits_npz` → {frame: BodyFit}."""
    path = Path(path)
    data = read_npz(path, "fits NPZ is missing")
    for key in ("frames", "poses", "Rh", "Th"):
        if key not in data:
            raise InputError(path, f"missing array {key!r}")
    if data["frames"].ndim != 1 or data["frames"].dtype.kind not in "US":
        raise InputError(path, f"frames must be a list of names, got {data['frames'].dtype} {data['frames'].shape}")
    t = len(data["frames"])
    poses = data["poses"]
    if poses.ndim != 2 or poses.shape[0] != t:
        raise InputError(path, f"poses has shape {poses.shape}, expected ({t}, N)")
    for key in ("Rh", "Th"):
        if data[key].shape != (t, 3):
            raise InputError(path, f"{key} has shape {data[key].shape}, expected ({t}, 3)")
    want = {"shapes": (t, None), "scale": (t,), "ids": (t,)}
    for key, shape in want.items():
        if key in data and (data[key].ndim != len(shape) or data[key].shape[0] != t):
            raise InputError(path, f"{key} has shape {data[key].shape}, expected ({t}{', S' if key == 'shapes' else ''})")
    for key in ("poses", "Rh", "Th", "shapes", "scale", "ids"):
        if key not in data:
            continue
        if data[key].dtype.kind not in "biuf":
            raise InputError(path, f"{key} is not a real numeric array (dtype {data[key].dtype})")
        if not np.all(np.isfinite(data[key])):
            raise InputError(path, f"{key} contains NaN or infinite values")
    if "scale" in data and np.any(data["scale"] <= 0):
        raise InputError(path, "scale must be positive")
    if poses.shape[1] == 0 or poses.shape[1] % 3:
        raise InputError(path, f"poses has {poses.shape[1]} values per frame, expected a positive multiple of 3")
    shapes = data.get("shapes", np.zeros((t, 0), np.float32))
    scale = data.get("scale", np.ones(t, np.float32))
    ids = data.get("ids", np.zeros(t, np.int64))
    return {str(f): BodyFit(poses[i], data["Rh"][i], data["Th"][i], shapes[i], float(scale[i]), int(ids[i]))
            for i, f in enumerate(data["frames"])}
