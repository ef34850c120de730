"""``uvatar demo``: run the whole AVH pipeline on a synthetic capture (see :mod:`uvatar.demo`)."""

from __future__ import annotations


def register(cli) -> None:
    p = cli.command(
        "demo",
        help="run synth → bake → select → train → export → animate → eval on a synthetic capture",
        description="Run the whole AVH pipeline on a synthetic studio capture made on the fly "
        "(nothing is downloaded) and write OUT/report.html and OUT/metrics.json. "
        "An interrupted demo resumes: a stage whose completion record (OUT/stages/<stage>.json) exists is skipped.",
    )
    p.add_argument("--out", default="demo_out", help="output folder")
    p.add_argument("--quick", action="store_true", help="smoke run (~3 min on 2 CPU cores)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the synthetic capture")
    p.add_argument("--epochs", type=int, default=None, help="override the training epochs")
    p.add_argument("--fits", choices=("studio", "fit"), default=None,
                   help="studio: the studio's own noisy fits; fit: the studio's fits are moved out and "
                        "`uvatar fit --from scans` makes them, the path a real capture takes (needs uvatar[fit]) "
                        "(default: the config's)")
    p.set_defaults(func=run)


def run(args) -> int:
    from dataclasses import replace
    from pathlib import Path

    from uvatar.demo import DEFAULT, QUICK, run_demo

    cfg = QUICK if args.quick else DEFAULT
    cfg = replace(cfg, seed=args.seed)
    if args.fits is not None:
        cfg = replace(cfg, fits=args.fits)
    if args.epochs is not None:
        if args.epochs < 1:
            from uvatar.errors import InputError

            raise InputError("--epochs", f"must be at least 1, got {args.epochs}")
        cfg = replace(cfg, epochs=args.epochs)
    metrics = run_demo(args.out, cfg)
    print(f"uvatar demo: report at {Path(args.out) / 'report.html'}, metrics at {Path(args.out) / 'metrics.json'}")
    for stage in metrics["stages"]:
        print(f"  {stage['name']:<8} {stage['status']:<28} {stage['seconds']:7.1f} s")
    failed = [s["name"] for s in metrics["stages"] if s["status"].startswith("failed")]
    return 1 if failed else 0
