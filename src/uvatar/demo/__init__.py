"""``uvatar demo``: the whole AVH pipeline on a synthetic studio capture, with nothing to download.

:mod:`uvatar.demo.pipeline` runs the stages (library calls; the demo resumes after the last finished
stage its stage record ``OUT/stage.json`` counts, :mod:`uvatar.stage_record`);
:mod:`uvatar.demo.report` writes ``OUT/report.html``.
"""

from uvatar.demo.pipeline import (
           DEFAULT,
           FINE,
           QUICK,
           DemoConfig,
           StageResult,
           demo_stages,
           quick_config,
           run_demo,
)
from uvatar.demo.report import write_demo_report

__all__ = ["DEFAULT", "FINE", "QUICK", "DemoConfig", "StageResult", "demo_stages", "quick_config", "run_demo",
           "write_demo_report"]
