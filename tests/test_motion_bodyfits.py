"""SMPL EasyMocap fits → anny by a real conversion (joint rotations through the rig mapping and
rest frames), checked on a fake SMPL model whose T-pose skeleton has anny's bone lengths: the
converted anny joints land on the SMPL joints."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uvatar.body import clear_body_model_cache, load_body_model
from uvatar.capture.fits import write_fit
from uvatar.capture.types import BodyFit
from uvatar.motion.amass import SMPL_BODY_JOINTS

pytest.importorskip("smplx")  # the SMPL backend's optional extra

SMPL_PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21]
TO_SEMANTIC = {"pelvis": "pelvis", "spine1": "spine1", "spine2": "spine2", "spine3": "spine3", "neck": "neck",
               "head": "head"}
for _side, _p in (("left", "l_"), ("right", "r_")):
    for _k in ("collar", "shoulder", "elbow", "wrist", "hip", "knee", "ankle"):
        TO_SEMANTIC[f"{_side}_{_k}"] = _p + _k
    TO_SEMANTIC[f"{_side}_foot"] = _p + "toe"
V, NB = 6890, 10


def _smpl_tpose_joints(anny) -> np.ndarray:
    """(24, 3) SMPL joints at anny's joint positions, the arms straightened out to a T-pose."""
    rest = anny.template.rest_joints.astype(np.float64)
    sj = anny.semantic_joints
    J = np.zeros((24, 3))
    for i, name in enumerate(SMPL_BODY_JOINTS):
        J[i] = rest[sj[TO_SEMANTIC[name]]]
    for side, sign, hand in (("l_", 1.0, 22), ("r_", -1.0, 23)):
        s = SMPL_BODY_JOINTS.index(("left" if sign > 0 else "right") + "_shoulder")
        upper = np.linalg.norm(rest[sj[side + "elbow"]] - rest[sj[side + "shoulder"]])
        fore = np.linalg.norm(rest[sj[side + "wrist"]] - rest[sj[side + "elbow"]])
        J[s + 2] = J[s] + [sign * upper, 0, 0]
        J[s + 4] = J[s + 2] + [sign * fore, 0, 0]
        J[hand] = J[s + 4] + [sign * 0.08, 0, 0]
    return J


def _fake_smpl(joints: np.ndarray, rng) -> dict:
    """A fake SMPL model whose regressor gives exactly ``joints`` (8 vertices around each)."""
    v = rng.normal(scale=0.3, size=(V, 3)) + [0, 1, 0]
    regressor = np.zeros((24, V))
    ring = np.concatenate([np.eye(3), -np.eye(3), [[0.5, 0.5, 0.5], [-0.5, -0.5, -0.5]]]) * 0.02
    for j in range(24):
        idx = np.arange(8) + 8 * j
        v[idx] = joints[j] + ring
        regressor[j, idx] = 1.0 / 8
    weights = rng.random((V, 24)) ** 8
    weights /= weights.sum(1, keepdims=True)
    return {"v_template": v, "f": rng.choice(V, size=(200, 3)).astype(np.int64),
            "shapedirs": rng.normal(scale=0.01, size=(V, 3, NB)),
            "posedirs": np.zeros((V, 3, 9 * 23), np.float32), "J_regressor": regressor, "weights": weights,
            "kintree_table": np.stack([np.array(SMPL_PARENTS) % 2**32, np.arange(24)]).astype(np.int64)}


@pytest.fixture()
def smpl_fits(tmp_path, monkeypatch):
    from test_body_smplx import _write_uv_obj

    anny = load_body_model("anny")
    rng = np.random.default_rng(0)
    data = _fake_smpl(_smpl_tpose_joints(anny), rng)
    root = tmp_path / "smpl"
    root.mkdir()
    np.savez(root / "SMPL_NEUTRAL.npz", **data)
    _write_uv_obj(root / "smpl_uv.obj", data, rng)
    monkeypatch.setenv("UVATAR_SMPL_DIR", str(root))
    clear_body_model_cache()
    T = 6
    poses = rng.normal(scale=0.35, size=(T, 24, 3))
    poses[:, 0] = 0.0
    poses[:, [4, 5], 1:] = 0.0  # knees bend about x, as knees do
    Rh = rng.normal(scale=0.5, size=(T, 3))
    Th = rng.normal(scale=0.3, size=(T, 3)) + [0, 1, 0]
    for t in range(T):
        write_fit(tmp_path / "fits" / f"{t:06d}.json",
                  BodyFit(poses=poses[t].reshape(-1), Rh=Rh[t], Th=Th[t], shapes=np.zeros(NB)))
    yield anny, tmp_path, poses, Rh, Th
    clear_body_model_cache()


def test_smpl_fits_to_anny_joints_match(smpl_fits):
    from uvatar.cli.main import main
    from uvatar.motion.sequences import load_motion

    anny, tmp, poses, Rh, Th = smpl_fits
    out = tmp / "anny.npz"
    assert main(["motion", "convert", str(tmp / "fits"), str(out), "--body", "anny"]) == 0
    motion = load_motion(out, body=anny)
    assert motion.body == "anny" and motion.num_joints == anny.num_joints  # not SMPL's 72 values relabelled
    assert motion.info["converted_from"] == "smpl" and "smpl model" in motion.info["source_rest_joints"]
    smpl = load_body_model("smpl")
    with torch.no_grad():
        ref = smpl.pose(torch.as_tensor(poses, dtype=torch.float32), Rh=torch.as_tensor(Rh, dtype=torch.float32),
                        Th=torch.as_tensor(Th, dtype=torch.float32)).joints.numpy()
        got = anny.pose(motion.joint_rotvecs, Rh=motion.Rh, Th=motion.Th).joints.numpy()
    sj = anny.semantic_joints
    dist = np.stack([np.linalg.norm(got[:, sj[TO_SEMANTIC[n]]] - ref[:, i], axis=-1)
                     for i, n in enumerate(SMPL_BODY_JOINTS)], 1)  # (T, 22) metres
    print(f"SMPL -> anny joint distance: max {1e3 * dist.max():.4f} mm, median {1e3 * np.median(dist):.4f} mm")
    assert dist.max() < 0.03, dict(zip(SMPL_BODY_JOINTS, dist.max(0).round(3), strict=True))


def test_smpl_fits_shape_count_mismatch_is_an_error(smpl_fits, capsys):
    from uvatar.cli.main import main

    anny, tmp, poses, Rh, Th = smpl_fits
    fit = BodyFit(poses=poses[0].reshape(-1), Rh=Rh[0], Th=Th[0], shapes=np.zeros(7))
    for t in range(2):
        write_fit(tmp / "bad" / f"{t:06d}.json", fit)
    assert main(["motion", "convert", str(tmp / "bad"), str(tmp / "x.npz"), "--body", "anny"]) == 1
    assert "shapes have 7 values, the smpl model has 10 betas" in capsys.readouterr().err
    assert not (tmp / "x.npz").exists()
