"""EasyMocap fits: JSON variants, NPZ round trip, each bad-input case."""

from __future__ import annotations

import json

import numpy as np
import pytest

from uvatar.capture.fits import read_fit, read_fits, read_fits_npz, write_fit, write_fits_npz
from uvatar.capture.types import BodyFit
from uvatar.errors import InputError


def make_fit(seed=0, joints=4, shapes=3) -> BodyFit:
    rng = np.random.default_rng(seed)
    return BodyFit(poses=rng.normal(size=joints * 3), Rh=rng.normal(size=3), Th=rng.normal(size=3),
                   shapes=rng.normal(size=shapes), scale=1.0 + seed * 0.1, id=seed)


def assert_same_fit(a: BodyFit, b: BodyFit):
    for key in ("poses", "Rh", "Th", "shapes"):
        np.testing.assert_allclose(getattr(a, key), getattr(b, key), rtol=1e-6, atol=1e-6)
    assert a.scale == pytest.approx(b.scale) and a.id == b.id


def test_json_round_trip(tmp_path):
    fit = make_fit(2)
    write_fit(tmp_path / "000000.json", fit)
    assert_same_fit(read_fit(tmp_path / "000000.json"), fit)
    data = json.loads((tmp_path / "000000.json").read_text())
    assert isinstance(data, list) and np.shape(data[0]["Rh"]) == (1, 3)  # EasyMocap nesting


@pytest.mark.parametrize("wrap", ["list", "annots"])
@pytest.mark.parametrize("nest", [True, False])
def test_json_variants(tmp_path, wrap, nest):
    person = {"id": 3, "Rh": [0.1, 0.2, 0.3], "Th": [1, 2, 3], "poses": [0.0] * 9, "shapes": [0.5] * 2}
    if nest:
        person = {k: [v] if isinstance(v, list) else v for k, v in person.items()}
    data = [person] if wrap == "list" else {"annots": [person]}
    (tmp_path / "f.json").write_text(json.dumps(data))
    fit = read_fit(tmp_path / "f.json")
    np.testing.assert_allclose(fit.Rh, [0.1, 0.2, 0.3], rtol=1e-6)
    assert fit.poses.shape == (9,) and fit.shapes.shape == (2,) and fit.scale == 1.0 and fit.id == 3


def test_several_people_and_person_id(tmp_path):
    write_fit(tmp_path / "f.json", [make_fit(0), make_fit(1)])
    assert len(read_fits(tmp_path / "f.json")) == 2
    assert_same_fit(read_fit(tmp_path / "f.json", person_id=1), make_fit(1))
    with pytest.raises(InputError, match="no person with id 7"):
        read_fit(tmp_path / "f.json", person_id=7)


@pytest.mark.parametrize("change,message", [
    ({"Rh": [[float("nan"), 0, 0]]}, "Rh contains NaN"),
    ({"poses": [[0.0, float("nan"), 0.0]]}, "poses contains NaN"),
    ({"Th": [[0, 0]]}, r"Th has shape \(1, 2\)"),
    ({"Rh": "abc"}, "Rh is not a numeric array"),
    ({"poses": [[0.0] * 7]}, "positive multiple of 3"),
    ({"scale": -1}, "scale must be one positive number"),
    ({"poses": None}, "poses is not a numeric array"),
])
def test_bad_fields_name_file_and_field(tmp_path, change, message):
    person = {"id": 0, "Rh": [[0, 0, 0]], "Th": [[0, 0, 0]], "poses": [[0.0] * 6], "shapes": [[0.0]]}
    person.update(change)
    path = tmp_path / "000004.json"
    path.write_text(json.dumps([person]))
    with pytest.raises(InputError, match=message) as info:
        read_fit(path)
    assert str(info.value).startswith(str(path))


def test_missing_keys_bad_json_and_expected_size(tmp_path):
    path = tmp_path / "f.json"
    path.write_text(json.dumps([{"Rh": [0, 0, 0]}]))
    with pytest.raises(InputError, match="missing key.*Th, poses"):
        read_fit(path)
    path.write_text("[{")
    with pytest.raises(InputError, match="invalid JSON"):
        read_fit(path)
    path.write_text("[]")
    with pytest.raises(InputError, match="no person"):
        read_fit(path)
    write_fit(path, make_fit(0, joints=4))
    with pytest.raises(InputError, match=r"poses has shape \(1, 12\), expected \(312,\)"):
        read_fit(path, num_pose_values=312)
    with pytest.raises(InputError, match="fit file is missing"):
        read_fit(tmp_path / "nope.json")


def test_npz_round_trip(tmp_path):
    fits = {f"{i:06d}": make_fit(i) for i in range(4)}
    write_fits_npz(tmp_path / "fits.npz", fits)
    back = read_fits_npz(tmp_path / "fits.npz")
    assert list(back) == list(fits)
    for frame in fits:
        assert_same_fit(back[frame], fits[frame])
    data = np.load(tmp_path / "fits.npz")
    assert data["poses"].shape == (4, 12) and data["Rh"].shape == (4, 3) and data["scale"].shape == (4,)


def test_npz_errors(tmp_path):
    with pytest.raises(InputError, match="different poses sizes"):
        write_fits_npz(tmp_path / "a.npz", {"0": make_fit(0, joints=2), "1": make_fit(1, joints=3)})
    np.savez(tmp_path / "b.npz", frames=np.array(["0"]), poses=np.zeros((1, 6)), Rh=np.zeros((1, 2)),
             Th=np.zeros((1, 3)))
    with pytest.raises(InputError, match="Rh has shape"):
        read_fits_npz(tmp_path / "b.npz")
    np.savez(tmp_path / "c.npz", frames=np.array(["0"]), poses=np.full((1, 6), np.nan), Rh=np.zeros((1, 3)),
             Th=np.zeros((1, 3)))
    with pytest.raises(InputError, match="poses contains NaN"):
        read_fits_npz(tmp_path / "c.npz")
