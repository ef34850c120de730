"""UV part masks of the anny body at 64 and 256 texels, and the ``uvatar body info`` command."""

import json

import numpy as np
import pytest

from uvatar.body import PART_NAMES, load_body_model, part_masks, part_vertex_weights
from uvatar.body.masks import part_joint_groups


@pytest.fixture(scope="module")
def body():
    return load_body_model("anny")


@pytest.mark.parametrize("resolution", [64, 256])
def test_part_masks_shapes_and_relations(body, resolution):
    from uvatar.geometry import rasterize_uv

    masks = part_masks(body, resolution)
    valid = rasterize_uv(body.template.uvs, body.template.uv_faces, resolution).mask
    assert set(masks) == set(PART_NAMES)
    for name, m in masks.items():
        assert m.shape == (resolution, resolution) and m.dtype == bool
        assert m.any(), name
        assert not (m & ~valid).any(), name  # only covered texels
    assert not (masks["hands"] & masks["feet"]).any()
    assert not (masks["hands"] & masks["head"]).any()
    assert not (masks["feet"] & masks["head"]).any()
    assert not (masks["face"] & ~masks["head"]).any()
    assert not (masks["fingers_toes"] & ~(masks["hands"] | masks["feet"])).any()
    assert masks["face"].sum() < masks["head"].sum()
    assert masks["fingers_toes"].sum() < (masks["hands"] | masks["feet"]).sum()
    # no part covers most of the body
    assert (masks["hands"] | masks["feet"] | masks["head"]).sum() < 0.6 * valid.sum()


def test_part_masks_mirror(body):
    """Left and right hands carry equal weight in the vertex masks (anny is symmetric)."""
    w = part_vertex_weights(body)["hands"] > 0.5
    x = body.template.vertices[:, 0]
    assert abs(int((w & (x > 0)).sum()) - int((w & (x < 0)).sum())) <= 2
    assert (body.template.vertices[w, 1] < 0.4).all()  # hands hang below the shoulders
    groups = part_joint_groups(body)
    names = [body.joint_names[j] for j in groups["fingers_toes"]]
    assert names and all(n.startswith(("finger", "toe")) for n in names)
    assert "wrist.L" in [body.joint_names[j] for j in groups["hands"]]


def test_face_is_frontal(body):
    m = part_masks(body, 128)
    from uvatar.geometry import rasterize_uv, texel_positions

    raster = rasterize_uv(body.template.uvs, body.template.uv_faces, 128)
    pos = np.asarray(texel_positions(raster, body.template.faces, body.template.vertices))
    head_z = body.template.rest_joints[body.semantic_joints["head"], 2]
    assert (pos[m["face"]][:, 2] > head_z).all()
    assert np.median(pos[m["head"] & ~m["face"]][:, 2]) < np.median(pos[m["face"]][:, 2])


def test_cli_body_info(capsys):
    from uvatar.cli.main import main

    assert main(["body", "info", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert (info["vertices"], info["faces"], info["uvs"], info["joints"]) == (13718, 27420, 21334, 104)
    assert len(info["conditioning_joints"]) == 35 and "height" in info["shape_names"]
    assert main(["body", "info"]) == 0
    assert "conditioning joints (35)" in capsys.readouterr().out


def test_cli_body_info_missing_smpl(monkeypatch, tmp_path, capsys):
    from uvatar.cli.main import main

    monkeypatch.delenv("UVATAR_SMPL_DIR", raising=False)
    assert main(["body", "info", "--model", "smpl", "--model-dir", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "smpl.is.tue.mpg.de" in err and len(err.strip().splitlines()) == 1


def test_cli_body_render(tmp_path):
    import imageio.v3 as iio

    from uvatar.cli.main import main

    out = tmp_path / "body.png"
    assert main(["body", "render", str(out), "--size", "48", "--parts"]) == 0
    img = iio.imread(out)
    assert img.ndim == 3 and img.shape[0] >= 48 and (img < 250).any()


def test_regions_follow_the_skinning_and_cover_the_charts():
    from uvatar.body import load_body_model
    from uvatar.body.masks import REGION_NAMES, part_masks, region_label_map, region_vertex_labels
    from uvatar.geometry import rasterize_uv

    body = load_body_model("anny")
    labels = region_vertex_labels(body)
    t = body.template
    assert labels.shape == (len(t.vertices),) and set(np.unique(labels)) == set(range(len(REGION_NAMES)))
    w = np.asarray(t.skin_weights)
    for joint, region in (("l_wrist", "hands"), ("r_knee", "legs"), ("l_elbow", "arms"), ("spine2", "torso")):
        j = body.semantic_joints[joint]
        own = w[:, j] > 0.9 * w[:, j].max()  # the vertices this joint moves most
        assert own.any() and (labels[own] == REGION_NAMES.index(region)).all(), joint
    lmap = region_label_map(body, 128)
    assert ((lmap >= 0) == rasterize_uv(t.uvs, t.uv_faces, 128).mask).all()
    face = part_masks(body, 128)["face"]  # the face region is the face part mask, up to texels on its border
    assert (lmap[face] == REGION_NAMES.index("face")).mean() > 0.9
