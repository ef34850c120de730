"""Multi-view sources for DVA: the uvatar capture layout, the EasyMocap layout and ZJU-MoCap.

Every source gives cameras (OpenCV, metres), frame names, per-frame body fits (EasyMocap convention),
images (H, W, 3) float32 in [0, 1] and masks (H, W) float32, plus its evaluation protocol:
``train_cameras``, ``train_frames``, ``test_cameras``, ``test_frames`` and a ``protocol`` string.

ZJU-MoCap (Neural Body protocol, Peng et al. 2021)
-------------------------------------------------
Layout: ``annots.npy`` (a pickled dict: ``cams`` with lists ``K`` (3,3), ``R`` (3,3), ``T`` (3,1) in
**millimetres**, ``D`` (5,1); ``ims``: per frame ``{"ims": [image path per camera]}``), images at those
paths, masks in ``mask_cihp/`` (or ``mask/``) at the same relative path with ``.png``, SMPL fits in
``new_params/<i>.npy`` (preferred) or ``params/<i>.npy``: dicts with ``poses`` (1,72), ``Rh``, ``Th``,
``shapes`` (1,10); ``i`` is the frame index (+1 for subjects 313/315 whose files start at 1).
Protocol: training views 0, 6, 12, 18; training frames the first ``num_train_frames`` (default 300);
test cameras all other views; test frames the novel poses after the training frames, every 30th; images
are scaled by ``ratio`` (default 0.5, 512x512) and the background (mask 0) is set to black; PSNR is
computed only inside the projected 3D bounding box of the posed body (vertices +- 5 cm), the box mask of
:func:`box_mask`.

uvatar captures
---------------
Training cameras: all but the held-out ones (``gt/info.json`` ``heldout_cameras`` if present, else every
4th camera starting with the 4th); training frames: all but ``heldout_frames`` and ``broken_frames``;
test: held-out cameras x held-out frames (all frames' last fifth when gt/ says nothing).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.capture.gt import GtInfo, read_gt_info
from uvatar.capture.types import BodyFit, Camera
from uvatar.errors import InputError
from uvatar.io_utils import read_image

NEURAL_BODY_TRAIN_VIEWS = (0, 6, 12, 18)


class MultiViewSource:
    """Base class. Subclasses fill ``cameras``, ``frames``, ``body_model``, ``shapes`` and the protocol."""

    root: Path
    cameras: dict[str, Camera]
    frames: list[str]
    body_model: str = "anny"
    shapes: np.ndarray | None = None
    train_cameras: list[str]
    test_cameras: list[str]
    train_frames: list[str]
    test_frames: list[str]
    protocol: str = ""
    eval_box_mask: bool = False  # PSNR inside the projected body box (Neural Body)

    image_scale: float = 1.0  # the loader resizes images by this factor (ZJU-MoCap's ratio)
    unusable: frozenset = frozenset()  # {(camera, frame)} whose mask does not show the subject (empty for want of it)

    def fit(self, frame: str) -> BodyFit:
        raise NotImplementedError

    def has_fit(self, frame: str) -> bool:
        raise NotImplementedError

    def image(self, cam: str, frame: str) -> np.ndarray:
        raise NotImplementedError

    def mask(self, cam: str, frame: str) -> np.ndarray:
        raise NotImplementedError

    def image_path(self, cam: str, frame: str) -> Path:
        raise NotImplementedError

    def mask_path(self, cam: str, frame: str) -> Path:
        raise NotImplementedError


def _load_image(path: Path, what="image") -> np.ndarray:
    """The file's own channels, float32 in [0, 1] (:func:`uvatar.io_utils.read_image`)."""
    return read_image(path, what, rgb=False)


def _resize(img: np.ndarray, ratio: float, nearest=False) -> np.ndarray:
    if ratio == 1.0:
        return img
    import cv2

    h, w = img.shape[:2]
    return cv2.resize(img, (int(round(w * ratio)), int(round(h * ratio))),
                      interpolation=cv2.INTER_NEAREST if nearest else cv2.INTER_AREA)


class CaptureSource(MultiViewSource):
    """The uvatar capture folder (cameras/, images/, masks/, fits/, optional gt/info.json)."""

    def __init__(self, root):
        from uvatar.capture import Capture
        from uvatar.fit.mask_views import unusable_views
        from uvatar.fit.masks import require_masks

        self.cap = Capture(root)
        self.root = self.cap.root
        require_masks(self.root)  # never half-made masks (`uvatar capture masks` killed)
        self.unusable = frozenset(unusable_views(self.root))
        self.cameras = self.cap.cameras()
        if not self.cameras:
            raise InputError(self.cap.cameras_dir / "intri.yml", "DVA needs a multi-view capture (no cameras)")
        self.frames = [f for f in self.cap.frames if self.cap.has_fit(f)]
        if not self.frames:
            raise InputError(self.cap.fits_dir, "no frame has a body fit")
        self.body_model = self.cap.body_model
        self.shapes = self.cap.body_shapes if self.cap.body_shapes.size else None
        info = read_gt_info(self.cap.root, required=False) or GtInfo(self.cap.gt_dir / "info.json")
        names = list(self.cameras)
        held_cams = [c for c in info.heldout_cameras if c in self.cameras]
        if not held_cams:
            held_cams = names[3::4] if len(names) >= 4 else names[-1:]
        broken = set(info.broken_frames)
        held = [f for f in info.heldout_frames if f in self.frames]
        if not held:
            held = self.frames[len(self.frames) * 4 // 5:]
        self.train_cameras = [c for c in names if c not in held_cams] or names
        self.test_cameras = held_cams
        self.train_frames = [f for f in self.frames if f not in held and f not in broken] or self.frames
        self.test_frames = [f for f in held if f not in broken]
        self.protocol = (f"uvatar capture: train on cameras {self.train_cameras} x {len(self.train_frames)} "
                         f"frames; test on held-out cameras {self.test_cameras} x held-out frames "
                         f"({len(self.test_frames)}), driven by {{driving}} training views; full-image "
                         "PSNR/SSIM against the photo")

    def fit(self, frame):
        return self.cap.load_fit(frame)

    def has_fit(self, frame):
        return self.cap.has_fit(frame)

    def image_path(self, cam, frame):
        return self.cap.image_path(cam, frame)

    def mask_path(self, cam, frame):
        return self.cap.mask_path(cam, frame)

    def image(self, cam, frame):
        return self.cap.load_image(cam, frame)

    def mask(self, cam, frame):
        return self.cap.load_mask(cam, frame).astype(np.float32)


class EasyMocapSource(MultiViewSource):
    """EasyMocap dataset folder: intri.yml + extri.yml, images/<cam>/<frame>.jpg, mask/<cam>/<frame>.png
    (or masks/), fits in output-smpl-3d/smpl/, output/smpl/, smpl/ or fits/ (<frame>.json). The fits
    are SMPL's unless ``body_model`` says otherwise (``train dva --model anny`` after ``uvatar fit``)."""

    FIT_DIRS = ("output-smpl-3d/smpl", "output/smpl", "smpl", "fits")

    def __init__(self, root, body_model: str = "smpl", require_fits: bool = True):
        from uvatar.capture import read_cameras

        self.root = Path(root)
        self.cameras = read_cameras(self.root)
        self.fit_dir = next((self.root / d for d in self.FIT_DIRS if (self.root / d).is_dir()), None)
        if self.fit_dir is None and require_fits:
            raise InputError(self.root, f"no fits folder (looked for {', '.join(self.FIT_DIRS)}; "
                                        "`uvatar fit` writes fits/)")
        self.frames = sorted(p.stem for p in self.fit_dir.glob("*.json")) if self.fit_dir else []
        if not self.frames and require_fits:
            raise InputError(self.fit_dir, "no fits (*.json)")
        self.image_frames = sorted({p.stem for c in self.cameras for p in (self.root / "images" / c).glob("*")
                                    if p.suffix.lower() in (".jpg", ".jpeg", ".png")})
        if not self.frames:  # checking a folder before `uvatar fit`: its frames are its images
            self.frames = self.image_frames
        self.body_model = body_model
        names = list(self.cameras)
        self.train_cameras = [c for i, c in enumerate(names) if i % 4 != 3] or names
        self.test_cameras = [c for c in names if c not in self.train_cameras] or names[-1:]
        cut = max(1, len(self.frames) * 4 // 5)
        self.train_frames, self.test_frames = self.frames[:cut], self.frames[cut:]
        self.protocol = "EasyMocap: every 4th camera and the last fifth of the frames held out"

    def _find(self, folder: str, cam: str, frame: str) -> Path:
        for sub in ((folder,) if folder != "mask" else ("mask", "masks")):
            for ext in (".jpg", ".png", ".jpeg"):
                p = self.root / sub / cam / f"{frame}{ext}"
                if p.is_file():
                    return p
        return self.root / folder / cam / f"{frame}.jpg"

    def fit(self, frame):
        from uvatar.capture import read_fit

        if self.fit_dir is None:
            raise InputError(self.root / "fits" / f"{frame}.json", "fit is missing")
        return read_fit(self.fit_dir / f"{frame}.json")

    def has_fit(self, frame):
        return self.fit_dir is not None and (self.fit_dir / f"{frame}.json").is_file()

    def image_path(self, cam, frame):
        return self._find("images", cam, frame)

    def mask_path(self, cam, frame):
        return self._find("mask", cam, frame)

    def image(self, cam, frame):
        return _load_image(self._find("images", cam, frame))[..., :3]

    def mask(self, cam, frame):
        m = _load_image(self._find("mask", cam, frame), "mask")
        return ((m.max(-1) if m.ndim == 3 else m) > 0.5).astype(np.float32)


class ZjuMocapSource(MultiViewSource):
    """ZJU-MoCap subject folder (see the module docstring for the layout and the protocol)."""

    eval_box_mask = True

    def __init__(self, root, ratio: float = 0.5, num_train_frames: int = 300, test_every: int = 30):
        self.root = Path(root)
        path = self.root / "annots.npy"
        if not path.is_file():
            raise InputError(path, "annots.npy is missing (not a ZJU-MoCap folder)")
        try:
            annots = np.load(path, allow_pickle=True).item()
            cams = annots["cams"]
            self._ims = [list(f["ims"]) for f in annots["ims"]]
        except Exception as exc:  # noqa: BLE001 - malformed pickles raise many kinds
            raise InputError(path, f"cannot read cams/ims ({exc.__class__.__name__}: {exc})") from None
        self.ratio = float(ratio)
        self.cameras = {}
        for i in range(len(cams["K"])):
            K = np.array(cams["K"][i], np.float64).copy()
            K[:2] *= self.ratio
            self.cameras[str(i)] = Camera(str(i), K, np.array(cams["R"][i], np.float64),
                                          np.array(cams["T"][i], np.float64).reshape(3) / 1000.0,
                                          0, 0, np.array(cams["D"][i], np.float64).reshape(-1))
        self.param_dir = self.root / ("new_params" if (self.root / "new_params").is_dir() else "params")
        self.offset = 1 if not (self.param_dir / "0.npy").is_file() and (self.param_dir / "1.npy").is_file() else 0
        self.frames = [str(i) for i in range(len(self._ims))]
        self.body_model = "smpl"
        names = list(self.cameras)
        h, w = self.mask(names[0], self.frames[0]).shape
        for cam in self.cameras.values():
            cam.width, cam.height = w, h
        self.train_cameras = [names[i] for i in NEURAL_BODY_TRAIN_VIEWS if i < len(names)]
        self.test_cameras = [c for c in names if c not in self.train_cameras]
        n_train = min(num_train_frames, len(self.frames))
        self.train_frames = self.frames[:n_train]
        self.test_frames = self.frames[n_train::test_every] or self.frames[-1:]
        self.protocol = (f"ZJU-MoCap, Neural Body protocol: train views {list(NEURAL_BODY_TRAIN_VIEWS)}, "
                         f"{n_train} training frames; novel-pose frames {n_train}:: every {test_every}; "
                         f"test views = the others; images x{self.ratio}, background black; PSNR inside "
                         "the projected 3D body box")

    @property
    def image_scale(self) -> float:
        return self.ratio

    def has_fit(self, frame):
        return (self.param_dir / f"{int(frame) + self.offset}.npy").is_file()

    def image_path(self, cam, frame):
        return self.root / self._rel(cam, frame)

    def mask_path(self, cam, frame):
        rel = Path(self._rel(cam, frame)).with_suffix(".png")
        found = [self.root / d / rel for d in ("mask_cihp", "mask") if (self.root / d / rel).is_file()]
        return found[0] if found else self.root / "mask_cihp" / rel

    def fit(self, frame):
        path = self.param_dir / f"{int(frame) + self.offset}.npy"
        if not path.is_file():
            raise InputError(path, "SMPL parameters are missing")
        try:
            p = np.load(path, allow_pickle=True).item()
            return BodyFit(poses=np.asarray(p["poses"], np.float32).reshape(-1),
                           Rh=np.asarray(p["Rh"], np.float32).reshape(3),
                           Th=np.asarray(p["Th"], np.float32).reshape(3),
                           shapes=np.asarray(p["shapes"], np.float32).reshape(-1))
        except (KeyError, ValueError, AttributeError) as exc:
            raise InputError(path, f"not a ZJU params dict ({exc})") from None

    def _rel(self, cam, frame) -> str:
        return self._ims[int(frame)][int(cam)]

    def image(self, cam, frame):
        img = _resize(_load_image(self.root / self._rel(cam, frame))[..., :3], self.ratio)
        return img * self.mask(cam, frame)[..., None]  # Neural Body: black background

    def mask(self, cam, frame):
        m = _load_image(self.mask_path(cam, frame), "mask")
        m = m.max(-1) if m.ndim == 3 else m
        return _resize((m > 0).astype(np.float32), self.ratio, nearest=True)


def box_mask(camera: Camera, vertices: np.ndarray, height: int, width: int, pad: float = 0.05) -> np.ndarray:
    """Neural Body evaluation mask: the projected 3D axis-aligned box of ``vertices`` (+- pad metres),
    filled face by face. Returns (H, W) bool."""
    import cv2

    lo, hi = vertices.min(0) - pad, vertices.max(0) + pad
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    pix = np.round(camera.project(corners)).astype(np.int32)
    faces = [[0, 1, 3, 2], [4, 5, 7, 6], [0, 1, 5, 4], [2, 3, 7, 6], [0, 2, 6, 4], [1, 3, 7, 5]]
    mask = np.zeros((height, width), np.uint8)
    for f in faces:  # one call per face: a single multi-polygon call would cut overlaps out (even-odd)
        cv2.fillPoly(mask, [pix[f]], 1)
    return mask.astype(bool)


def open_source(path, **kwargs) -> MultiViewSource:
    """Pick the loader from the folder's content: capture.json -> capture, annots.npy -> ZJU-MoCap,
    intri.yml -> EasyMocap."""
    root = Path(path)
    if (root / "capture.json").is_file():
        return CaptureSource(root)
    if (root / "annots.npy").is_file():
        return ZjuMocapSource(root, **kwargs)
    if (root / "intri.yml").is_file():
        return EasyMocapSource(root, **kwargs)
    raise InputError(root, "not a capture, ZJU-MoCap or EasyMocap folder (no capture.json, annots.npy "
                           "or intri.yml)")
