"""Fit jobs of the admin area: a supervisor and one worker process per running fit.

``tessera serve`` starts a :class:`JobRunner` in a process of its own
(:class:`RunnerProcess`): a supervisor that takes ``queued`` jobs from the
catalog (``fitter.collection.catalog``) and runs each in its own worker process, at most
``workers`` at a time (default one per core), so the web process never computes
a fit and never stalls behind one.
Each worker calls :func:`fitter.fitting.pipeline.fit_scan` with a progress callback
that writes the stage and the overall fraction into the catalog (the same
callback interface that drives the CLI's bars), throttled to a few writes a
second; the admin page polls them.

Crash safety
------------
* A fit writes into ``.tessera/staging/job-<n>/`` (``fit_scan`` itself writes a
  temporary folder, fsyncs and renames); the finished bundle is then renamed
  into the collection, the collection folder fsynced, and only then is the job
  ``done`` (both by ``fitter.fitting.bundle``, the one bundle writer; an old
  bundle is parked in the staging folder until the new one is in place). A
  reader sees no bundle or a whole one, never half of one.
* Cancel: the supervisor kills the worker process (SIGTERM, then SIGKILL) and
  deletes its staging folder: no partial bundle is left.
* A worker killed from outside (``kill -9``) is noticed by the supervisor: the
  job becomes ``interrupted`` and its staging folder is removed.
* If the server itself dies, every worker notices that its pipe from the
  supervisor is closed and exits at once; the next runner to start marks jobs
  left ``running`` as ``interrupted`` and clears the staging area. The upload is
  kept in every case; ``retry`` re-queues the job on it.

Only one runner works on a collection at a time (an ``flock`` on
``.tessera/runner.lock``); a second server on the same collection serves but
leaves the jobs to the first.

Workers are started by multiprocessing's ``forkserver`` method, with
``fitter.fitting.pipeline`` preloaded into the fork server: a job starts in
milliseconds, and never inherits the web server's threads or sockets (a plain
``fork`` of a threaded server can deadlock on a lock held by another thread).
"""

from __future__ import annotations

import fcntl
import logging
import multiprocessing
import os
import shutil
import threading
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..fitting.bundle import publish
from ..fitting.cores import usable_cores
from ..fitting.options import OptionError, fit_options
from ..fitting.stages import overall_progress
from .catalog import Catalog, CatalogError, state_dir

if TYPE_CHECKING:  # the readers load numpy: only the fit's worker process imports them
    from ..fitting.io.limits import InputLimits

log = logging.getLogger(__name__)

PROGRESS_INTERVAL = 0.25  # seconds between progress writes within one stage
EXIT_ORPHANED = 70


def staging_dir(collection: Path, job_id: int) -> Path:
    return state_dir(collection) / "staging" / f"job-{job_id}"


class _ProgressWriter:
    """``fit_scan``'s progress callback: the overall fraction from the stages' weights
    (``fitter.fitting.stages.overall_progress``), into the catalog."""

    def __init__(self, catalog: Catalog, job_id: int) -> None:
        self.catalog, self.job_id = catalog, job_id
        self.stage = ""
        self.best = 0.0
        self.last_write = 0.0

    def __call__(self, stage: str, fraction: float) -> None:
        # with max_error the grid grows and stages repeat: the bar never goes back
        self.best = max(self.best, min(overall_progress(stage, fraction), 0.99))
        now = time.monotonic()
        if stage != self.stage or now - self.last_write >= PROGRESS_INTERVAL:
            self.stage, self.last_write = stage, now
            self.catalog.report_progress(self.job_id, stage, self.best)


def _watch_supervisor(pipe: Connection) -> None:
    """Exit the worker when the supervisor's end of ``pipe`` closes (the server died)."""
    try:
        pipe.recv()
    except (EOFError, OSError):
        pass
    os._exit(EXIT_ORPHANED)


def publish_bundle(staged: Path, destination: Path) -> None:
    """Rename the complete bundle ``staged`` (in a job's staging folder) to ``destination``
    in the collection by :func:`fitter.fitting.bundle.publish`: synced, an old bundle
    replaced, the collection folder fsynced. The old bundle waits for its removal in the
    staging folder, which the supervisor clears if the worker dies meanwhile."""
    publish(staged, destination, aside=staged.parent)


def run_job(collection: str, job_id: int, supervisor: Connection | None = None,
            limits: InputLimits | None = None) -> None:
    """Worker process body: fit one job's upload and publish the bundle into the collection.

    ``limits`` bounds the read of the upload (the server's ``TESSERA_UPLOAD_*`` settings,
    :class:`fitter.collection.uploads.UploadLimits`; default ``InputLimits()``).

    Errors of the input (``ScanError``, bad options) end the job ``failed`` with
    their message; any other exception is recorded the same way with its type,
    because a job must never stay ``running`` without a worker.
    """
    if supervisor is not None:
        threading.Thread(target=_watch_supervisor, args=(supervisor,), daemon=True).start()
    from ..fitting.io import ScanError
    from ..fitting.pipeline import fit_scan

    root = Path(collection)
    catalog = Catalog(root)
    job = catalog.get_job(job_id)
    if job is None or job.state != "running":
        return
    staging = staging_dir(root, job_id)
    shutil.rmtree(staging, ignore_errors=True)
    try:
        upload = catalog.get_upload(job.upload_id)
        if upload is None:
            raise CatalogError(f"upload {job.upload_id} of job {job_id} is not in the catalog")
        scan_path = state_dir(root) / upload["stored_path"]
        options = fit_options(job.options)
        staging.mkdir(parents=True)
        bundle = fit_scan(scan_path, staging / job.object_id, options,
                          _ProgressWriter(catalog, job_id), limits=limits)
        catalog.report_progress(job_id, "publish", 0.995)
        publish_bundle(bundle.path, root / job.object_id)
        provenance = bundle.manifest.get("provenance", {})
        catalog.set_bundle(job.object_id, job.object_id, str(bundle.manifest.get("units", "")),
                           provenance.get("sha256"))
        catalog.finish_job(job_id, "done")
    except (ScanError, OptionError, CatalogError, OSError) as exc:
        catalog.finish_job(job_id, "failed", str(exc))
    except Exception as exc:  # noqa: BLE001 - the job boundary: record it, never leave it running
        log.exception("job %d failed", job_id)
        catalog.finish_job(job_id, "failed", f"internal error ({type(exc).__name__}): {exc}")
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        catalog.close()


def _forkserver_context() -> multiprocessing.context.BaseContext:
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(["fitter.fitting.pipeline", "fitter.collection.jobs"])
    return ctx


@dataclass
class _Running:
    process: multiprocessing.process.BaseProcess
    pipe: Connection
    cancelling: bool = False


class JobRunner:
    """The supervisor of a collection's fit jobs (see the module docstring).

    Parameters
    ----------
    collection : path
        A managed collection (its catalog must exist).
    workers : int, optional
        Fits running at once; default the cores this process may run on
        (``fitter.fitting.cores.usable_cores``).
    poll_interval : float
        Seconds between looks at the catalog.
    limits : InputLimits, optional
        What a job's read of its upload accepts (``tessera serve`` passes the server's
        ``TESSERA_UPLOAD_*`` limits); default ``InputLimits()``.
    """

    def __init__(self, collection: str | os.PathLike, workers: int | None = None,
                 poll_interval: float = 0.2, limits: InputLimits | None = None) -> None:
        self.collection = Path(collection).resolve()
        self.limits = limits
        self.workers = workers or usable_cores()
        if self.workers < 1:
            raise ValueError(f"workers must be at least 1, got {self.workers}")
        self.poll_interval = poll_interval
        self._running: dict[int, _Running] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock_file: Any = None
        self.active = False

    # ---------------------------------------------------------------- lifecycle
    def start(self) -> JobRunner:
        """Take the collection's runner lock, recover after a crash, start supervising.

        When another runner holds the lock this one stays inactive (``active`` False).
        """
        lock_path = state_dir(self.collection) / "runner.lock"
        self._lock_file = open(lock_path, "a+")  # noqa: SIM115 - held for the runner's life
        try:
            fcntl.flock(self._lock_file, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            log.warning("another job runner works on %s; this server leaves jobs to it",
                        self.collection)
            self._lock_file.close()
            self._lock_file = None
            return self
        self.active = True
        self.recover()
        self._ctx = _forkserver_context()
        self._thread = threading.Thread(target=self._loop, name="tessera-job-runner",
                                        daemon=True)
        self._thread.start()
        return self

    def recover(self) -> list[int]:
        """Jobs left ``running`` by a dead runner become ``interrupted``; staging is cleared."""
        with Catalog(self.collection) as catalog:
            ids = catalog.interrupt_running("interrupted: the server or its worker stopped "
                                            "during the fit; the upload is kept, retry to fit "
                                            "it again")
        shutil.rmtree(state_dir(self.collection) / "staging", ignore_errors=True)
        if ids:
            log.warning("jobs %s were running when the last server stopped: now interrupted",
                        ", ".join(map(str, ids)))
        return ids

    def stop(self, timeout: float = 10.0) -> None:
        """Stop supervising; running fits are killed and their jobs become ``interrupted``."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
        with Catalog(self.collection) as catalog:
            for job_id, running in list(self._running.items()):
                self._kill(running.process)
                running.pipe.close()
                catalog.finish_job(job_id, "interrupted", "interrupted: the server was stopped "
                                   "during the fit; retry to fit it again")
                shutil.rmtree(staging_dir(self.collection, job_id), ignore_errors=True)
        self._running.clear()
        if self._lock_file is not None:
            self._lock_file.close()
            self._lock_file = None
        self.active = False

    def __enter__(self) -> JobRunner:
        return self.start()

    def __exit__(self, *exc_info: object) -> None:
        self.stop()

    # ---------------------------------------------------------------- supervising
    @staticmethod
    def _kill(process: multiprocessing.process.BaseProcess) -> None:
        if process.is_alive():
            process.terminate()
            process.join(2.0)
        if process.is_alive():
            process.kill()
        process.join(5.0)

    def _loop(self) -> None:
        catalog = Catalog(self.collection)
        try:
            while not self._stop.is_set():
                try:
                    self._step(catalog)
                except Exception:  # noqa: BLE001 - keep supervising; the next step retries
                    log.exception("job runner step failed")
                self._stop.wait(self.poll_interval)
        finally:
            catalog.close()

    def _step(self, catalog: Catalog) -> None:
        # 1. fits that ended: a worker that died without recording an end was killed
        for job_id, running in list(self._running.items()):
            if running.process.is_alive():
                continue
            running.process.join()
            running.pipe.close()
            del self._running[job_id]
            code = running.process.exitcode
            if running.cancelling:
                catalog.finish_job(job_id, "cancelled", "cancelled while running")
            elif catalog.finish_job(job_id, "interrupted",
                                    f"interrupted: the worker process ended unexpectedly "
                                    f"({_exit_text(code)}); the upload is kept, retry to fit "
                                    "it again"):
                log.warning("job %d: worker ended with %s", job_id, _exit_text(code))
            shutil.rmtree(staging_dir(self.collection, job_id), ignore_errors=True)
        # 2. cancel requests for running fits: stop the process itself
        for job in catalog.running_jobs():
            running = self._running.get(job.id)
            if job.cancel_requested and running is not None and not running.cancelling:
                running.cancelling = True
                self._kill(running.process)
        # 3. start queued jobs while there is a free worker
        while len(self._running) < self.workers and not self._stop.is_set():
            job = catalog.claim_next_job()
            if job is None:
                break
            reader, writer = self._ctx.Pipe(duplex=False)
            process = self._ctx.Process(target=run_job, name=f"tessera-fit-{job.id}",
                                        args=(str(self.collection), job.id, reader, self.limits),
                                        daemon=True)
            process.start()
            reader.close()  # only the worker holds the read end; ours would mask EOF
            catalog.set_worker(job.id, process.pid)
            self._running[job.id] = _Running(process, writer)

    def busy(self) -> int:
        """Fits running now."""
        return len(self._running)


def _runner_process_main(collection: str, workers: int | None, parent: Connection,
                         limits: InputLimits | None = None) -> None:
    """Body of :class:`RunnerProcess`: supervise until the parent closes its pipe end."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    logging.basicConfig(level=logging.WARNING, format="tessera jobs: %(message)s")
    runner = JobRunner(collection, workers, limits=limits).start()
    try:
        parent.recv()
    except (EOFError, OSError):
        pass  # the server stopped, or died: its end of the pipe is closed either way
    runner.stop()


class RunnerProcess:
    """A :class:`JobRunner` in a process of its own, for ``tessera serve``.

    The supervisor must not live in a process that forks (gunicorn's arbiter forks
    its request workers at any time, and a fork copies only the forking thread,
    perhaps with another thread's lock held), so ``tessera serve`` starts it here,
    by ``spawn``. It stops when :meth:`stop` is called or when the server dies
    (its pipe closes): running fits are then killed and marked ``interrupted``.
    """

    def __init__(self, collection: str | os.PathLike, workers: int | None = None,
                 limits: InputLimits | None = None) -> None:
        self.collection = str(Path(collection).resolve())
        self.workers = workers
        self.limits = limits
        self._process: multiprocessing.process.BaseProcess | None = None
        self._pipe: Connection | None = None

    def start(self) -> RunnerProcess:
        ctx = multiprocessing.get_context("spawn")
        reader, self._pipe = ctx.Pipe(duplex=False)
        self._process = ctx.Process(target=_runner_process_main, name="tessera-jobs",
                                    args=(self.collection, self.workers, reader, self.limits),
                                    daemon=False)
        self._process.start()
        reader.close()
        return self

    def stop(self, timeout: float = 20.0) -> None:
        if self._pipe is not None:
            self._pipe.close()  # EOF for the runner: it stops its fits and exits
            self._pipe = None
        if self._process is not None:
            self._process.join(timeout)
            if self._process.is_alive():
                self._process.kill()
            self._process = None


def _exit_text(code: int | None) -> str:
    if code is None:
        return "still running"
    if code < 0:
        return f"killed by signal {-code}"
    return f"exit status {code}"
