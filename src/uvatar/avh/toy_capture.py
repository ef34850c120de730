"""A toy synthetic capture + its exact bake, on :class:`ToyTubeBody`, for AVH animate/eval tests.

Each frame: a random pose of the conditioning joints; texture and body-frame displacement from
:func:`uvatar.avh.fake_baked.fake_maps`; the scan is the posed body subdivided once and displaced
(world axes: ``R(Rh) d``) with that texture; ``gt/frames/<f>.npz`` holds ``surface`` (posed body texel
+ displacement) and ``mask``; ``gt/info.json`` lists ``heldout_frames``. The baked dataset stores
the same maps with κ = w = 1 on covered texels (a perfect bake).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from uvatar.avh.data import body_to_world
from uvatar.avh.fake_baked import fake_maps
from uvatar.io_utils import write_json, write_npz


def make_toy_capture(root: str | Path, body, num_frames: int = 8, heldout: int = 2, resolution: int = 32,
                     image_size: int = 64, seed: int = 0) -> tuple[Path, Path]:
    """Write ROOT/capture (with gt/) and ROOT/baked; returns (capture_dir, baked_dir).

    The last ``heldout`` frames are held out (not in the baked selection).
    """
    from uvatar.capture import BodyFit, TexturedMesh, write_cameras, write_capture_info, write_fit, write_mesh
    from uvatar.geometry import rasterize_uv, sample_texture, subdivide, texel_positions
    from uvatar.render import orbit_cameras

    root = Path(root)
    cap, baked = root / "capture", root / "baked"
    rng = np.random.default_rng(seed)
    t = body.template
    J = body.num_joints
    cond = list(body.conditioning_joints)
    raster = rasterize_uv(t.uvs, t.uv_faces, resolution)
    _, faces1, uvs1, uv_faces1, origin = subdivide(t.vertices, t.faces, t.uvs, t.uv_faces, 1, "midpoint")
    names = [f"{i:06d}" for i in range(num_frames)]
    for name in names:
        pose = np.zeros((J, 3), np.float32)
        pose[cond] = rng.uniform(-0.6, 0.6, (len(cond), 3))
        Rh = np.array([0.0, rng.uniform(-0.5, 0.5), 0.0], np.float32)
        Th = np.array([rng.normal(0, 0.05), 0.0, 0.0], np.float32)
        tex, disp = fake_maps(pose.reshape(-1), resolution, cond)
        disp_world = body_to_world(disp, Rh)
        with torch.no_grad():
            base = body.pose(torch.from_numpy(pose)[None], Rh=torch.from_numpy(Rh)[None],
                             Th=torch.from_numpy(Th)[None]).vertices[0].numpy()
        v1 = np.asarray(origin.vertex_matrix @ base, np.float32)
        v1 = v1 + np.asarray(sample_texture(disp_world, origin.vertex_uv), np.float32)
        write_mesh(cap / "scans" / f"{name}.obj", TexturedMesh(v1, faces1, uvs1.astype(np.float32), uv_faces1, tex))
        write_fit(cap / "fits" / f"{name}.json", BodyFit(poses=pose.reshape(-1), Rh=Rh, Th=Th,
                                                         shapes=np.zeros(0, np.float32)))
        surface = np.asarray(texel_positions(raster, t.faces, base), np.float32) + disp_world
        write_npz(cap / "gt" / "frames" / f"{name}.npz", pose=pose.reshape(-1), texture=tex, offset=disp_world,
                  surface=surface, mask=raster.mask)
        write_npz(baked / "frames" / f"{name}.npz", texture=tex, displacement=disp_world,
                  kappa=raster.mask.astype(np.float32), w=raster.mask.astype(np.float32), valid=raster.mask,
                  pose=pose.reshape(-1), Rh=Rh, Th=Th)
    train = names[: num_frames - heldout]
    write_capture_info(cap, names, fps=10.0, body_model=body.name)
    write_cameras(cap / "cameras", orbit_cameras((0, 0.8, 0), 3.5, 2, 5.0, fov_deg=35, width=image_size,
                                                 height=image_size))
    write_json(cap / "gt" / "info.json", {"heldout_frames": names[num_frames - heldout:], "broken_frames": [],
                                          "texels": resolution, "takes": {"all": [0, num_frames - heldout]}})
    write_json(baked / "dataset.json", {"texels": resolution, "body_model": {"name": body.name, "shapes": None},
                                        "selection": {"train": train[:-1], "val": train[-1:]}})
    return cap, baked
