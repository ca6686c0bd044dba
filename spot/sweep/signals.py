"""How a launch stops on a signal: SIGINT ends it as :class:`Interrupted`; a SIGTERM's cleanup
(:func:`on_sigterm`) runs in steps, each with its own deadline and message (:func:`sigterm_cleanup`),
and a watchdog ends the process if the cleanup overruns.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any


def quiet_ray_sigterm() -> None:
    """In a trial's process: a SIGTERM that lands while the main thread runs a weakref callback or a
    ``__del__`` ends the process as any other, without ``Exception ignored ... SystemExit: 1``.

    Ray's worker handles SIGTERM (sent to the trial processes when Ray shuts down at a sweep's end)
    by raising ``SystemExit`` wherever the main thread is. Inside a callback of the garbage collector
    Python cannot raise it: it prints ``Exception ignored in: <function WeakSet...._remove>`` and the
    traceback to stderr, which Ray forwards to the end of the sweep's log, and the process goes on
    (until Ray kills it). This :data:`sys.unraisablehook` takes such a ``SystemExit`` (one raised by
    Ray's ``sigterm_handler``), prints nothing and sends the SIGTERM again a moment later, outside the
    callback, where Ray's handler ends the process as it meant to; anything else goes to the hook
    that was there. Set once per process."""
    from spot import runtime

    def ray_sigterm(unraisable: Any) -> int | None:
        ok = isinstance(unraisable.exc_value, SystemExit) and _raised_by_ray_sigterm(unraisable.exc_traceback)
        return signal.SIGTERM if ok else None

    runtime.resend_swallowed_signal("ray_sigterm", ray_sigterm)


def _raised_by_ray_sigterm(tb: Any) -> bool:
    """Whether the traceback passes through Ray's worker SIGTERM handler (``ray/_private/worker.py``)."""
    while tb is not None:
        code = tb.tb_frame.f_code
        if code.co_name == "sigterm_handler" and code.co_filename.replace("\\", "/").endswith("ray/_private/worker.py"):
            return True
        tb = tb.tb_next
    return False


class Interrupted(Exception):  # noqa: N818 - a stop, not an error
    """The launch was stopped by SIGTERM or SIGINT; its runs are closed (KILLED) and Ray is shut down.

    ``exit_code`` is the shell's convention, 128 + the signal number (143 for SIGTERM, 130 for SIGINT).
    """

    def __init__(self, signum: int) -> None:
        self.signum = signum
        self.exit_code = 128 + signum
        super().__init__(f"sweep stopped by {signal.Signals(signum).name}")


SIGTERM_GRACE_S = 60.0  # the longest a SIGTERM's cleanup may take before the process exits anyway
_CLEANUP = {"step": ""}  # the step of a signal's cleanup now running (:func:`_cleanup_step`), for the watchdog
CLEANUP_REQUEST_S = 5  # the deadline of each MLflow request of a signal's cleanup (no retries then)
CLEANUP_STEPS_S = {
    "stopping the trials": 10.0,
    "closing the runs": 25.0,
    "stopping Ray": 10.0,
    "stopping the MLflow server": 10.0,
}  # each step's deadline; together below SIGTERM_GRACE_S, so the watchdog is the last resort only


def say(message: str) -> None:
    """A line on stderr from a signal handler: it must not raise, even when the handler interrupted a
    write to the same stream (a reentrant write raises ``RuntimeError``)."""
    with contextlib.suppress(Exception):
        print(message, file=sys.stderr, flush=True)


@contextlib.contextmanager
def on_sigterm(stop: Callable[[], None], grace_s: float = SIGTERM_GRACE_S) -> Iterator[None]:
    """Within the block, SIGTERM runs ``stop()`` and ends the process with exit code 143.

    A SIGTERM to the sweep's process group (``timeout``, a batch scheduler) reaches Ray's GCS,
    raylet and workers too, and Tune's own cleanup would then wait forever on the dead cluster;
    so the driver does not unwind through Tune: ``stop()`` stops the trials, closes the runs in
    MLflow (the server runs in its own session and survives the signal), stops Ray and the server,
    and the process exits at once. The exit is certain: an exception from ``stop()`` is printed,
    a flush of a stream that raises cannot skip the exit, and a watchdog thread (started with the
    block, armed by the signal, so the handler starts no thread) ends the process with the same
    code if ``stop()`` has not returned after ``grace_s`` seconds. Further SIGTERMs are ignored
    meanwhile. The handler ``ray.init`` installs (``sys.exit(15)``) is restored after the block.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.getsignal(signal.SIGTERM)
    armed, over = threading.Event(), threading.Event()

    def watchdog() -> None:
        armed.wait()
        if not over.wait(grace_s):  # set at once when the block ended without a signal
            step = f" (in step '{_CLEANUP['step']}')" if _CLEANUP["step"] else ""
            say(f"SIGTERM: cleanup still running after {grace_s:.0f} s{step}; exiting")
            os._exit(128 + signal.SIGTERM)

    def handler(signum: int, frame: Any) -> None:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        _CLEANUP["step"] = ""
        armed.set()
        try:
            stop()
        except BaseException as e:  # noqa: BLE001 - reported, then the exit below
            say(f"SIGTERM: cleanup failed: {type(e).__name__}: {e}")
        finally:
            for stream in (sys.stdout, sys.stderr):
                with contextlib.suppress(Exception):
                    stream.flush()
            os._exit(128 + signum)

    threading.Thread(target=watchdog, name="sigterm-watchdog", daemon=True).start()
    signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
        over.set()
        armed.set()


def _kill_trial_workers(timeout: float = 5.0) -> None:
    """SIGKILL the worker processes (``ray::...``: the trials) of the local Ray node this driver
    started and wait for them, without talking to Ray; the node itself stays up, so nothing a
    trial could still do (finish its run, open the next seed's) outlives the closing of the runs."""
    import psutil
    import ray
    from ray._private import ray_constants

    node = getattr(ray._private.worker, "_global_node", None)
    if node is None:
        return
    workers = []
    for info in node.all_processes.get(ray_constants.PROCESS_TYPE_RAYLET, []):
        with contextlib.suppress(psutil.Error):
            for child in psutil.Process(info.process.pid).children(recursive=True):
                with contextlib.suppress(psutil.Error, IndexError):
                    if child.cmdline()[0].startswith("ray::"):
                        workers.append(child)
    for worker in workers:
        with contextlib.suppress(psutil.Error):
            worker.kill()
    psutil.wait_procs(workers, timeout=timeout)


def _kill_local_ray() -> None:
    """Stop the processes of the local Ray node this driver started, without talking to them (the
    GCS may already be gone, and ``ray.shutdown()`` would wait for it)."""
    import ray

    node = getattr(ray._private.worker, "_global_node", None)
    if node is not None:
        with contextlib.suppress(Exception):
            node.kill_all_processes(check_alive=False, allow_graceful=True)


def _cleanup_step(name: str, fn: Callable[[float], Any]) -> None:
    """One step of a signal's cleanup: says what it does and its deadline (:data:`CLEANUP_STEPS_S`),
    runs ``fn(deadline)`` (a ``time.monotonic()`` value it keeps to), says how it failed or that it
    overran; never raises."""
    budget = CLEANUP_STEPS_S[name]
    start = time.monotonic()
    _CLEANUP["step"] = name
    say(f"SIGTERM: {name} (deadline {budget:.0f} s)")
    try:
        fn(start + budget)
    except Exception as e:  # noqa: BLE001 - reported; the next step runs
        say(f"SIGTERM: {name} failed after {time.monotonic() - start:.1f} s: {type(e).__name__}: {e}")
        return
    spent = time.monotonic() - start
    if spent > budget:
        say(f"SIGTERM: {name} took {spent:.1f} s, past its deadline of {budget:.0f} s")


def _left(deadline: float) -> float:
    return max(0.5, deadline - time.monotonic())


def sigterm_cleanup(store: Any, close: Callable[[str, float], None], started_ray: bool) -> None:
    """A SIGTERM's cleanup, in steps with their own deadlines (:func:`_cleanup_step`): stop the
    trials, close the runs (``close(reason, deadline)``; MLflow requests get :data:`CLEANUP_REQUEST_S`
    and no retries, and the runs go through the SQLite store itself if the server is gone or does not
    answer), stop Ray, stop the MLflow server (``store.stop``: a :class:`spot.sweep.tracking_store.Store`)."""
    from spot.tracking import limits

    os.environ.update({k: "0" if "RETRIES" in k else str(CLEANUP_REQUEST_S) for k in limits.HTTP_DEADLINES})
    say("SIGTERM: stopping the trials, closing the runs, stopping Ray")
    if started_ray:
        _cleanup_step("stopping the trials", lambda until: _kill_trial_workers(_left(until)))
    _cleanup_step("closing the runs", lambda until: close("launch stopped by SIGTERM", until))
    if started_ray:
        _cleanup_step("stopping Ray", lambda until: _kill_local_ray())
    _cleanup_step("stopping the MLflow server", lambda until: store.stop(_left(until)))
