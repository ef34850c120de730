"""``uvatar demo``: run the whole AVH pipeline on a synthetic capture (see :mod:`uvatar.demo`).

``--seed``, ``--epochs``, ``--fits`` and ``--orientation`` are generated from :class:`uvatar.demo.DemoConfig`; their
defaults are those of ``DEFAULT`` or, with ``--quick``, ``QUICK`` (``--fine``: ``FINE``, 256² maps).
"""

from __future__ import annotations

from uvatar.cli.flags import ConfigFlags


def _flags() -> ConfigFlags:
    from uvatar.avh.model import ORIENTATIONS
    from uvatar.demo.pipeline import DEFAULT, FINE, FIT_SOURCES, FLAG_FIELDS, QUICK, DemoConfig

    return ConfigFlags(DemoConfig, fields=FLAG_FIELDS,
                       choices={"fits": FIT_SOURCES, "orientation": ORIENTATIONS},
                       presets={"default": DEFAULT, "quick": QUICK, "fine": FINE}, help={
                           "seed": "random seed of the synthetic capture", "epochs": "training epochs",
                           "progress": "progress bars (--no-progress: none)",
                           "orientation": "what the generators see of the pose: studio adds the body's orientation "
                                          "in the capture's world (the studio's lights are fixed in it); body is "
                                          "the paper's local pose only",
                           "fits": "studio: the studio's own noisy fits; fit: the studio's fits are moved out and "
                                   "`uvatar fit --from scans` makes them, the path a real capture takes "
                                   "(needs uvatar[fit])"})


def register(cli) -> None:
    p = cli.command(
        "demo",
        help="run synth → bake → select → train → export → animate → eval on a synthetic capture",
        description="Run the whole AVH pipeline on a synthetic studio capture made on the fly "
        "(nothing is downloaded) and write OUT/report.html and OUT/metrics.json. "
        "An interrupted demo resumes after its last finished stage (its stage record, OUT/stage.json); a rerun "
        "with other settings (--quick, --fine, --seed, --epochs, ...) is refused: use another --out.",
    )
    p.add_argument("--out", default="demo_out", help="output folder")
    size = p.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="smoke run (~3 min on 2 CPU cores); the quick preset")
    size.add_argument("--fine", action="store_true", help="256² maps instead of 128² (the plaid and the creases "
                                                          "survive; ~12 min on 2 CPU cores); the fine preset")
    _flags().add_to(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    from uvatar.demo import DEFAULT, FINE, QUICK, run_demo
    from uvatar.errors import options_as_input_error

    with options_as_input_error("uvatar demo options"):
        cfg = _flags().config(args, base=QUICK if args.quick else FINE if args.fine else DEFAULT)
    metrics = run_demo(args.out, cfg)
    print(f"uvatar demo: report at {Path(args.out) / 'report.html'}, metrics at {Path(args.out) / 'metrics.json'}")
    for stage in metrics["stages"]:
        print(f"  {stage['name']:<8} {stage['status']:<28} {stage['seconds']:7.1f} s")
    failed = [s["name"] for s in metrics["stages"] if s["status"].startswith("failed")]
    return 1 if failed else 0
