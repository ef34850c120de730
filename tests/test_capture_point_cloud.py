"""Coloured point clouds as textured scans (``uvatar.capture.point_cloud``) and point-cloud takes through
``uvatar capture import``: the surface against the shape the points were drawn from, the texture against
the colours they carry, each bad cloud one line naming its file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from uvatar.capture.point_cloud import (
    PointCloudConfig,
    PointCloudError,
    colours_at,
    mesh_from_point_cloud,
    point_spacing,
    snap_to_points,
)
from uvatar.errors import InputError

AXES = np.array([0.25, 0.85, 0.18])          # an ellipsoid a person's size, metres


def _colour(p: np.ndarray) -> np.ndarray:
    """The colour field the points carry: smooth stripes over the body."""
    return np.clip(0.5 + 0.45 * np.sin(np.array([9.0, 7.0, 11.0]) * p + np.array([0.0, 1.0, 2.0])), 0, 1)


def _ellipsoid_cloud(n: int, seed: int = 0, hole: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    if hole is not None:                        # a cap cut off the top: the shell open there
        d = d[d[:, 1] < hole]
    p = d * AXES
    return p, _colour(p).astype(np.float32)


def _radial_error_m(v: np.ndarray) -> np.ndarray:
    """Distance of each point from the ellipsoid, to first order (metres)."""
    v = np.asarray(v, np.float64)
    g = v / AXES**2
    f = np.sqrt(((v / AXES) ** 2).sum(1)) - 1
    return np.abs(f) * np.sqrt(((v / AXES) ** 2).sum(1)) / np.linalg.norm(g, axis=1)


@pytest.fixture(scope="module")
def ellipsoid():
    points, colors = _ellipsoid_cloud(80_000)
    mesh, made = mesh_from_point_cloud(points, colors, PointCloudConfig(max_faces=30_000))
    return points, colors, mesh, made


def test_spacing_of_a_grid_and_of_a_random_sample():
    g = np.stack(np.meshgrid(np.arange(120), np.arange(120), [0.0]), -1).reshape(-1, 3) * 0.002
    assert point_spacing(g) == pytest.approx(0.002, rel=0.12)
    rng = np.random.default_rng(1)
    plane = np.c_[rng.uniform(0, 1, (40_000, 2)), np.zeros(40_000)]        # 1 / sqrt(40,000 per m²) = 5 mm
    assert point_spacing(plane) == pytest.approx(0.005, rel=0.1)


def test_the_surface_is_the_ellipsoid_closed_outward_and_within_a_voxel(ellipsoid):
    import trimesh

    _, _, mesh, made = ellipsoid
    assert made["faces"] <= 30_000 < made["marched_faces"]
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    assert tm.is_watertight and len(tm.split(only_watertight=False)) == 1
    assert tm.volume == pytest.approx(4 / 3 * np.pi * AXES.prod(), rel=0.01)        # > 0: counter-clockwise
    err = _radial_error_m(mesh.vertices)
    assert np.median(err) < 0.05 * made["voxel"] and err.max() < made["voxel"]


def test_the_texture_holds_the_points_colours(ellipsoid):
    from uvatar.geometry.uv_raster import UVRasterConfig, rasterize_uv

    _, _, mesh, _ = ellipsoid
    res = mesh.texture.shape[0]
    raster = rasterize_uv(mesh.uvs, mesh.uv_faces, res, UVRasterConfig(conservative=False))
    face, bary = raster.face_index.reshape(-1), raster.bary.reshape(-1, 3)
    inside = face >= 0
    at = np.einsum("nc,ncd->nd", bary[inside], mesh.vertices[mesh.faces[face[inside]]].astype(np.float64))
    err = np.abs(mesh.texture.reshape(-1, 3)[inside] - _colour(at))
    assert np.median(err) < 0.02 and np.quantile(err, 0.99) < 0.1      # the field moves ~0.05 a point spacing


def test_colours_at_is_the_inverse_distance_mean_of_the_nearest_points():
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(2)
    points, colors = rng.uniform(size=(300, 3)), rng.uniform(size=(300, 3)).astype(np.float32)
    queries = rng.uniform(size=(50, 3))
    got = colours_at(queries, cKDTree(points), colors, 4, 1e-9)
    for q, c in zip(queries, got, strict=True):                     # the plain twin: every distance, the four smallest
        d = np.linalg.norm(points - q, axis=1)
        near = np.argsort(d)[:4]
        w = 1 / (d[near] + 1e-9)
        np.testing.assert_allclose(c, (w[:, None] * colors[near]).sum(0) / w.sum(), rtol=1e-5)
    exact = colours_at(points[:5], cKDTree(points), colors, 4, 1e-9)
    np.testing.assert_allclose(exact, colors[:5], atol=1e-5)                 # on a point: its colour


def test_snapping_puts_a_shifted_sheet_back_on_its_points():
    from scipy.spatial import cKDTree

    n = 30
    xy = np.stack(np.meshgrid(np.arange(n), np.arange(n)), -1).reshape(-1, 2) * 0.01
    k = np.arange(n * n).reshape(n, n)
    faces = np.concatenate([np.stack([k[:-1, :-1], k[:-1, 1:], k[1:, :-1]], -1).reshape(-1, 3),
                            np.stack([k[1:, :-1], k[:-1, 1:], k[1:, 1:]], -1).reshape(-1, 3)])
    g = np.stack(np.meshgrid(np.arange(3 * n), np.arange(3 * n)), -1).reshape(-1, 2) * (0.01 / 3)
    points = np.c_[g, np.zeros(len(g))]
    vertices = np.c_[xy, np.full(len(xy), 0.004)]
    snapped = snap_to_points(vertices, faces, cKDTree(points), points, 8, max_move=0.01)
    inner = (xy > 0.02).all(1) & (xy < 0.27).all(1)
    np.testing.assert_allclose(snapped[inner, 2], 0.0, atol=1e-9)
    np.testing.assert_allclose(snapped[:, :2], xy, atol=1e-12)            # along the normal only
    capped = snap_to_points(vertices, faces, cKDTree(points), points, 8, max_move=0.001)
    np.testing.assert_allclose(capped[inner, 2], 0.003, atol=1e-9)


def test_an_open_shell_and_a_handful_of_points_are_refused():
    points, colors = _ellipsoid_cloud(40_000, hole=0.5)               # the top third of the shell missing
    with pytest.raises(PointCloudError, match="enclose no volume"):
        mesh_from_point_cloud(points, colors)
    with pytest.raises(PointCloudError, match="at least"):
        mesh_from_point_cloud(points[:50], colors[:50])
    with pytest.raises(ValueError, match="voxel must be > 0"):
        PointCloudConfig(voxel=0)


def _write_ply_points(path: Path, points: np.ndarray, colors: np.ndarray | None) -> None:
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")] + ([("red", "u1"), ("green", "u1"), ("blue", "u1")]
                                                            if colors is not None else [])
    rows = np.zeros(len(points), fields)
    for k, c in enumerate("xyz"):
        rows[c] = points[:, k]
    if colors is not None:
        for k, c in enumerate(("red", "green", "blue")):
            rows[c] = np.round(colors[:, k] * 255)
    head = ["ply", "format binary_little_endian 1.0", f"element vertex {len(points)}"]
    head += [f"property {'float' if t == '<f4' else 'uchar'} {n}" for n, t in fields] + ["end_header"]
    path.write_bytes(("\n".join(head) + "\n").encode() + rows.tobytes())


def test_a_take_of_point_clouds_imports_as_textured_scans(tmp_path):
    """A folder of PLY and Draco point clouds (8i's and MPEG's takes are such PLYs): each frame a closed
    textured scan; a cloud without colours is one line naming its file, the rest import."""
    import DracoPy

    from uvatar.capture.importers.frame_reader import POINT_CLOUD_NOTE
    from uvatar.capture.importers.mesh_sequence import import_mesh_sequence
    from uvatar.capture.importers.pipeline import ImportConfig
    from uvatar.capture.meshio import read_mesh

    src = tmp_path / "take"
    src.mkdir()
    clouds = [_ellipsoid_cloud(60_000, seed=s) for s in range(3)]
    _write_ply_points(src / "frame_000.ply", *clouds[0])
    (src / "frame_001.drc").write_bytes(DracoPy.encode(clouds[1][0], colors=np.round(clouds[1][1] * 255).astype(np.uint8)))
    _write_ply_points(src / "frame_002.ply", clouds[2][0], None)
    summary = import_mesh_sequence(src, tmp_path / "cap", ImportConfig(point_voxel=2.0), progress=False)
    assert summary["frames"] == 2 and summary["skipped"] == 1
    assert POINT_CLOUD_NOTE in summary["notes"]
    assert any("frame_002.ply" in p and "without colours" in p for p in summary["problems"])
    for name in ("000000", "000001"):
        scan = read_mesh(tmp_path / "cap" / "scans" / f"{name}.ply")
        assert scan.num_faces > 10_000 and scan.has_uvs and scan.texture is not None
        assert np.median(_radial_error_m(scan.vertices)) < 1e-3            # metres, +y up as the cloud stood


def test_read_mesh_refuses_a_point_cloud_and_a_draco_cloud_keeps_its_colours(tmp_path):
    import DracoPy
    from scipy.spatial import cKDTree

    from uvatar.capture.mesh_draco import read_drc
    from uvatar.capture.meshio import read_mesh

    points, colors = _ellipsoid_cloud(2000)
    _write_ply_points(tmp_path / "cloud.ply", points, colors)
    with pytest.raises(InputError, match=r"cloud\.ply.*holds a point cloud \(no faces\), not a triangle mesh"):
        read_mesh(tmp_path / "cloud.ply")
    cloud = read_mesh(tmp_path / "cloud.ply", points_ok=True)
    assert cloud.num_faces == 0 and np.abs(cloud.vertex_colors - colors).max() <= 0.5 / 255 + 1e-6
    (tmp_path / "cloud.drc").write_bytes(DracoPy.encode(points, colors=np.round(colors * 255).astype(np.uint8)))
    drc = read_drc(tmp_path / "cloud.drc")
    assert drc.num_faces == 0 and drc.num_vertices == len(points)
    d, ref = cKDTree(points).query(drc.vertices)             # Draco reorders and quantizes (14 bits) the points
    assert d.max() < 2 * np.ptp(points, 0).max() / 2**14 and len(np.unique(ref)) == len(points)
    assert np.abs(drc.vertex_colors - colors[ref]).max() <= 0.5 / 255 + 1e-6


def test_a_voxelized_cloud_in_voxel_units_imports_at_its_stated_voxel_size(tmp_path):
    """8i's takes are integer voxel indices: the height detection takes them for millimetres and says
    so; ``units`` as metres per unit (the voxel's size) puts the scan back at its size."""
    from uvatar.capture.importers.mesh_sequence import import_mesh_sequence
    from uvatar.capture.importers.pipeline import ImportConfig
    from uvatar.capture.meshio import read_mesh

    voxel = 0.002
    points, colors = _ellipsoid_cloud(120_000, seed=3)
    cells, first = np.unique(np.round(points / voxel), axis=0, return_index=True)
    src = tmp_path / "take"
    src.mkdir()
    _write_ply_points(src / "frame_000.ply", cells, colors[first])
    guessed = import_mesh_sequence(src, tmp_path / "guessed", progress=False)
    assert any("grid of whole numbers" in n for n in guessed["notes"])
    assert any(n.startswith("units not stated by the files: mm (the first frame is 850") for n in guessed["notes"])
    stated = import_mesh_sequence(src, tmp_path / "stated", ImportConfig(units=str(voxel)), progress=False)
    assert not any("grid of whole numbers" in n for n in stated["notes"])
    scan = read_mesh(tmp_path / "stated" / "scans" / "000000.ply")
    assert np.ptp(scan.vertices[:, 1]) == pytest.approx(2 * AXES[1], abs=0.01)
    assert np.median(_radial_error_m(scan.vertices)) < voxel


@pytest.mark.parametrize("units, ok", [("m", True), ("0.001729", True), ("1e-3", True), ("0", False),
                                       ("-0.5", False), ("km", False), ("nan", False)])
def test_units_are_a_named_unit_or_metres_per_unit(units, ok):
    from uvatar.capture.importers.calibration import unit_scale
    from uvatar.capture.importers.pipeline import ImportConfig

    assert (unit_scale(units) is not None) == ok
    if ok:
        assert ImportConfig(units=units).units == units
    else:
        with pytest.raises(ValueError, match="units must be m, cm, mm or metres per unit"):
            ImportConfig(units=units)


def test_a_cloud_with_a_stray_point_far_away_is_refused_before_its_grid_is_made():
    points, colors = _ellipsoid_cloud(20_000)
    points = np.vstack([points, [[0.0, 5e3, 5e3]]])
    colors = np.vstack([colors, [[1.0, 0.0, 0.0]]])
    with pytest.raises(PointCloudError, match="stray points far from the rest"):
        mesh_from_point_cloud(points, colors)
