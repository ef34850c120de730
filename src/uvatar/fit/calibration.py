"""Refine the cameras' orientations against the person's detections (``uvatar fit --refine-cameras``).

A calibration that is a few pixels off in one view puts the triangulated body, its silhouette and
every texel sampled from that view in the wrong place, and no later stage can undo it. On Pose2Sim's
4-camera recording (``docs/real.md``) the keypoints triangulated from three cameras land 9-12 px
(at 544x960) off the detections in cam01 and cam03, in the same direction in every frame, and the
visual hull of three cameras' person masks misses 6-7 % of the fourth's mask until it is shifted by
the same amount: the calibration, not the detector.

:func:`refine_camera_rotations` is a bundle adjustment over the whole sequence with the lenses and
the camera centres held: each camera turns by a small rotation about its own centre (``omega``
(C, 3) radians, ``R' = exp(omega) R``, ``T' = exp(omega) T``), every confident keypoint of every frame
is a free 3D point (started at its triangulation), and the Geman-McClure of the reprojection error
(``sigma_px``) is minimised with a weak prior on ``omega`` (Adam, its steps decayed on a cosine to a thousandth). With four or more centres that
are not on one line nothing else can absorb a turn of one camera, so no camera has to be held fixed.
A turn larger than ``max_degrees`` is refused (the calibration is broken or belongs to another
capture, which no small turn should paper over).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from uvatar.capture.types import Camera
from uvatar.errors import check_values

__all__ = ["CameraRefineConfig", "refine_camera_rotations", "rotated_camera", "leave_one_out_offsets"]


@dataclass(frozen=True)
class CameraRefineConfig:
    """iterations / lr (radians per Adam step for the turns; points move ``lr`` x their depth);
    sigma_px: Geman-McClure scale of the reprojection error (pixels); min_conf: detections below
    are not used; prior_px: a turn that moves the image by this many pixels costs as much as one
    reprojection residual of ``sigma_px``; max_degrees: larger turns are refused.

    The prior keeps the turns from chasing the detector: MediaPipe places a landmark a little
    differently from the front and from the back, and the turns can absorb that too. On the real
    recording the share of each view's person mask outside the visual hull of the other three
    (a check the keypoints never see) is 4.7 % before, 1.65 / 0.9 / 1.0 / 1.3 / 1.6 % after with
    ``prior_px`` 20 / 50 / 100 / 200 / 1000 (the keypoint error falls 6.9 -> 4.7 px at 50, 4.4 at 1000).
    On noise-free detections and no prior the turns are exact; the prior shrinks them a little."""

    iterations: int = 400
    lr: float = 2e-3
    sigma_px: float = 15.0
    min_conf: float = 0.5
    prior_px: float = 50.0
    max_degrees: float = 3.0

    def __post_init__(self) -> None:
        check_values([
            (self.iterations >= 1, f"iterations must be >= 1, got {self.iterations}"),
            (min(self.lr, self.sigma_px, self.prior_px, self.max_degrees) > 0,
             "lr, sigma_px, prior_px and max_degrees must be > 0"),
            (0 <= self.min_conf < 1, f"min_conf must be in [0, 1), got {self.min_conf}"),
        ])


def rotated_camera(camera: Camera, omega) -> Camera:
    """``camera`` turned about its own centre by the rotation vector ``omega`` (3,) radians, applied
    in the camera's frame: ``R' = exp(omega) R``, ``T' = exp(omega) T`` (the centre stays)."""
    import roma

    turn = roma.rotvec_to_rotmat(torch.as_tensor(np.asarray(omega, np.float64).reshape(3))).numpy()
    return replace(camera, R=turn @ camera.R, T=turn @ camera.T)


def refine_camera_rotations(cameras: list[Camera], xy: np.ndarray, conf: np.ndarray, points: np.ndarray,
                            points_conf: np.ndarray, config: CameraRefineConfig | None = None,
                            progress=None) -> tuple[list[Camera], dict]:
    """Turn each of C ``cameras`` so that the detections agree.

    xy (F, C, K, 2) pixels as detected, conf (F, C, K) in [0, 1]; points (F, K, 3) their
    triangulation and points_conf (F, K) (0: not triangulated). Returns the turned cameras and a
    report: per camera the turn (degrees) and the image shift it makes at the principal point
    (pixels), and the mean reprojection error (pixels) before and after. Raises ``ValueError``
    when fewer than 3 cameras or no keypoint seen by two of them, or a turn above ``max_degrees``.
    ``progress(done, total)`` is called after every step."""
    import roma

    cfg = config or CameraRefineConfig()
    C = len(cameras)
    xy, conf = np.asarray(xy, np.float64), np.asarray(conf, np.float64)
    points, points_conf = np.asarray(points, np.float64), np.asarray(points_conf, np.float64)
    seen = (conf >= cfg.min_conf) & (points_conf[:, None] > 0)                 # (F, C, K)
    if C < 3:
        raise ValueError(f"refining the cameras needs 3 or more cameras, got {C}")
    if (seen.sum(1) >= 2).sum() == 0:
        raise ValueError("refining the cameras needs keypoints seen by two cameras; none are")
    from uvatar.fit.projection import CameraTensors, camera_tensors, project_cameras

    t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
    cams = camera_tensors(cameras, dtype=torch.float64)
    obs = t(xy)                                                                # (F, C, K, 2)
    weight = t(seen.astype(np.float64))                                        # (F, C, K)
    omega = torch.zeros(C, 3, dtype=torch.float64, requires_grad=True)
    depth = float(np.median(np.linalg.norm(points[points_conf > 0][:, None] - np.stack([c.center for c in cameras]),
                                           axis=-1)))
    pts = t(points).requires_grad_(True)
    focal = cams.K[:, 0, 0]
    opt = torch.optim.Adam([{"params": [omega], "lr": cfg.lr}, {"params": [pts], "lr": cfg.lr * depth}])
    decay = torch.optim.lr_scheduler.CosineAnnealingLR(opt, cfg.iterations, eta_min=cfg.lr * 1e-3)  # Adam's steps settle

    def residual():
        turn = roma.rotvec_to_rotmat(omega)
        turned = CameraTensors(cams.K, turn @ cams.R, (turn @ cams.T[..., None])[..., 0], cams.dist)
        px, _ = project_cameras(pts, turned)                                   # (F, C, K, 2)
        return (px - obs).norm(dim=-1)                                         # (F, C, K)

    def mean_error(r, camera=None):
        w = weight if camera is None else weight[:, camera]
        r = r if camera is None else r[:, camera]
        return float((r * w).sum() / w.sum()) if w.sum() > 0 else None

    with torch.no_grad():
        before = residual()
    s2 = cfg.sigma_px ** 2
    for step in range(cfg.iterations):
        opt.zero_grad()
        r = residual()
        data = (s2 * r * r / (s2 + r * r) * weight).sum() / weight.sum()
        prior = s2 * (((focal[:, None] * omega) / cfg.prior_px) ** 2).sum(1).mean()
        (data + prior).backward()
        opt.step()
        decay.step()
        if progress is not None:
            progress(step + 1, cfg.iterations)
    with torch.no_grad():
        after = residual()
    omega_np = omega.detach().numpy()
    degrees = np.degrees(np.linalg.norm(omega_np, axis=1))
    if degrees.max() > cfg.max_degrees:
        worst = int(degrees.argmax())
        raise ValueError(f"camera {cameras[worst].name} would turn by {degrees[worst]:.1f} deg, more than "
                         f"{cfg.max_degrees} deg: its calibration looks broken, not a few pixels off")
    refined = [rotated_camera(c, w) for c, w in zip(cameras, omega_np, strict=True)]
    report = {"cameras": {c.name: {"turn_deg": float(d), "shift_px": float(c.K[0, 0] * np.linalg.norm(w[:2])),
                                   "reprojection_px_before": mean_error(before, i),
                                   "reprojection_px_after": mean_error(after, i)}
                          for i, (c, d, w) in enumerate(zip(cameras, degrees, omega_np, strict=True))},
              "reprojection_px_before": mean_error(before), "reprojection_px_after": mean_error(after),
              "observations": int(seen.sum()), "frames": int(xy.shape[0])}
    return refined, report


def leave_one_out_offsets(cameras: list[Camera], xy: np.ndarray, conf: np.ndarray, min_conf: float = 0.5,
                          triangulate_config=None) -> dict:
    """Per camera, the mean signed offset (dx, dy) pixels of the keypoints triangulated from the
    *other* cameras and projected into it, against its own detections: a calibration error shows
    as an offset in the same direction in every frame (a detector's noise averages out).
    xy (F, C, K, 2), conf (F, C, K)."""
    from uvatar.fit.triangulate import triangulate
    from uvatar.render.cameras import project_points

    out = {}
    for c, cam in enumerate(cameras):
        others = np.array(conf, np.float64, copy=True)
        others[:, c] = 0
        tri = triangulate(xy, others, cameras, triangulate_config)
        ok = (tri.conf > 0) & (np.asarray(conf)[:, c] >= min_conf)
        if not ok.any():
            out[cam.name] = None
            continue
        px, _ = project_points(cam, tri.points[ok])
        d = px - np.asarray(xy)[:, c][ok]
        out[cam.name] = {"dx_px": float(d[:, 0].mean()), "dy_px": float(d[:, 1].mean()),
                         "rms_px": float(np.sqrt((d ** 2).sum(1).mean())), "count": int(ok.sum())}
    return out


BACKUP_DIR = "before_refine"


def refine_capture_cameras(capture, observations: dict, frames, config: CameraRefineConfig | None = None,
                           triangulate_config=None) -> tuple[dict, dict]:
    """Refine the capture's cameras against the subject's detections in ``observations`` ({frame:
    :class:`~uvatar.fit.observe.FrameObservation`}, the ``frames`` used), write them to
    ``cameras/`` (the calibration as it was kept once in ``cameras/before_refine/``) and save each
    frame's keypoints triangulated again through them. Returns (the observations through the refined
    cameras, the report of :func:`refine_camera_rotations` with the leave-one-out offsets before
    and after). Raises :class:`~uvatar.errors.InputError` naming ``cameras/`` when it cannot."""
    import shutil

    from uvatar.errors import InputError
    from uvatar.fit.observe import observation_path, save_observation
    from uvatar.fit.triangulate import triangulate

    used = [f for f in frames if f in observations]
    if not used:
        raise InputError(capture.cameras_dir, "refine_cameras=True: no frame with detections to refine against")
    names = [c.name for c in observations[used[0]].cameras]
    used = [f for f in used if [c.name for c in observations[f].cameras] == names]
    stack = lambda key: np.stack([np.asarray(getattr(observations[f], key), np.float64) for f in used])  # noqa: E731
    xy, conf = stack("xy"), stack("conf")
    cameras = observations[used[0]].cameras
    try:
        refined, report = refine_camera_rotations(cameras, xy, conf, stack("points"), stack("points_conf"), config)
    except ValueError as exc:
        raise InputError(capture.cameras_dir, f"refine_cameras=True: {exc}") from None
    report["leave_one_out_before"] = leave_one_out_offsets(cameras, xy, conf, triangulate_config=triangulate_config)
    report["leave_one_out_after"] = leave_one_out_offsets(refined, xy, conf, triangulate_config=triangulate_config)
    backup = capture.cameras_dir / BACKUP_DIR
    if not backup.is_dir():
        tmp = capture.cameras_dir / (BACKUP_DIR + ".tmp")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir()
        for f in capture.cameras_dir.glob("*.yml"):
            shutil.copy2(f, tmp / f.name)
        tmp.rename(backup)
    by_name = {c.name: c for c in refined}
    capture.replace_cameras({n: by_name.get(n, c) for n, c in capture.cameras().items()})
    out = dict(observations)
    for f, obs in observations.items():   # every frame's, the failed ones too: all go on through these cameras
        if [c.name for c in obs.cameras] != names:
            continue
        tri = triangulate(obs.xy, obs.conf, refined, triangulate_config)
        out[f] = replace(obs, cameras=list(refined), points=tri.points.astype(np.float32),
                         points_conf=tri.conf.astype(np.float32), reprojection_px=tri.reprojection_px.astype(np.float32))
        save_observation(observation_path(capture.person_root, f), out[f])
    report["calibration_kept_in"] = str(backup)
    return out, report
