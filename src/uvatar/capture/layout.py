"""The capture folder (see docs/ARCHITECTURE.md and DESIGN.md):

    capture.json            {"fps", "units", "body_model": {"name", "shapes"}, "frames", "provenance"}
    scans/000000.obj|.ply|.glb (+ texture, .mtl)    one textured scan per frame
    fits/000000.json        EasyMocap fits (or fits.npz with the whole sequence)
    cameras/intri.yml, cameras/extri.yml           optional, multi-view
    images/<cam>/000000.png, masks/<cam>/000000.png
    gt/                     ground truth (synthetic captures only)
    people/<id>/            every other person fitted (``uvatar fit --person all``): fits/, masks/<cam>/,
                            fitting/ and person.json ({"body_model", "shapes", "provenance"}) of that
                            person; images and cameras are the capture's. ``Capture(root, person=id)``
                            reads them as it reads the subject's.
"""

from __future__ import annotations

from functools import cached_property
from pathlib import Path

import numpy as np

from uvatar.capture.cameras import read_cameras
from uvatar.capture.fits import read_fit, read_fits_npz
from uvatar.capture.meshio import IMAGE_SUFFIXES, find_scan, load_texture, read_mesh
from uvatar.capture.types import BodyFit, Camera, TexturedMesh
from uvatar.errors import InputError
from uvatar.io_utils import read_json, write_json

CAPTURE_JSON = "capture.json"
PERSON_JSON = "person.json"
PEOPLE_DIR = "people"


def check_person_id(person) -> str | None:
    """A person id ("1", "2", ...: another person than the subject) as text; None for the subject."""
    if person is None:
        return None
    text = str(person).strip()
    if not text.isdigit() or int(text) < 1:
        raise InputError("person", f"a person id is a whole number >= 1 (the subject has none), got {person!r}")
    return str(int(text))


def frame_name(frame) -> str:
    """A frame's file stem: an int index becomes its zero-padded name (5 -> "000005"), a name stays."""
    return f"{frame:06d}" if isinstance(frame, int) else str(frame)


def is_frame_range(spec) -> bool:
    """True for a half-open range of take frame numbers such as ``"0:120"``, ``"120:"`` or ``":30"``."""
    import re

    return isinstance(spec, str) and re.fullmatch(r"\s*\d*\s*:\s*\d*\s*", spec) is not None


def frames_in_range(frames, spec: str, flag: str = "--frames") -> list[str]:
    """The frame names whose take number (the name read as an integer: ``000120`` is 120) lies in the
    half-open range ``spec`` = ``"A:B"`` (as in Python; A or B may be left out), in capture order.

    InputError naming ``flag`` when the range is malformed or holds none of ``frames``."""
    if not is_frame_range(spec):
        raise InputError(flag, f"expected a range of frame numbers A:B (half-open, e.g. 0:120), got {spec!r}")
    lo, hi = (part.strip() for part in spec.split(":"))
    start, stop = int(lo) if lo else 0, int(hi) if hi else None
    if stop is not None and stop <= start:
        raise InputError(flag, f"the range {spec} is empty (B must be greater than A)")
    numbered = [(f, int(f)) for f in map(str, frames) if f.isdigit()]
    chosen = [f for f, n in numbered if n >= start and (stop is None or n < stop)]
    if not chosen:
        have = f"{numbered[0][1]}..{numbered[-1][1]}" if numbered else "none numbered"
        raise InputError(flag, f"no frame in {spec} (the capture's frames are {have})")
    return chosen


def write_capture_info(root: str | Path, frames: list[str], fps: float = 25.0, body_model: str = "anny",
                       shapes=None, provenance: dict | None = None, **extra) -> dict:
    """Write ``root/capture.json`` atomically and return the dict written."""
    info = {"fps": float(fps), "units": "m",
            "body_model": {"name": body_model, "shapes": [] if shapes is None else np.asarray(shapes).tolist()},
            "frames": [str(f) for f in frames], "provenance": provenance or {}, **extra}
    write_json(Path(root) / CAPTURE_JSON, info)
    return info


def require_made(root: str | Path) -> None:
    """Refuse, in one line, a capture its maker left half made: ``uvatar synth`` (record in the
    capture's folder) or ``uvatar capture import`` (records in ``images/`` and ``scans/``) killed or
    failed before its last frame (:func:`uvatar.stage_record.require_complete`). A capture without
    records (made by hand, or before records existed) is taken as it is."""
    from uvatar.stage_record import require_complete

    root = Path(root)
    require_complete(root, "synth", f"uvatar synth {root}", unit="frames", check_inputs=False)
    for part, unit in (("images", "images"), ("scans", "frames")):
        require_complete(root / part, "capture import", f"uvatar capture import SRC {root}", unit=unit,
                         check_inputs=False)


def read_capture_info(root: str | Path) -> dict:
    """Read and minimally check ``capture.json`` (errors name the file)."""
    path = Path(root) / CAPTURE_JSON
    info = read_json(path, "capture.json is missing (is this a capture folder?)")
    if "frames" in info and (not isinstance(info["frames"], list)
                             or not all(isinstance(f, str | int) for f in info["frames"])):
        raise InputError(path, "'frames' must be a list of frame names")
    fps = info.get("fps", 25)
    if not isinstance(fps, int | float) or fps <= 0:
        raise InputError(path, f"'fps' must be a positive number, got {fps!r}")
    body = info.get("body_model", {"name": "anny"})
    if isinstance(body, str):
        body = {"name": body}
    if not isinstance(body, dict) or "name" not in body:
        raise InputError(path, "'body_model' must be {\"name\": ..., \"shapes\": [...]}")
    if not isinstance(body["name"], str) or not body["name"]:
        raise InputError(path, f"'body_model.name' must be a name (anny, smpl, smplx), got {str(body['name'])[:40]!r}")
    shapes = body.get("shapes")
    if shapes is not None and (not isinstance(shapes, list) or not all(
            isinstance(v, int | float) and not isinstance(v, bool) and np.isfinite(v) for v in shapes)):
        raise InputError(path, "'body_model.shapes' must be a list of numbers (or null)")
    info["body_model"] = body
    return info


def _first_existing(folder: Path, stem: str, suffixes=IMAGE_SUFFIXES) -> Path:
    for suffix in suffixes:
        candidate = folder / f"{stem}{suffix}"
        if candidate.is_file():
            return candidate
    return folder / f"{stem}.png"


class Capture:
    """A capture folder, read lazily. ``frames`` come from capture.json (or the scans/fits files).
    ``person``: another person's id (``people/<id>/``: their fits, masks, fitting and shape; the
    images, cameras, scans and gt stay the capture's); None: the subject.

    >>> cap = Capture("captures/alice")                     # doctest: +SKIP
    >>> mesh, fit = cap.load_scan(cap.frames[0]), cap.load_fit(cap.frames[0])  # doctest: +SKIP
    """

    def __init__(self, root: str | Path, person: str | int | None = None):
        self.root = Path(root)
        if not self.root.is_dir():
            raise InputError(self.root, "capture folder does not exist")
        require_made(self.root)  # first: an import killed before its last frame has no capture.json yet
        self.info = read_capture_info(self.root)
        self.person = check_person_id(person)

    # people
    @property
    def person_root(self) -> Path:
        """The folder of this person's fits, masks and fitting/ (the capture's root for the subject)."""
        return self.root if self.person is None else self.root / PEOPLE_DIR / self.person

    def people(self) -> list[str]:
        """Ids of the other people fitted (``people/<id>/fits/`` exists), in numeric order."""
        folder = self.root / PEOPLE_DIR
        ids = [p.name for p in folder.iterdir() if p.name.isdigit() and (p / "fits").is_dir()] \
            if folder.is_dir() else []
        return sorted(ids, key=int)

    def for_person(self, person: str | int | None) -> Capture:
        """The same capture seen as ``person`` (None: the subject)."""
        return Capture(self.root, person)

    @cached_property
    def person_info(self) -> dict:
        """``people/<id>/person.json`` ({} for the subject or when missing)."""
        path = self.person_root / PERSON_JSON
        return read_json(path) if self.person is not None and path.is_file() else {}

    # folders
    @property
    def scans_dir(self) -> Path:
        return self.root / "scans"

    @property
    def fits_dir(self) -> Path:
        return self.person_root / "fits"

    @property
    def masks_dir(self) -> Path:
        return self.person_root / "masks"

    @property
    def fitting_dir(self) -> Path:
        return self.person_root / "fitting"

    @property
    def cameras_dir(self) -> Path:
        return self.root / "cameras"

    @property
    def gt_dir(self) -> Path:
        return self.root / "gt"

    @property
    def fps(self) -> float:
        return float(self.info.get("fps", 25.0))

    @property
    def body_model(self) -> str:
        return str(self.person_info.get("body_model") or self.info["body_model"]["name"])

    @property
    def body_shapes(self) -> np.ndarray:
        if self.person is not None:
            return np.asarray(self.person_info.get("shapes") or [], dtype=np.float32)
        return np.asarray(self.info["body_model"].get("shapes") or [], dtype=np.float32)

    @cached_property
    def frames(self) -> list[str]:
        """Frame names ("000000", ...) from capture.json, else from scans/ or fits/ file stems."""
        if self.info.get("frames"):
            return [str(f) for f in self.info["frames"]]
        for folder in (self.scans_dir, self.fits_dir):
            stems = sorted({p.stem for p in folder.glob("*") if p.suffix.lower() in (".obj", ".ply", ".glb", ".json")})
            if stems:
                return stems
        return []

    # scans
    def scan_path(self, frame: str) -> Path:
        """Path of the frame's scan (.obj/.ply/.glb; the .obj name if none exists)."""
        return find_scan(self.scans_dir, frame) or self.scans_dir / f"{frame}.obj"

    def has_scan(self, frame: str) -> bool:
        return find_scan(self.scans_dir, frame) is not None

    def load_scan(self, frame: str) -> TexturedMesh:
        return read_mesh(self.scan_path(frame))

    # fits
    def fit_path(self, frame: str) -> Path:
        return self.fits_dir / f"{frame}.json"

    @cached_property
    def _fits_npz(self) -> dict[str, BodyFit] | None:
        npz = self.person_root / "fits.npz"
        return read_fits_npz(npz) if npz.is_file() else None

    def has_fit(self, frame: str) -> bool:
        return self.fit_path(frame).is_file() or (self._fits_npz is not None and frame in self._fits_npz)

    def load_fit(self, frame: str, person_id: int | None = None) -> BodyFit:
        """The frame's fit from ``fits/<frame>.json``, else from ``fits.npz``."""
        path = self.fit_path(frame)
        if not path.is_file() and self._fits_npz is not None and frame in self._fits_npz:
            return self._fits_npz[frame]
        return read_fit(path, person_id)

    # cameras and images
    def has_cameras(self) -> bool:
        return (self.cameras_dir / "intri.yml").is_file()

    @cached_property
    def _cameras(self) -> dict[str, Camera]:
        return read_cameras(self.cameras_dir) if self.has_cameras() else {}

    def cameras(self) -> dict[str, Camera]:
        """{name: Camera} from cameras/intri.yml + extri.yml ({} when the capture has none)."""
        return dict(self._cameras)

    def replace_cameras(self, cameras: dict[str, Camera]) -> None:
        """Write ``cameras`` as the capture's calibration (cameras/intri.yml + extri.yml, atomically)
        and read them from now on."""
        from uvatar.capture.cameras import write_cameras

        write_cameras(self.cameras_dir, cameras)
        self.__dict__.pop("_cameras", None)

    def image_path(self, cam: str, frame: str) -> Path:
        return _first_existing(self.root / "images" / cam, frame)

    def mask_path(self, cam: str, frame: str) -> Path:
        return _first_existing(self.masks_dir / cam, frame)

    def load_image(self, cam: str, frame: str) -> np.ndarray:
        """(H, W, 3) float32 RGB in [0, 1]."""
        return load_texture(self.image_path(cam, frame), what="image")

    def load_mask(self, cam: str, frame: str) -> np.ndarray:
        """(H, W) bool foreground mask (any channel > 0.5)."""
        return load_texture(self.mask_path(cam, frame), what="mask image").max(axis=-1) > 0.5

    def __repr__(self) -> str:
        who = f", person={self.person!r}" if self.person is not None else ""
        return f"Capture({str(self.root)!r}{who}, frames={len(self.frames)})"
