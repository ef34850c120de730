"""SMPL backend on a fake SMPL model written here; checks posing against smplx's own forward."""

import math
import pickle

import numpy as np
import pytest
import torch

pytest.importorskip("smplx")

from uvatar.body import clear_body_model_cache, load_body_model  # noqa: E402
from uvatar.body.smplx_backend import SmplxBody, SmplxConfig, read_obj_uvs  # noqa: E402
from uvatar.errors import InputError  # noqa: E402

SMPL_PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21]
V, J, NB = 6890, 24, 10  # smplx's forward picks extra joints from fixed SMPL vertex ids, so keep V


def _fake_smpl(rng):
    F = 200
    v = rng.normal(scale=0.3, size=(V, 3))
    regressor = np.zeros((J, V))
    for j in range(J):
        idx = rng.choice(V, 8, replace=False)
        regressor[j, idx] = 1.0 / 8
    weights = rng.random((V, J)) ** 8
    weights /= weights.sum(1, keepdims=True)
    return {
        "v_template": v, "f": rng.choice(V, size=(F, 3)).astype(np.int64),
        "shapedirs": rng.normal(scale=0.01, size=(V, 3, NB)),
        "posedirs": rng.normal(scale=0.01, size=(V, 3, 9 * (J - 1))).astype(np.float32),
        "J_regressor": regressor, "weights": weights,
        "kintree_table": np.stack([np.array(SMPL_PARENTS) % 2**32, np.arange(J)]).astype(np.int64),
    }


def _write_uv_obj(path, data, rng):
    F = len(data["f"])
    with open(path, "w") as fh:
        for x in data["v_template"][:3]:
            fh.write(f"v {x[0]} {x[1]} {x[2]}\n")
        for uv in rng.random((3 * F, 2)):
            fh.write(f"vt {uv[0]:.6f} {uv[1]:.6f}\n")
        for i, f in enumerate(data["f"]):
            fh.write("f " + " ".join(f"{f[k] + 1}/{3 * i + k + 1}" for k in range(3)) + "\n")


@pytest.fixture(scope="module")
def smpl_dir(tmp_path_factory):
    rng = np.random.default_rng(0)
    root = tmp_path_factory.mktemp("smpl")
    data = _fake_smpl(rng)
    np.savez(root / "SMPL_NEUTRAL.npz", **data)
    with open(root / "SMPL_MALE.pkl", "wb") as fh:
        pickle.dump(data, fh)
    _write_uv_obj(root / "smpl_uv.obj", data, rng)
    return root, data


def _smplx_reference(data, rotvecs, betas):
    import smplx

    model = smplx.SMPL(model_path="unused", data_struct=smplx.utils.Struct(**data), num_betas=NB)
    out = model(global_orient=rotvecs[:, 0], body_pose=rotvecs[:, 1:].reshape(len(rotvecs), -1),
                betas=betas)
    return out.vertices, out.joints[:, :J]


@pytest.mark.parametrize("gender", ["neutral", "male"])  # .npz and .pkl
def test_smpl_pose_matches_smplx_forward(smpl_dir, gender):
    root, data = smpl_dir
    body = SmplxBody(SmplxConfig("smpl", model_dir=str(root), gender=gender))
    assert body.num_joints == 24 and body.template.vertices.shape == (V, 3)
    assert body.conditioning_joints == tuple(range(1, 24))
    g = torch.Generator().manual_seed(0)
    rv = 0.5 * torch.randn(3, J, 3, generator=g)
    betas = torch.randn(3, NB, generator=g)
    posed = body.pose(rv, shape=betas)
    ref_v, ref_j = _smplx_reference(data, rv, betas)
    torch.testing.assert_close(posed.vertices, ref_v, atol=1e-5, rtol=0)
    torch.testing.assert_close(posed.joints, ref_j, atol=1e-5, rtol=0)


def test_smpl_rest_template_uvs_and_world_axes(smpl_dir):
    root, data = smpl_dir
    body = SmplxBody(SmplxConfig("smpl", model_dir=str(root)))
    t = body.template
    np.testing.assert_allclose(body.rest_pose().vertices[0].numpy(), t.vertices, atol=1e-6)
    assert t.uvs.shape == (3 * len(data["f"]), 2) and t.uv_faces.shape == t.faces.shape
    np.testing.assert_array_equal(t.faces, data["f"])
    np.testing.assert_allclose(body.rest_joint_rotations, np.repeat(np.eye(3)[None], J, 0))
    # SMPL local axes are world axes: world_to_local is the identity, and the known answer holds
    sj = body.semantic_joints
    world = torch.zeros(1, J, 3)
    world[0, sj["l_elbow"]] = torch.tensor([math.radians(60), 0, 0])
    torch.testing.assert_close(body.world_to_local_rotvecs(world), world)
    posed = body.pose(world)
    rest = torch.as_tensor(t.rest_joints)
    e = rest[sj["l_elbow"]]
    import roma

    Rx = roma.rotvec_to_rotmat(world[0, sj["l_elbow"]])
    torch.testing.assert_close(posed.joints[0, sj["l_wrist"]], e + Rx @ (rest[sj["l_wrist"]] - e), atol=1e-5, rtol=0)


def test_load_body_model_uses_env(smpl_dir, monkeypatch):
    root, _ = smpl_dir
    clear_body_model_cache()
    monkeypatch.setenv("UVATAR_SMPL_DIR", str(root))
    body = load_body_model("smpl")
    assert body.name == "smpl" and load_body_model("smpl") is body
    clear_body_model_cache()


def test_missing_model_says_what_to_get(tmp_path, monkeypatch):
    monkeypatch.delenv("UVATAR_SMPL_DIR", raising=False)
    clear_body_model_cache()
    with pytest.raises(InputError, match="smpl.is.tue.mpg.de"):
        load_body_model("smpl")
    with pytest.raises(InputError, match=r"smpl-x.is.tue.mpg.de") as err:
        load_body_model("smplx", model_dir=tmp_path)
    assert str(tmp_path) in str(err.value) and "SMPLX_NEUTRAL.npz" in str(err.value)


def test_missing_uv_obj_and_bad_files(smpl_dir, tmp_path):
    root, data = smpl_dir
    np.savez(tmp_path / "SMPL_NEUTRAL.npz", **data)
    with pytest.raises(InputError, match="UV"):
        SmplxBody(SmplxConfig("smpl", model_dir=str(tmp_path)))
    with pytest.raises(InputError, match="triangles"):
        bad = tmp_path / "bad_uv.obj"
        bad.write_text("vt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n")
        SmplxBody(SmplxConfig("smpl", model_dir=str(tmp_path), uv_obj=str(bad)))
    broken = tmp_path / "broken" / "SMPL_NEUTRAL.npz"
    broken.parent.mkdir()
    np.savez(broken, v_template=data["v_template"])
    with pytest.raises(InputError, match="missing"):
        SmplxBody(SmplxConfig("smpl", model_dir=str(broken), uv_obj=str(root / "smpl_uv.obj")))


def test_read_obj_uvs_triangulates_quads(tmp_path):
    p = tmp_path / "quad.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nf 1/1 2/2 3/3 4/4\n")
    faces, uvs, uv_faces = read_obj_uvs(p)
    np.testing.assert_array_equal(faces, [[0, 1, 2], [0, 2, 3]])
    np.testing.assert_array_equal(uv_faces, faces)
    assert uvs.shape == (4, 2)
    p.write_text("v 0 0 0\nf 1 1 1\n")
    with pytest.raises(InputError, match="texture"):
        read_obj_uvs(p)


SMPLX_PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15,
                 20, 25, 26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 20, 37, 38,
                 21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49, 50, 21, 52, 53]


def test_smplx_pose_matches_smplx_lbs(tmp_path):
    """SMPL-X (55 joints) on a small fake model, against smplx's own ``lbs`` with its buffers."""
    import smplx

    rng = np.random.default_rng(1)
    Vx, Jx = 300, 55
    regressor = np.zeros((Jx, Vx))
    for j in range(Jx):
        regressor[j, rng.choice(Vx, 5, replace=False)] = 0.2
    weights = rng.random((Vx, Jx)) ** 8
    data = {
        "v_template": rng.normal(scale=0.3, size=(Vx, 3)), "f": rng.choice(Vx, size=(100, 3)).astype(np.int64),
        "shapedirs": rng.normal(scale=0.01, size=(Vx, 3, 20)),
        "posedirs": rng.normal(scale=0.01, size=(Vx, 3, 9 * (Jx - 1))),
        "J_regressor": regressor, "weights": weights / weights.sum(1, keepdims=True),
        "kintree_table": np.stack([np.array(SMPLX_PARENTS) % 2**32, np.arange(Jx)]).astype(np.int64),
        "hands_componentsl": np.eye(45), "hands_componentsr": np.eye(45),
        "hands_meanl": rng.normal(size=45), "hands_meanr": rng.normal(size=45),
        "lmk_faces_idx": np.zeros(5, np.int64), "lmk_bary_coords": np.full((5, 3), 1 / 3),
    }
    np.savez(tmp_path / "SMPLX_NEUTRAL.npz", **data)
    _write_uv_obj(tmp_path / "smplx_uv.obj", data, rng)
    body = SmplxBody(SmplxConfig("smplx", model_dir=str(tmp_path)))
    assert body.num_joints == 55 and body.conditioning_joints == tuple(range(1, 22))
    sj = body.semantic_joints
    assert (sj["l_wrist"], sj["r_wrist"], sj["head"], sj["jaw"]) == (20, 21, 15, 22)
    assert body.joint_names[25] == "left_index1" and body.joint_names[54] == "right_thumb3"
    g = torch.Generator().manual_seed(2)
    rv = 0.4 * torch.randn(2, Jx, 3, generator=g)
    betas = torch.randn(2, 10, generator=g)
    m = smplx.SMPLX(model_path=str(tmp_path / "SMPLX_NEUTRAL.npz"), num_betas=10, use_pca=False,
                    flat_hand_mean=True)
    ref_v, ref_j = smplx.lbs.lbs(betas, rv.reshape(2, -1), m.v_template, m.shapedirs, m.posedirs,
                                 m.J_regressor, m.parents, m.lbs_weights)
    posed = body.pose(rv, shape=betas)
    torch.testing.assert_close(posed.vertices, ref_v, atol=1e-5, rtol=0)
    torch.testing.assert_close(posed.joints, ref_j, atol=1e-5, rtol=0)
