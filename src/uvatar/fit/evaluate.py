"""Body fits against ground truth (``uvatar synth`` captures) and against the scans.

:func:`evaluate_fits` compares fits (``{frame: BodyFit}``, e.g. from ``uvatar fit`` or the capture's
own ``fits/``) with the true poses in ``gt/frames/<frame>.npz`` (local axis-angles, Rh, Th) and the
true shape (:func:`true_body_shape`: ``gt/info.json`` ``body_shapes``, which ``uvatar synth`` writes). The protocol text in
the returned dict says exactly what is measured. Another person's fits (``Capture(root, person=id)``,
``uvatar fit --person all``) are compared with the bystander of ``gt/bystanders.npz`` (``uvatar synth
--bystanders``) whose root translation is nearest to theirs (mean over the frames).
"""

from __future__ import annotations

import numpy as np
import torch

from uvatar.geometry.distance import point_surface_distance

__all__ = ["evaluate_fits", "bystander_truth"]

PROTOCOL = (
    "MPJPE: mean Euclidean distance (mm) between fitted and true world positions of the body model's "
    "pose-conditioning joints (fingers, toes, eyes excluded), per frame then averaged over frames; no "
    "Procrustes alignment. Angle error: geodesic angle (deg) between fitted and true world orientations of "
    "each conditioning joint. Scan-to-body: distance (mm) from up to {scan_points} evenly strided vertices "
    "of each frame's scan to the posed fitted body surface (exact point-to-triangle), pooled over frames "
    "(median, p90); clothing makes it positive even for a perfect body. Shape error: mean vertex distance "
    "(mm) between the rest-pose body with the fitted shape and with the true shape (from capture.json). "
    "Frames: those with both a fit and gt/frames/<frame>.npz.")


def _rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    rel = np.einsum("...ji,...jk->...ik", Ra, Rb)
    cos = (np.trace(rel, axis1=-2, axis2=-1) - 1) / 2
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _normalized_rotations(transforms: np.ndarray) -> np.ndarray:
    R = transforms[..., :3, :3]
    return R / np.linalg.norm(R[..., :, :1], axis=-2, keepdims=True)


def _pose_batch(body, fits, shape):
    rot = np.stack([body.joint_rotvecs_from_fit(f) for f in fits])
    Rh = np.stack([f.Rh for f in fits])
    Th = np.stack([f.Th for f in fits])
    scale = np.array([f.scale for f in fits], np.float32)
    with torch.no_grad():
        return body.pose(torch.as_tensor(rot), Rh=torch.as_tensor(Rh), Th=torch.as_tensor(Th),
                         scale=torch.as_tensor(scale), shape=None if shape is None else torch.as_tensor(shape))


def true_body_shape(body, capture) -> np.ndarray | None:
    """The studio's true shape: ``gt/info.json`` ``body_shapes``. Captures made before it was recorded
    there: capture.json's shape, unless ``uvatar fit`` replaced it (provenance ``fit``), then the
    body's default shape (what ``uvatar synth`` always used)."""
    from uvatar.capture.gt import read_gt_info

    info = read_gt_info(capture.root, required=False)
    shapes = None if info is None else info.body_shapes
    if shapes is None:
        fitted = "fit" in (capture.info.get("provenance") or {})
        if capture.body_shapes.size and not fitted:
            shapes = capture.body_shapes
        else:
            return body.default_shape().detach().cpu().numpy().astype(np.float32)
    shapes = np.asarray(shapes, np.float32)
    return shapes if shapes.size == len(body.shape_names) else None


def bystander_truth(capture, fits: dict) -> tuple[int, dict, np.ndarray]:
    """(bystander index, {frame: true BodyFit}, true shape (S,)) of the bystander in
    ``gt/bystanders.npz`` nearest to the fits ``{frame: BodyFit}`` (mean root-translation distance)."""
    from uvatar.capture.types import BodyFit
    from uvatar.errors import InputError
    from uvatar.io_utils import read_npz

    path = capture.gt_dir / "bystanders.npz"
    if not path.is_file():
        raise InputError(path, "no bystanders' ground truth (a synthetic capture with bystanders > 0)")
    gt = read_npz(path)
    count = len([k for k in gt if k.startswith("Th_")])
    index = {f: i for i, f in enumerate(capture.frames)}
    frames = [f for f in fits if f in index]
    if not count or not frames:
        raise InputError(path, "no bystander or no frame to compare with")
    fitted = np.stack([np.asarray(fits[f].Th, np.float64).reshape(3) for f in frames])
    rows = [index[f] for f in frames]
    b = int(np.argmin([np.linalg.norm(gt[f"Th_{k}"][rows] - fitted, axis=1).mean() for k in range(count)]))
    truth = {f: BodyFit(poses=gt[f"poses_{b}"][index[f]].reshape(-1), Rh=gt[f"Rh_{b}"][index[f]],
                        Th=gt[f"Th_{b}"][index[f]]) for f in frames}
    return b, truth, np.asarray(gt[f"shape_{b}"], np.float32)


def evaluate_fits(body, capture, fits: dict, shape, scan_points: int = 20000, batch: int = 8) -> dict:
    """Fits ``{frame: BodyFit}`` of ``capture`` (with ``gt/``) against the truth -> dict (mm, deg).

    ``shape``: the fits' shared shape (S,) (None: each fit's own ``shapes`` or the default)."""
    from uvatar.capture.types import BodyFit
    from uvatar.errors import InputError
    from uvatar.io_utils import read_npz

    gt_dir = capture.gt_dir / "frames"
    other = None
    if capture.person is not None:  # another person: the nearest bystander of the synth
        other, truth, true_shape = bystander_truth(capture, fits)
        frames = [f for f in capture.frames if f in truth]
    else:
        frames = [f for f in capture.frames if f in fits and (gt_dir / f"{f}.npz").is_file()]
        true_shape = true_body_shape(body, capture)
    if not frames:
        raise InputError(capture.root, "no frame has both a fit and ground truth (gt/frames/*.npz)")
    if shape is None and np.asarray(fits[frames[0]].shapes).size == len(body.shape_names):
        shape = fits[frames[0]].shapes
    shape = None if shape is None else np.asarray(shape, np.float32)
    joints = list(body.conditioning_joints)
    names = [body.joint_names[j] for j in joints]
    mpjpe, angles, scan_d, per_frame = [], [], [], {}
    for start in range(0, len(frames), batch):
        chunk = frames[start:start + batch]
        if other is None:
            gts = [read_npz(gt_dir / f"{f}.npz") for f in chunk]
            true = [BodyFit(poses=g["pose"], Rh=g["Rh"], Th=g["Th"]) for g in gts]
        else:
            true = [truth[f] for f in chunk]
        pt = _pose_batch(body, true, true_shape)
        pf = _pose_batch(body, [fits[f] for f in chunk], shape)
        jt, jf = pt.joints[:, joints].numpy(), pf.joints[:, joints].numpy()
        err = np.linalg.norm(jt - jf, axis=-1) * 1000                                    # (B, Jc)
        ang = _rotation_angle_deg(_normalized_rotations(pt.joint_transforms[:, joints].numpy()),
                                  _normalized_rotations(pf.joint_transforms[:, joints].numpy()))
        mpjpe.append(err)
        angles.append(ang)
        for i, f in enumerate(chunk):
            row = {"mpjpe_mm": float(err[i].mean()), "angle_deg": float(ang[i].mean())}
            if other is None and capture.has_scan(f):
                scan = capture.load_scan(f)
                step = max(1, scan.num_vertices // scan_points)
                d = point_surface_distance(scan.vertices[::step], pf.vertices[i].numpy(), body.template.faces) * 1000
                scan_d.append(d)
                row["scan_to_body_median_mm"] = float(np.median(d))
            per_frame[f] = row
    err, ang = np.concatenate(mpjpe), np.concatenate(angles)
    out = {
        "frames": len(frames), **({"bystander": other} if other is not None else {}),
        "mpjpe_mm": float(err.mean(1).mean()),
        "mpjpe_median_mm": float(np.median(err.mean(1))),
        "mpjpe_max_frame_mm": float(err.mean(1).max()),
        "per_joint_mpjpe_mm": {n: float(v) for n, v in zip(names, err.mean(0), strict=True)},
        "angle_error_deg": float(ang.mean()),
        "per_joint_angle_deg": {n: float(v) for n, v in zip(names, ang.mean(0), strict=True)},
        "per_frame": per_frame,
        "protocol": PROTOCOL.format(scan_points=scan_points),
    }
    if scan_d:
        d = np.concatenate(scan_d)
        out.update(scan_to_body_median_mm=float(np.median(d)), scan_to_body_p90_mm=float(np.percentile(d, 90)),
                   scan_to_body_mean_mm=float(d.mean()))
    with torch.no_grad():
        zero = torch.zeros(1, body.num_joints, 3)
        rest_fit = body.pose(zero, shape=None if shape is None else torch.as_tensor(shape)).vertices[0].numpy()
        rest_true = body.pose(zero, shape=None if true_shape is None else torch.as_tensor(true_shape)).vertices[0].numpy()
    out["shape_error_mm"] = float(np.linalg.norm(rest_fit - rest_true, axis=1).mean() * 1000)
    out["shape"] = None if shape is None else [float(x) for x in shape]
    out["true_shape"] = None if true_shape is None else [float(x) for x in true_shape]
    return out
