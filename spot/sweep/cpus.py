"""A trial's CPUs on its node: the slots it claims, and the free ones its threads follow.

A trial claims the CPUs it asked for (``resources.cpu``) as slots: ``flock``s on the files
``cpu<i>`` in ``$SPOT_CPU_SLOTS_DIR`` (default ``$TMPDIR/spot-cpu-slots``), held while the trial
runs and released when it ends however it ends, so concurrent trials that share the folder (every
sweep on the node, by default) get disjoint CPUs, and the trial's process is pinned to them
(``sched_setaffinity``, every thread).

How its threads use CPUs no trial holds depends on ``$SPOT_TRIAL_THREADS`` (:data:`MODES`):

* ``pinned`` (the default): the trial keeps the CPUs it claimed (a 1-CPU trial's XLA pool has one
  thread). It is the default because ``follow`` was measured no faster on the quickstart (2 cores:
  178.0 s against 169.5 s, docs/benchmarks.md) and changed a result: a PT reward model trained in
  a widened 2-thread process differs in the last digits from a pinned one's, and the quickstart's PT
  and SPOT scores with it (7.8 and 3.8 against 8.1 and 7.7), so a run's numbers would depend on
  whether it happened to run alone.
* ``follow``: a watcher thread looks at the slots every :data:`POLL_S` seconds and
  *borrows* free ones (it locks them too, and writes ``borrowed-<i>``), up to twice the trial's own
  (:func:`pool_size`), widening the process's affinity onto them; a 1-CPU trial that runs alone on
  a 2-CPU node therefore gets every core, and its threads narrow back to the trial's own slots as
  soon as another trial starts: a starting trial
  that finds too few free slots while some are borrowed writes ``want-<pid>`` and waits (up to
  :data:`WAIT_S`) while the borrowers give their borrowed slots back at their next look. XLA's CPU
  thread pool is sized once, when the process's first backend starts, from the affinity mask or
  ``$NPROC`` (``xla::DefaultThreadPoolSize``): the trial sets ``NPROC`` to :func:`pool_size` before
  jax starts, so the pool has a thread per CPU the trial may come to hold (XLA then partitions
  large elementwise loops and runs independent operations, such as the three updates of IQL's
  ``parallel`` order, side by side). Eigen stays single-threaded in a 1-CPU trial
  (``--xla_cpu_multi_thread_eigen=false``, as before). Under spot's XLA flags
  (:mod:`spot.runtime`) IQL's updates are bit-equal to a pinned trial's, widened or not (a test);
  the PT reward model's training is not (above).
* ``follow-eigen``: as ``follow``, and Eigen's operations use every thread of the pool too; their
  sums may then differ in the last digits from a 1-CPU trial's (docs/sweeps.md), and a narrowed
  trial splits them over threads that share one core.

A trial that asked for a fraction of a CPU (``resources.cpu: 0.5``: Ray then runs more trials than
the node has cores) claims no slot, and nor does one as large as the node or one that finds no free
slot: nothing is claimed, pinned or borrowed, and its threads run where the OS puts them. In
``pinned`` mode such a trial's XLA pool still has as many threads as a pinned trial's (``NPROC``,
:meth:`Share.xla_cpus`), so its numbers are a pinned trial's. Nothing here imports jax.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from spot import SpotError

MODE_VAR = "SPOT_TRIAL_THREADS"
MODES = ("pinned", "follow", "follow-eigen")
POLL_S = 1.0  # seconds between two looks at the slots (a starting trial waits at most about this)
WAIT_S = 10.0  # how long a starting trial waits for borrowed slots to come back


def mode() -> str:
    """``$SPOT_TRIAL_THREADS`` (default ``pinned``); another value is a :class:`spot.SpotError`."""
    value = os.environ.get(MODE_VAR, "").strip() or MODES[0]
    if value not in MODES:
        raise SpotError(f"${MODE_VAR}={value!r}: expected one of {', '.join(MODES)}")
    return value


def slots_dir() -> Path:
    """The node's slot folder: ``$SPOT_CPU_SLOTS_DIR``, else ``$TMPDIR/spot-cpu-slots`` (made here)."""
    folder = Path(os.environ.get("SPOT_CPU_SLOTS_DIR") or Path(tempfile.gettempdir()) / "spot-cpu-slots")
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def set_affinity(cpus: list[int] | set[int]) -> None:
    """Every thread of this process on ``cpus`` (threads started later inherit their creator's)."""
    for tid in os.listdir("/proc/self/task"):
        with contextlib.suppress(OSError):  # a thread that ended meanwhile
            os.sched_setaffinity(int(tid), cpus)


def _lock(folder: Path, cpu: int) -> Any | None:
    """The open, locked slot file of ``cpu``, or None if another process holds it."""
    f = open(folder / f"cpu{cpu}", "a")  # noqa: SIM115 - held (locked) until released
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        f.close()
        return None
    return f


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


def _live_marks(folder: Path, prefix: str) -> list[Path]:
    """The ``<prefix>-*`` marks whose process (the pid in the file) is alive; dead ones are removed."""
    out = []
    for path in folder.glob(f"{prefix}-*"):
        try:
            pid = int(path.read_text() or "0")
        except (OSError, ValueError):
            continue  # being written or removed right now
        if pid and _alive(pid):
            out.append(path)
        else:
            with contextlib.suppress(OSError):
                path.unlink()
    return out


def _mark(path: Path) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}")
    tmp.write_text(str(os.getpid()))
    tmp.replace(path)  # whole, never a half-written pid


def claim(folder: Path, allowed: list[int], n: int, wait_s: float = WAIT_S) -> dict[int, Any]:
    """Lock ``n`` free slots among ``allowed`` (``{cpu: open file}``), or none. While some slots are
    borrowed by another trial (``borrowed-<i>``), say ``want-<pid>`` and wait up to ``wait_s`` for
    them to come back."""
    held: dict[int, Any] = {}
    want = folder / f"want-{os.getpid()}"
    start = time.monotonic()
    try:
        while True:
            for cpu in allowed:
                if len(held) < n and cpu not in held and (f := _lock(folder, cpu)) is not None:
                    held[cpu] = f
            waited = time.monotonic() - start
            if len(held) == n or waited > wait_s or (waited > 0.1 and not _live_marks(folder, "borrowed")):
                break  # (0.1 s: a borrower marks its slot just after locking it)
            if not want.exists():
                _mark(want)
            time.sleep(0.02)
    finally:
        with contextlib.suppress(OSError):
            want.unlink()
    if len(held) < n:
        for f in held.values():
            f.close()
        return {}
    return held


class Share:
    """The CPUs of one trial: its own slots, and (``follow`` modes) the free slots it borrowed.

    :meth:`look` is one look at the slots (the watcher thread calls it every ``poll_s``): give the
    borrowed slots back if a starting trial wants some, else borrow the free ones; the process's
    affinity is set to :meth:`cpus` whenever they change. :meth:`mean_cpus` is the number of CPUs
    the trial had, averaged over its time so far.
    """

    def __init__(self, folder: Path, allowed: list[int], own: dict[int, Any], how: str) -> None:
        self.folder, self.allowed, self.own, self.how = folder, allowed, own, how
        self.borrow = how != "pinned"
        self.limit = pool_size(len(own), len(allowed)) if self.borrow else len(own)  # CPUs held at most
        self.borrowed: dict[int, Any] = {}
        self._lock = threading.Lock()
        self._since = self._start = time.monotonic()
        self._cpu_time = 0.0

    def cpus(self) -> list[int]:
        """The CPUs the trial's threads may run on: its own and borrowed slots (all allowed CPUs if
        it holds no slot)."""
        return sorted([*self.own, *self.borrowed]) if self.own else list(self.allowed)

    def _account(self) -> None:
        now = time.monotonic()
        self._cpu_time += (now - self._since) * len(self.cpus())
        self._since = now

    def mean_cpus(self) -> float:
        with self._lock:
            self._account()
            return self._cpu_time / max(self._since - self._start, 1e-9) if self._since > self._start else 0.0

    def shares_node(self, cpus: int) -> bool:
        """Whether a trial of ``cpus`` CPUs holding this share runs unpinned beside other trials: it
        holds no slot (a fraction of a CPU asked, or none free) and is smaller than the node."""
        return not self.own and cpus < len(self.allowed)

    def xla_cpus(self, cpus: int) -> int:
        """Before jax starts: ``NPROC`` for XLA's pool in the ``follow`` modes (:func:`pool_size`
        threads), and in ``pinned`` mode for a trial that holds no slot (``cpus`` threads, as a
        pinned trial's pool: unpinned, XLA would size it from the whole node's affinity, and a PT
        reward model trained with more threads differs in the last digits); a ``NPROC`` already
        set is kept. Returns the CPU count to configure XLA for
        (:func:`spot.sweep.trial.configure_process`): the trial's ``cpus``, or its pool's in
        ``follow-eigen`` (Eigen then stays multi-threaded)."""
        if not self.borrow:
            if self.shares_node(cpus):  # no slot: a pool the size of a pinned trial's
                os.environ.setdefault("NPROC", str(cpus))
            return cpus
        pool = pool_size(cpus, len(self.allowed))
        os.environ.setdefault("NPROC", str(pool))
        return pool if self.how == "follow-eigen" else cpus

    def _give_back(self) -> None:
        for cpu, f in self.borrowed.items():
            with contextlib.suppress(OSError):
                (self.folder / f"borrowed-{cpu}").unlink()
            f.close()
        self.borrowed = {}

    def look(self) -> bool:
        """One look at the slots; True if the trial's CPUs changed."""
        if not (self.own and self.borrow):
            return False
        with self._lock:
            before = self.cpus()
            self._account()
            if _live_marks(self.folder, "want"):
                self._give_back()
            else:
                for cpu in self.allowed:
                    if len(self.own) + len(self.borrowed) >= self.limit:
                        break
                    if cpu not in self.own and cpu not in self.borrowed and (f := _lock(self.folder, cpu)):
                        self.borrowed[cpu] = f
                        _mark(self.folder / f"borrowed-{cpu}")
            changed = self.cpus() != before
            if changed:
                set_affinity(self.cpus())
            return changed

    def close(self) -> None:
        """Borrowed and own slots released, the process's threads on the allowed CPUs again."""
        with self._lock:
            self._account()
            self._give_back()
            if self.own:
                set_affinity(self.allowed)
            for f in self.own.values():
                f.close()
            self.own = {}


def pool_size(cpus: int, node: int) -> int:
    """The CPUs a trial of ``cpus`` may come to hold on a node of ``node`` (and its XLA pool's
    threads): twice its own, at most the node's. Capped so that a narrowed trial's pool stays
    small (its threads then share the trial's own CPUs) and so that one lone trial on a large node
    does not take every free slot from the trials that start after it."""
    return max(cpus, min(node, 2 * cpus))


def _watch(share: Share, stop: threading.Event, poll_s: float) -> None:
    while not stop.wait(poll_s):
        share.look()


@contextlib.contextmanager
def trial_cpus(
    n: int, poll_s: float = POLL_S, wait_s: float = WAIT_S, how: str | None = None, claim_slots: bool = True
) -> Iterator[Share]:
    """Claim ``n`` CPU slots of this node for a trial and pin the process to them (none with
    ``claim_slots`` False: a trial that asked Ray for a fraction of a CPU shares the node's cores
    with the others, as the OS schedules them); in the ``follow``
    modes (``how``, default :func:`mode`) a watcher thread widens the process onto free slots and
    narrows it back (module docstring). Yields the :class:`Share`; at the end the watcher stops,
    every slot is released and the process's threads get the CPUs they had back (a reused actor
    runs the next trial in them)."""
    how = how or mode()
    allowed = sorted(os.sched_getaffinity(0))
    folder = slots_dir()
    own = claim(folder, allowed, n, wait_s) if claim_slots and n < len(allowed) else {}
    share = Share(folder, allowed, own, how)
    stop = threading.Event()
    watcher = threading.Thread(target=_watch, args=(share, stop, poll_s), name="spot-cpus", daemon=True)
    try:
        if own:
            set_affinity(share.cpus())
            share.look()
            watcher.start()
        yield share
    finally:
        stop.set()
        if watcher.is_alive():
            watcher.join()
        share.close()
