"""The experiment harness (issue 20, paper §4): grids of tasks × methods × seeds run as Ray tasks,
``capevo experiment run|report|verify``.

- :func:`load_config` / :class:`ExperimentConfig`: grids from YAML, the packaged hypothesis configs
  (``h1``, ``h2``, ``h3``, ``ablation-t3``) and the presets ``paper``, ``cpu-small``, ``smoke``.
- :func:`make_method` / :func:`method_names`: ours (``ours-code``, ``ours-neural``, ``ours``), the
  static lower bound ``s-ecm``, the H3 ``explorer``, and the baselines of :mod:`capevo.baselines`.
- :func:`run_experiment`: the cells as Ray tasks, resumable, files back on the driver.
- :func:`write_report` / :func:`verify_run`: the report and the check that recomputes it.

A run directory::

    RUN_DIR/
      experiment.json        the grid (ExperimentConfig.to_dict(), with its YAML text)
      provenance.json        commit, package versions, machine, load, times, wall time, command;
                             a resumed run keeps the earlier runs' under earlier_runs
      cells/<name>/          ExperimentConfig.cell_names(): <task>-<method>-s<seed>[-gov-off][-k=v]
         cell.json           {"cell": CellSpec.to_dict(), "knowledge": what the method starts from}
         metrics.jsonl       one IterationRecord.to_dict() per iteration 1..n, fsynced as emitted
         done.json           written last, atomically: wall_s, env_steps_train, env_steps_eval, attempts,
                             capevo_commit (the code that ran the cell)
         failed.json         instead, when every attempt failed: error, traceback, attempts
         registry/ traces/ evolve/ checkpoints/ ...   the method's own files
      report/report.md, report/*.png, report/numbers.json
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from capevo._lazy import lazy_getattr

if TYPE_CHECKING:
    from capevo.experiment.config import ExperimentConfig, MethodEntry, load_config, make_experiment, preset_names
    from capevo.experiment.methods import make_method, method_names
    from capevo.experiment.progress import GridProgress, RecordingGridProgress, RichGridProgress
    from capevo.experiment.report import write_report
    from capevo.experiment.runner import RunSummary, run_experiment
    from capevo.experiment.verify import verify_run

_HOMES = {
    "ExperimentConfig": "capevo.experiment.config",
    "MethodEntry": "capevo.experiment.config",
    "load_config": "capevo.experiment.config",
    "make_experiment": "capevo.experiment.config",
    "preset_names": "capevo.experiment.config",
    "make_method": "capevo.experiment.methods",
    "method_names": "capevo.experiment.methods",
    "GridProgress": "capevo.experiment.progress",
    "RecordingGridProgress": "capevo.experiment.progress",
    "RichGridProgress": "capevo.experiment.progress",
    "write_report": "capevo.experiment.report",
    "RunSummary": "capevo.experiment.runner",
    "run_experiment": "capevo.experiment.runner",
    "verify_run": "capevo.experiment.verify",
}
__all__ = [
    "ExperimentConfig",
    "GridProgress",
    "MethodEntry",
    "RecordingGridProgress",
    "RichGridProgress",
    "RunSummary",
    "load_config",
    "make_experiment",
    "make_method",
    "method_names",
    "preset_names",
    "run_experiment",
    "verify_run",
    "write_report",
]
__getattr__ = lazy_getattr(__name__, _HOMES)
