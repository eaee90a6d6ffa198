"""``capevo experiment run``: a grid's cells as Ray tasks, resumable, with the files back on the driver
(issue 20 "Harness").

Each cell (:meth:`ExperimentConfig.cells`) is one Ray task, :func:`run_cell`. It runs in a
temporary directory on whatever node Ray picks (no shared filesystem is assumed): it writes
``cell.json``, appends one :meth:`IterationRecord.to_dict` line to ``metrics.jsonl`` per
iteration (fsynced as emitted) beside the method's own files (registry, MCAP traces,
checkpoints), and returns the whole directory as the bytes of a tar archive, a Ray object. The
driver unpacks it under ``RUN_DIR/cells/<name>.partial``, writes ``done.json`` into it
atomically, and renames the directory to ``cells/<name>`` (:meth:`ExperimentConfig.cell_names`).

By default ``ray.init(num_cpus=workers)`` starts a local Ray instance in this process (no
dashboard, quiet logs); ``address`` (``ray://HOST:10001`` or ``auto``) joins a running cluster
instead, whose nodes must have the same capevo installed. One Ray task asks for one CPU.

The code that runs: Ray puts the driver's working directory first on its workers' ``sys.path``, so
the workers import the capevo found there, whatever the driver imported. Every worker compares a
digest of the package it imported (:data:`CODE_SHA256`, read at import) with the driver's and
refuses to run a cell with other code (:func:`check_same_code`; the driver looks once before
submitting any cell), and each ``done.json`` names the commit and the digest that ran it. So run a
grid from the directory of the code it is meant to run (a worktree: ``cd`` into it), not with that
code on ``PYTHONPATH``.

Failures: Ray re-runs a task whose worker process died (``max_retries``); a cell whose method
raised is submitted again by the driver, up to ``retries`` more attempts; a cell that failed
every attempt gets ``failed.json`` (error, traceback, attempts) and the other cells go on.

Resuming: the same command on the same ``RUN_DIR`` skips every cell with ``done.json`` and runs
every other one (a ``.partial`` directory and a ``failed.json`` from an earlier run are removed
first: a failed cell is tried again). ``experiment.json`` must describe the same cells (the
iterations, budget and settings of each).

Inside a cell: a cell works in ``WORK_DIR/<name>`` on its worker's host (``--work-dir``; default
``<tmp>/capevo-work/<key of host and RUN_DIR>``), not in a temporary directory, so a cell whose
process died (a SIGKILLed worker or driver, a machine that went down) keeps its finished
iterations. The next attempt on that host continues it after its last complete record when the
method can (``resumes(cell)``: ours through evolve's resume, AM with PPO from its last
checkpoint; see :class:`capevo.baselines.base.Method`) and the code is the same (the SHA-256 of
the attempt that began it). A resumed cell is a continuation, not a replay: the interrupted
iteration is run again from its start, and its random streams differ from an uninterrupted run's.
Each attempt appends a line to the cell's ``resumes.jsonl`` (after which iteration it began, when,
on which host, with which code), and ``done.json`` lists ``resumed_after``. Every other case
starts the cell over in an emptied directory: a method that cannot resume, other code, other
settings, and any attempt after the method raised (an error is not an interruption). A finished
cell's work directory is removed once its archive is made; an interrupted attempt's partial
traces stay in the cell's files (the learner-step audit counts its learner traces apart,
:mod:`capevo.evolve.audit`).

Invariants:
1. A cell directory without ``.partial`` in its name has ``done.json`` or ``failed.json``;
   ``done.json`` is written last (after every other file of the cell is on disk) and
   atomically, and a cell with it is never run again.
2. ``metrics.jsonl`` of a done cell has exactly ``cell.iterations`` records, iterations
   1..n as the baselines number them (R₁ is iteration 1's evaluation); a method that emitted
   fewer or out of order fails the attempt.
3. ``done.json``'s ``env_steps_train`` and ``env_steps_eval`` are the sums over the records.
4. One cell's failure never stops or loses another cell's files.
5. No cell runs with other capevo code than the driver's (the package's files differ), and no
   cell continues iterations that other code began.
6. A resumed cell's kept records are byte for byte those the interrupted attempt wrote.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import logging
import os
import platform
import shutil
import socket
import subprocess
import sys
import tarfile
import tempfile
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from capevo.baselines.base import CellSpec, IterationRecord
from capevo.errors import Conflict, Invalid, Unavailable
from capevo.evolve.metrics import append_durably, write_atomically
from capevo.experiment.config import ExperimentConfig
from capevo.experiment.progress import GridProgress, RecordingGridProgress
from capevo.experiment.run_files import (
    CELL_JSON,
    CELLS,
    DONE,
    EXPERIMENT_JSON,
    FAILED,
    METRICS,
    PROVENANCE_JSON,
    RESUMES,
)

log = logging.getLogger(__name__)

PARTIAL = ".partial"
PACKAGES = ("capevo", "robosuite", "mujoco", "torch", "stable-baselines3", "ray", "numpy", "scipy", "gymnasium")
WORKER_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}
"""Every cell uses one core: Ray gives each task one CPU, so its math libraries get one thread."""


def _dumps(obj: Any) -> bytes:
    return (json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False) + "\n").encode()


# --- one cell (runs in a Ray worker) -----------------------------------------------------------


def run_cell(
    cell_dict: Mapping[str, Any], name: str, driver_code: str | None = None, work_dir: str | None = None
) -> dict[str, Any]:
    """Run one cell and return its files (the Ray task's body).

    ``driver_code`` is the driver's :data:`CODE_SHA256`: a worker that imported other code
    refuses the cell (:func:`check_same_code`). ``work_dir`` is where the cell works
    (``work_dir/<name>``, kept across attempts, resumed where it can be; see the module
    docstring); None works in a temporary directory and resumes nothing.

    Returns:
        ``{"tar": bytes of the cell directory, "wall_s", "env_steps_train", "env_steps_eval",
        "iterations", "resumed_after", "capevo_commit", "learner_steps_traced"}`` (the commit of
        the code that ran the cell, on the host that ran it; for a method that ran an evolve loop,
        each iteration's recorded learner steps beside those in its learner's traces, which stay
        on that host). ``wall_s`` of a resumed cell is this attempt's plus the kept iterations'.

    Raises:
        Invalid: the method's records are not iterations 0..n-1.
        Conflict: the worker runs other code than the driver.
        Exception: whatever the method raised (the driver retries, then records it).
    """
    check_same_code(driver_code)
    # robosuite sets its logger's level on import: import it first, then quiet it
    import robosuite  # noqa: F401

    logging.getLogger("robosuite_logs").setLevel(logging.ERROR)
    cell = CellSpec.from_dict(cell_dict)
    with contextlib.ExitStack() as stack:
        if work_dir is None:
            base = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix=f"capevo-cell-{name}-")))
        else:
            base = Path(work_dir)
            try:
                base.mkdir(parents=True, exist_ok=True)
            except OSError:  # a cluster node without the driver's path: this host's own
                base = Path(tempfile.gettempdir()) / "capevo-work" / base.name
                base.mkdir(parents=True, exist_ok=True)
        d = base / name
        try:
            result = _run_cell_in(cell, d, name)
        except Exception:
            # an error, not an interruption: the next attempt starts over
            shutil.rmtree(d, ignore_errors=True)
            raise
        if work_dir is not None:
            shutil.rmtree(d, ignore_errors=True)
        return result


def _run_cell_in(cell: CellSpec, d: Path, name: str) -> dict[str, Any]:
    from capevo.evolve.audit import learner_step_checks
    from capevo.experiment.methods import knowledge_of, make_method

    t0 = time.perf_counter()
    method = make_method(cell.method)
    records = _kept_records(d, cell, method)
    if not records:
        shutil.rmtree(d, ignore_errors=True)
        d.mkdir(parents=True)
        knowledge = knowledge_of(cell.method, cell.options)
        write_atomically(d / CELL_JSON, _dumps({"cell": cell.to_dict(), "knowledge": knowledge}))
    else:
        # drop a torn last line: the kept records, exactly as they were written (invariant 6)
        write_atomically(d / METRICS, b"".join(_dumps(r.to_dict()) for r in records))
    kept = len(records)
    append_durably(
        d / RESUMES,
        _dumps(
            {
                "after_iteration": kept,
                "started_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                "host": socket.gethostname(),
                "capevo_sha256": CODE_SHA256,
                "capevo_commit": CODE_COMMIT,
            }
        ),
    )

    def emit(record: IterationRecord) -> None:
        if record.iteration != len(records) + 1:
            raise Invalid(
                f"{cell.method} emitted iteration {record.iteration} after {len(records)} records "
                "(iterations are numbered 1..n)",
                details={"field": "iteration"},
            )
        append_durably(d / METRICS, _dumps(record.to_dict()))
        records.append(record)

    # the method's own files (registry/, traces/, checkpoints) go beside cell.json and metrics.jsonl
    if kept == 0:
        method.run(cell, d, emit=emit)
    elif kept < cell.iterations:
        method.run(cell, d, emit=emit, after=kept)  # type: ignore[call-arg]
    if len(records) != cell.iterations:
        raise Invalid(
            f"{cell.method} emitted {len(records)} of {cell.iterations} iterations", details={"field": "iterations"}
        )
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        tar.add(d, arcname=name)
    return {
        "tar": buf.getvalue(),
        "wall_s": time.perf_counter() - t0 + sum(r.wall_s for r in records[:kept]),
        "env_steps_train": sum(r.env_steps_train for r in records),
        "env_steps_eval": sum(r.env_steps_eval for r in records),
        "iterations": len(records),
        "resumed_after": _resumed_after(d),
        "capevo_commit": CODE_COMMIT,
        "capevo_sha256": CODE_SHA256,
        # the traces do not travel with the cell (they are large): check them here, on their host
        "learner_steps_traced": [c.to_dict() for c in learner_step_checks(d / "evolve")],
    }


def _kept_records(d: Path, cell: CellSpec, method: Any) -> list[IterationRecord]:
    """The records an interrupted attempt left in ``d`` that this attempt may continue after; []
    to start over (see the module docstring for when)."""
    resumes = getattr(method, "resumes", None)
    if not d.is_dir() or not callable(resumes) or not resumes(cell):
        return []
    try:
        began = json.loads((d / CELL_JSON).read_text(encoding="utf-8"))
        attempts = [json.loads(line) for line in (d / RESUMES).read_text(encoding="utf-8").splitlines()]
        lines = (d / METRICS).read_bytes().splitlines(keepends=True) if (d / METRICS).exists() else []
    except (OSError, ValueError):
        return []
    if began.get("cell") != cell.to_dict() or not attempts or attempts[0].get("capevo_sha256") != CODE_SHA256:
        return []
    records: list[IterationRecord] = []
    for line in lines:
        try:
            record = IterationRecord.from_dict(json.loads(line))
        except (ValueError, TypeError, KeyError, Invalid):
            break  # a torn last line: the process died while writing it
        if record.iteration != len(records) + 1 or _dumps(record.to_dict()) != line:
            break
        records.append(record)
    return records if len(records) <= cell.iterations else []


def _resumed_after(d: Path) -> list[int]:
    lines = (d / RESUMES).read_text(encoding="utf-8").splitlines()
    return [int(json.loads(line)["after_iteration"]) for line in lines[1:]]


# --- the driver --------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class RunSummary:
    """What :func:`run_experiment` did."""

    run_dir: Path
    done: tuple[str, ...]
    """Cells finished by this run."""
    skipped: tuple[str, ...]
    """Cells already done before it (never redone)."""
    failed: tuple[str, ...]
    wall_s: float


def cell_state(cell_dir: Path) -> str:
    """``done``, ``failed`` or ``todo`` for a cell directory."""
    if (cell_dir / DONE).is_file():
        return "done"
    if (cell_dir / FAILED).is_file():
        return "failed"
    return "todo"


def _check_same_grid(run_dir: Path, config: ExperimentConfig) -> None:
    path = run_dir / EXPERIMENT_JSON
    if not path.is_file():
        return
    try:
        old = ExperimentConfig.from_dict(json.loads(path.read_text(encoding="utf-8")))
    except (ValueError, Invalid) as exc:
        raise Invalid(f"{path} is not an experiment config: {exc}", details={"field": "run_dir"}) from None
    mine = {n: c.to_dict() for n, c in config.cell_names().items()}
    theirs = {n: c.to_dict() for n, c in old.cell_names().items()}
    changed = sorted(k for k in mine.keys() & theirs.keys() if mine[k] != theirs[k])
    if changed:
        raise Invalid(
            f"{run_dir} holds a run whose cells {', '.join(changed[:3])} have other settings; "
            "use another run directory",
            details={"field": "run_dir"},
        )


def _git_commit() -> str | None:
    here = Path(__file__).resolve().parents[2]
    try:
        out = subprocess.run(
            ["git", "-C", str(here), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10, check=True
        )
    except (OSError, subprocess.SubprocessError):
        return None
    dirty = subprocess.run(
        ["git", "-C", str(here), "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True
    )
    return out.stdout.strip() + ("-dirty" if dirty.stdout.strip() else "")


CODE_DIR = str(Path(__file__).resolve().parents[2])
"""Where this process imported capevo from."""
CODE_COMMIT = _git_commit()
"""The commit of that checkout when this process imported it (``-dirty`` with uncommitted changes;
None outside a git checkout): provenance. Read once, at import: the modules imported do not change
when the checkout does, so reading it at the end of a cell could name code that never ran."""


def _package_sha256() -> str:
    """SHA-256 over the capevo package's files (relative paths and bytes; caches left out)."""
    package = Path(__file__).resolve().parents[1]
    digest = hashlib.sha256()
    for path in sorted(package.rglob("*")):
        if path.is_file() and "__pycache__" not in path.parts and path.suffix != ".pyc":
            digest.update(path.relative_to(package).as_posix().encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()


CODE_SHA256 = _package_sha256()
"""What this process runs, read at import: equal digests are the same code whatever the commits
(a commit of results only changes the commit, not the code)."""


def check_same_code(driver_code: str | None) -> None:
    """Refuse to run a cell (in a Ray worker) with other code than the driver's.

    Why: Ray puts the driver's working directory first on its workers' ``sys.path``, so a driver
    started from one checkout with its code on ``PYTHONPATH`` (a worktree) has its cells import
    the checkout in the working directory, silently (measured with Ray 2.60).

    Raises:
        Conflict: ``driver_code`` is given and is not :data:`CODE_SHA256`.
    """
    _refuse_other_code(worker=_code_of_worker(), driver=driver_code)


def _refuse_other_code(*, worker: tuple[str, str | None, str], driver: str | None) -> None:
    code, commit, where = worker
    if driver is not None and driver != code:
        raise Conflict(
            f"a Ray worker imported other capevo code than the driver's, from {where} (commit {commit}): "
            "Ray puts the driver's working directory first on its workers' path, so start capevo "
            "experiment run from the directory of the code you mean to run",
            details={"worker_sha256": code, "driver_sha256": driver, "worker_commit": commit, "worker_dir": where},
        )


def _code_of_worker() -> tuple[str, str | None, str]:
    return CODE_SHA256, CODE_COMMIT, CODE_DIR


def _earlier_runs(run_dir: Path) -> list[dict[str, Any]]:
    """The provenance of the runs before this one in ``run_dir``, latest first (a resumed run
    keeps them: its cells may have been run by them)."""
    try:
        old = json.loads((run_dir / PROVENANCE_JSON).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return []
    if not isinstance(old, dict):
        return []
    before = old.pop("earlier_runs", None)
    return [old, *(r for r in before or () if isinstance(r, dict))]


def _versions() -> dict[str, str | None]:
    from importlib.metadata import PackageNotFoundError, version

    out: dict[str, str | None] = {}
    for p in PACKAGES:
        try:
            out[p] = version(p)
        except PackageNotFoundError:
            out[p] = None
    return out


def _load() -> list[float] | None:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def _extract(run_dir: Path, name: str, result: Mapping[str, Any], attempts: int) -> None:
    cells = run_dir / CELLS
    partial = cells / (name + PARTIAL)
    shutil.rmtree(partial, ignore_errors=True)
    with tempfile.TemporaryDirectory(prefix=".unpack-", dir=cells) as tmp:
        with tarfile.open(fileobj=io.BytesIO(result["tar"]), mode="r") as tar:
            tar.extractall(tmp, filter="data")
        os.replace(Path(tmp) / name, partial)
    done = {
        "wall_s": result["wall_s"],
        "env_steps_train": result["env_steps_train"],
        "env_steps_eval": result["env_steps_eval"],
        "attempts": attempts,
        # a resumed run mixes cells of several runs: each says which code ran it
        "capevo_commit": result.get("capevo_commit"),
        "capevo_sha256": result.get("capevo_sha256"),
    }
    if result.get("resumed_after"):
        done["resumed_after"] = result["resumed_after"]
    if result.get("learner_steps_traced"):
        done["learner_steps_traced"] = result["learner_steps_traced"]
    write_atomically(partial / DONE, _dumps(done))
    final = cells / name
    shutil.rmtree(final, ignore_errors=True)
    os.replace(partial, final)


def _record_failure(run_dir: Path, name: str, cell: CellSpec, exc: BaseException, attempts: int) -> None:
    from capevo.experiment.methods import knowledge_of

    d = run_dir / CELLS / name
    shutil.rmtree(d, ignore_errors=True)
    d.mkdir(parents=True)
    try:
        knowledge = knowledge_of(cell.method, cell.options)
    except Invalid:
        knowledge = ""
    write_atomically(d / CELL_JSON, _dumps({"cell": cell.to_dict(), "knowledge": knowledge}))
    cause = getattr(exc, "cause", None) or exc
    tb = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
    write_atomically(
        d / FAILED, _dumps({"error": f"{type(cause).__name__}: {cause}"[:2000], "traceback": tb, "attempts": attempts})
    )


def _summary_of(result: Mapping[str, Any]) -> str:
    return (
        f"{result['iterations']} iterations, {result['env_steps_train']} training + {result['env_steps_eval']} "
        f"evaluation env steps, {result['wall_s']:.0f} s"
    )


def start_ray(*, workers: int, address: str | None) -> bool:
    """Start a local Ray instance with ``workers`` CPUs, or join ``address``; True when this call
    started or joined it (and :func:`stop_ray` should end it)."""
    import ray

    if ray.is_initialized():
        return False
    kwargs: dict[str, Any] = {
        "include_dashboard": False,
        "log_to_driver": False,
        "logging_level": logging.WARNING,
        "configure_logging": True,
        "runtime_env": {"env_vars": dict(WORKER_ENV)},
    }
    if address:
        try:
            _join_cluster(ray, address, kwargs)
        except ConnectionError as e:
            # Ray >= 2.59 starts clusters with token auth on; a client without the token times out
            # with a generic message, so name the likely causes here.
            raise Unavailable(
                f"could not join the Ray cluster at {address}: {e}. Check that the head is running and "
                "its client port is reachable; a cluster started by Ray >= 2.59 needs RAY_AUTH_MODE=token "
                "and its token (RAY_AUTH_TOKEN, or the head's ~/.ray/auth_token) here too (docs/multi-host.md)",
                details={"field": "address", "address": address},
            ) from e
    else:
        ray.init(num_cpus=workers, **kwargs)
    return True


JOIN_ATTEMPTS = 3


def _join_cluster(ray: Any, address: str, kwargs: Mapping[str, Any]) -> None:
    """``ray.init`` on a Ray Client address, retrying when the head answered but failed to start
    this client's session.

    Why: on a freshly started head, Ray 2.60's client proxy loses the first client's dedicated
    server process in about one join of three (``Starting Ray client server failed``, or
    ``psutil.ZombieProcess`` while it waits for that process); measured with the cluster test's
    setup, the next join always succeeded. Ray reports this as ``ConnectionAbortedError``
    ("Initialization failure from server"), which is retried; other ``ConnectionError`` s (head
    unreachable, a missing token) are not, because retrying cannot fix them.
    """
    for attempt in range(1, JOIN_ATTEMPTS + 1):
        try:
            ray.init(address=address, **kwargs)
            return
        except ConnectionAbortedError as e:
            if attempt == JOIN_ATTEMPTS:
                raise
            log.warning("joining %s failed (attempt %d of %d), retrying: %s", address, attempt, JOIN_ATTEMPTS, e)
            with contextlib.suppress(Exception):
                ray.shutdown()  # drop the half-made client context before the next ray.init
            time.sleep(1.0)


def stop_ray() -> None:
    import ray

    ray.shutdown()


def default_work_dir(run_dir: Path) -> Path:
    """``<tmp>/capevo-work/<key>``: the cells' work directories of the run in ``run_dir`` started
    on this host (the key is a digest of the host name and the run directory's absolute path, so
    two runs never share one and the same run finds its own again)."""
    key = hashlib.sha256(f"{socket.gethostname()}\0{Path(run_dir).resolve()}".encode()).hexdigest()[:16]
    return Path(tempfile.gettempdir()) / "capevo-work" / key


def run_experiment(
    config: ExperimentConfig,
    run_dir: Path,
    *,
    workers: int = 2,
    address: str | None = None,
    retries: int = 1,
    max_retries: int = 2,
    progress: GridProgress | None = None,
    command: Sequence[str] | None = None,
    only: Callable[[CellSpec], bool] | None = None,
    work_dir: Path | None = None,
) -> RunSummary:
    """Run (or resume) ``config``'s grid into ``run_dir``.

    Args:
        config: The grid.
        run_dir: The run directory (created; see :mod:`capevo.experiment` for its layout).
        workers: CPUs of the local Ray instance (ignored with ``address``).
        address: A Ray cluster to join (``ray://HOST:10001`` or ``auto``); None starts one here.
        retries: Further attempts of a cell whose method raised.
        max_retries: Ray's re-runs of a task whose worker process died.
        progress: Display sink (default: a recording one).
        command: Recorded in ``provenance.json``.
        only: Run only the cells it accepts (the others are left as they are).
        work_dir: Where cells work on their worker's host, kept until a cell is done so that an
            interrupted one can resume (default :func:`default_work_dir`).

    Returns:
        What ran, what was skipped, what failed.

    Raises:
        Invalid: ``run_dir`` holds a run of other cells' settings, or bad arguments.
    """
    import ray

    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise Invalid(f"workers must be a positive integer, got {workers!r}", details={"field": "workers"})
    if isinstance(retries, bool) or not isinstance(retries, int) or retries < 0:
        raise Invalid(f"retries must be a non-negative integer, got {retries!r}", details={"field": "retries"})
    t0 = time.perf_counter()
    sink: GridProgress = progress if progress is not None else RecordingGridProgress()
    run_dir = Path(run_dir)
    cells_dir = run_dir / CELLS
    _check_same_grid(run_dir, config)
    cells_dir.mkdir(parents=True, exist_ok=True)
    write_atomically(run_dir / EXPERIMENT_JSON, _dumps(config.to_dict()))
    for leftover in cells_dir.iterdir():
        # an interrupted run's unpacking: never a finished cell
        if leftover.name.endswith(PARTIAL) or leftover.name.startswith(".unpack-"):
            shutil.rmtree(leftover, ignore_errors=True)
    provenance: dict[str, Any] = {
        "capevo_commit": CODE_COMMIT,
        "capevo_sha256": CODE_SHA256,
        "packages": _versions(),
        "machine": {
            "cores": os.cpu_count(),
            "platform": platform.platform(),
            "python": platform.python_version(),
            "load_at_start": _load(),
        },
        "ray": {"address": address or "local", "workers": workers if not address else None},
        "started_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "command": list(command) if command is not None else [sys.executable, *sys.argv],
    }
    earlier = _earlier_runs(run_dir)
    if earlier:
        provenance["earlier_runs"] = earlier
    work = str(Path(work_dir) if work_dir is not None else default_work_dir(run_dir))
    provenance["work_dir"] = work
    grid = list(config.cell_names().items())
    states = {name: cell_state(cells_dir / name) for name, _ in grid}
    skipped = tuple(n for n, _ in grid if states[n] == "done")
    todo = [(n, c) for n, c in grid if states[n] != "done" and (only is None or only(c))]
    done: list[str] = []
    failed: list[str] = []
    sink.started(total=len(grid), done=len(skipped), failed=0)
    owns_ray = False
    try:
        if todo:
            owns_ray = start_ray(workers=workers, address=address)
            # one cheap look before any cell: the common case (a local instance) fails here, at once
            _refuse_other_code(worker=ray.get(ray.remote(num_cpus=0)(_code_of_worker).remote()), driver=CODE_SHA256)
            task = ray.remote(num_cpus=1, max_retries=max_retries)(run_cell)
            for name, _ in todo:
                shutil.rmtree(cells_dir / name, ignore_errors=True)  # an unfinished cell starts over
            slots = workers if not address else max(1, int(ray.cluster_resources().get("CPU", 1)))
            attempts = dict.fromkeys((n for n, _ in todo), 1)
            by_ref = {task.remote(c.to_dict(), n, CODE_SHA256, work): (n, c) for n, c in todo}
            while by_ref:
                sink.update(running=min(slots, len(by_ref)))
                ready, _ = ray.wait(list(by_ref), num_returns=1, timeout=1.0)
                for ref in ready:
                    name, cell = by_ref.pop(ref)
                    try:
                        result = ray.get(ref)
                    except Exception as exc:  # the cell's own error, or its worker died max_retries times
                        if attempts[name] <= retries:
                            attempts[name] += 1
                            sink.message(f"retrying {name} (attempt {attempts[name]}): {_short(exc)}")
                            by_ref[task.remote(cell.to_dict(), name, CODE_SHA256, work)] = (name, cell)
                            continue
                        _record_failure(run_dir, name, cell, exc, attempts[name])
                        failed.append(name)
                        sink.cell_finished(name, ok=False, summary=_short(exc))
                        continue
                    _extract(run_dir, name, result, attempts[name])
                    done.append(name)
                    sink.cell_finished(name, ok=True, summary=_summary_of(result))
    finally:
        if owns_ray:
            with contextlib.suppress(Exception):
                stop_ray()
        wall = time.perf_counter() - t0
        provenance["machine"]["load_at_end"] = _load()
        provenance["finished_at"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
        provenance["wall_s"] = round(wall, 3)
        provenance["cells"] = {"total": len(grid), "run": len(done), "skipped": len(skipped), "failed": len(failed)}
        write_atomically(run_dir / PROVENANCE_JSON, _dumps(provenance))
        sink.close()
    return RunSummary(
        run_dir=run_dir, done=tuple(done), skipped=skipped, failed=tuple(failed), wall_s=time.perf_counter() - t0
    )


def _short(exc: BaseException) -> str:
    cause = getattr(exc, "cause", None) or exc
    text = f"{type(cause).__name__}: {cause}"
    return text.splitlines()[0][:300] if text else type(cause).__name__


__all__ = [
    "PARTIAL",
    "RunSummary",
    "cell_state",
    "default_work_dir",
    "run_cell",
    "run_experiment",
    "start_ray",
    "stop_ray",
]
