"""``uvatar body info``: what a body model holds (counts, conditioning joints, shape names)."""

from __future__ import annotations

from uvatar.cli.flags import ConfigFlags


def _flags() -> ConfigFlags:
    """``load_body_model``'s parameters: --model, --model-dir, --uv-obj."""
    from uvatar.body.registry import BODY_MODELS, load_body_model

    return ConfigFlags(load_body_model, fields=("name", "model_dir", "uv_obj"), rename={"name": "model"},
                       choices={"name": BODY_MODELS}, help={
                           "name": "body model", "model_dir": "SMPL/SMPL-X model folder (none: $UVATAR_SMPL_DIR)",
                           "uv_obj": "OBJ with the SMPL/SMPL-X UV layout"})


def register(cli) -> None:
    p = cli.command("body info", help="print a body model's vertex/face/UV/joint counts and joint subsets")
    _flags().add_to(p)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_info)

    r = cli.command("body render", help="render the body model's rest pose (front and side) to a PNG")
    r.add_argument("out", help="output image (.png)")
    _flags().add_to(r)
    r.add_argument("--size", type=int, default=384, help="height of each view in pixels")
    r.add_argument("--parts", action="store_true", help="colour hands, feet, head and face")
    r.set_defaults(func=_render)


def body_summary(body) -> dict:
    """A JSON-ready summary of a body model."""
    t = body.template
    return {
        "name": body.name,
        "vertices": t.num_vertices,
        "faces": t.num_faces,
        "uvs": int(t.uvs.shape[0]),
        "joints": body.num_joints,
        "conditioning_joints": [t.joint_names[j] for j in body.conditioning_joints],
        "semantic_joints": {k: t.joint_names[v] for k, v in body.semantic_joints.items()},
        "shape_names": list(body.shape_names),
        "default_shape": [round(float(x), 6) for x in body.default_shape().tolist()],
        "height_m": round(float(t.vertices[:, 1].max() - t.vertices[:, 1].min()), 4),
    }


def _info(args) -> int:
    import json

    from uvatar.body import load_body_model

    body = load_body_model(**_flags().values(args))
    s = body_summary(body)
    if args.json:
        print(json.dumps(s))
        return 0
    print(f"body model  {s['name']}")
    print(f"vertices    {s['vertices']}")
    print(f"triangles   {s['faces']}")
    print(f"uvs         {s['uvs']}")
    print(f"joints      {s['joints']}")
    print(f"height      {s['height_m']} m (rest pose)")
    print(f"conditioning joints ({len(s['conditioning_joints'])}): {', '.join(s['conditioning_joints'])}")
    print(f"shape ({len(s['shape_names'])}): " + ", ".join(
        f"{n}={v:g}" for n, v in zip(s["shape_names"], s["default_shape"], strict=True)))
    return 0


_PART_COLORS = {"head": (0.3, 0.45, 0.9), "hands": (0.3, 0.8, 0.35), "feet": (0.9, 0.8, 0.2)}


def _render(args) -> int:
    import numpy as np

    from uvatar.body import load_body_model, part_vertex_weights
    from uvatar.errors import InputError
    from uvatar.io_utils import write_image
    from uvatar.render.cameras import look_at_camera
    from uvatar.render.contact import contact_sheet
    from uvatar.render.mesh_renderer import render_mesh

    if args.size < 16:
        raise InputError("--size", f"must be at least 16, got {args.size}")
    body = load_body_model(**_flags().values(args))
    t = body.template
    colors = None
    if args.parts:
        colors = np.full((t.num_vertices, 3), 0.75, np.float32)
        for name, w in part_vertex_weights(body).items():
            if name in _PART_COLORS:
                colors[w > 0.5] = _PART_COLORS[name]
    lo, hi = t.vertices.min(0), t.vertices.max(0)
    center = (lo + hi) / 2
    dist = 1.4 * float(hi[1] - lo[1]) / (2 * np.tan(np.radians(20)))
    views = []
    for name, direction in (("front", (0.0, 0.0, 1.0)), ("left side", (1.0, 0.0, 0.0))):
        cam = look_at_camera(center + dist * np.asarray(direction), center, fov_deg=40.0,
                             width=int(args.size * 0.75), height=args.size, name=name)
        views.append(render_mesh(t.vertices, t.faces, cam, vertex_colors=colors, shading=True).rgb)
    write_image(args.out, contact_sheet(views, cols=2, labels=["front (+Z)", "left side (+X)"]))
    print(f"wrote {args.out}")
    return 0
