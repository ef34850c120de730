"""``OUT/preview.png``: a contact sheet of scans (textured, and shaded to show the folds) and
camera images of a few frames spread over the capture."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["write_preview"]

def _facing_camera(Rh: np.ndarray, Th: np.ndarray, size: int, name: str, height: float = 0.85,
                   fov: float = 42.0):
    """A camera 2.6 m in front of the person (turned with the body), aimed at ``height``."""
    from scipy.spatial.transform import Rotation

    from uvatar.render.cameras import look_at_camera

    fwd = Rotation.from_rotvec(Rh).apply([0.35, 0.0, 1.0])
    target = np.array([Th[0], height, Th[2]])
    return look_at_camera(target + 2.6 * fwd / np.linalg.norm(fwd) + [0, 0.15, 0], target, (0, 1, 0), fov,
                          size, size, name)

def write_preview(root: str | Path, plan: dict, cfg, count: int = 6, size: int = 256) -> Path:
    """Render the preview sheet (rows of: textured scan, shaded scan, camera image)."""
    from uvatar.capture.meshio import read_mesh
    from uvatar.io_utils import read_image, write_image
    from uvatar.render.contact import contact_sheet
    from uvatar.render.mesh_renderer import render_mesh

    root = Path(root)
    names = plan["frames"]
    picks = np.linspace(0, len(names) - 1, min(count, len(names))).round().astype(int)
    if plan["broken"] and len(picks) >= 3:  # show one broken frame
        picks[1] = names.index(sorted(plan["broken"])[0])
    picks = np.unique(picks)
    tiles, labels = [], []
    for i in picks:
        name = names[i]
        path = root / "scans" / f"{name}.obj"
        if not path.is_file():
            continue
        mesh = read_mesh(path)
        cam = _facing_camera(plan["Rh"][i], plan["Th"][i], size, "preview")
        take = plan["take_names"][int(plan["take_of_frame"][i])]
        tag = " broken" if name in plan["broken"] else ""
        tiles.append(render_mesh(mesh.vertices, mesh.faces, cam, uvs=mesh.uvs, uv_faces=mesh.uv_faces,
                                 texture=mesh.texture).rgb)
        labels.append(f"{name} {take}{tag}")
        close = _facing_camera(plan["Rh"][i], plan["Th"][i], size, "closeup", height=1.1, fov=24.0)
        tiles.append(render_mesh(mesh.vertices, mesh.faces, close, shading=True).rgb)
        labels.append(f"{mesh.num_faces} faces, shaded")
        if plan["cameras"]:
            cam0 = plan["cameras"][i % len(plan["cameras"])]
            img = root / "images" / cam0.name / f"{name}.png"
            if img.is_file():
                im = read_image(img)
                rep = max(1, size // max(im.shape[:2]))
                im = np.repeat(np.repeat(im, rep, 0), rep, 1)  # small camera images: nearest upscale
                tiles.append(im[..., :3])
                labels.append(f"camera {cam0.name}")
    path = root / "preview.png"
    if tiles:
        write_image(path, contact_sheet(tiles, cols=6 if plan["cameras"] else 4, labels=labels))
    return path
