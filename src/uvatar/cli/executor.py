"""Executor flags shared by the per-frame commands (``bake``, ``synth``, ``fit``): ``--executor``,
``--address``, ``--cpus-per-task``, ``--max-retries``; defaults from :class:`uvatar.parallel.ExecutorConfig`."""

from __future__ import annotations


def add_executor_flags(p) -> None:
    from uvatar.parallel import EXECUTORS, ExecutorConfig

    d = ExecutorConfig()
    p.add_argument("--executor", choices=EXECUTORS, default=d.kind,
                   help="where frames run: local (process pool of --workers) or ray (a Ray cluster; "
                        "pip install 'uvatar[cluster]')")
    p.add_argument("--address", default=d.address,
                   help="ray: cluster address (auto, HOST:6379, ray://HOST:10001); default: a private local Ray")
    p.add_argument("--cpus-per-task", type=float, default=d.cpus_per_task, help="ray: CPUs each frame task declares")
    p.add_argument("--max-retries", type=int, default=d.max_retries,
                   help="ray: re-runs of a task whose worker process was lost")


def executor_from_args(args, workers: int | None):
    """ExecutorConfig from the flags; ``workers``: the command's --workers (ray: most tasks in flight,
    None = unlimited)."""
    from uvatar.errors import options_as_input_error
    from uvatar.parallel import ExecutorConfig

    if args.executor == "ray":
        workers = 0 if workers is None or workers <= 1 else workers
    with options_as_input_error("--executor options"):
        return ExecutorConfig(kind=args.executor, workers=1 if workers is None else workers, address=args.address,
                              cpus_per_task=args.cpus_per_task, max_retries=args.max_retries)
