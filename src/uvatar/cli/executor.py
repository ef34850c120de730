"""Executor flags shared by the per-frame commands (``bake``, ``synth``): ``--executor``, ``--address``,
``--cpus-per-task``, ``--max-retries``, generated from :class:`uvatar.parallel.ExecutorConfig`."""

from __future__ import annotations

from uvatar.cli.flags import ConfigFlags


def executor_flags() -> ConfigFlags:
    from uvatar.parallel import EXECUTORS, ExecutorConfig

    return ConfigFlags(
        ExecutorConfig, fields=("kind", "address", "cpus_per_task", "max_retries"), rename={"kind": "executor"},
        choices={"kind": EXECUTORS},
        help={"kind": "where frames run: local (process pool of --workers) or ray (a Ray cluster; "
                      "pip install 'uvatar[cluster]')",
              "address": "ray: cluster address (auto, HOST:6379, ray://HOST:10001); none: a private local Ray",
              "cpus_per_task": "ray: CPUs each frame task declares",
              "max_retries": "ray: re-runs of a task whose worker process was lost"})


def add_executor_flags(p) -> None:
    executor_flags().add_to(p)


def executor_from_args(args, workers: int | None):
    """ExecutorConfig from the flags; ``workers``: the command's --workers (ray: most tasks in flight,
    None = unlimited)."""
    from uvatar.errors import options_as_input_error

    if args.kind == "ray":
        workers = 0 if workers is None or workers <= 1 else workers
    with options_as_input_error("--executor options"):
        return executor_flags().config(args, workers=1 if workers is None else workers)
