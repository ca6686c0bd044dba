"""spot.sweep.cpus: a trial's threads follow the free CPU slots of its node (issue 40, item 1).

Each "trial" here is a child process that holds ``trial_cpus(1)`` on the first two CPUs this
process may use and writes its affinity and own slots to a file every 20 ms until told to stop.
Conditions are waited for (seconds, not milliseconds: the machine may be loaded), never timed.
"""

import json
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from spot import SpotError
from spot.sweep import cpus

ROOT = Path(__file__).resolve().parents[1]
CPUS = sorted(os.sched_getaffinity(0))[:2]
needs_two = pytest.mark.skipif(len(CPUS) < 2, reason="needs a machine with at least 2 CPUs this process may use")

CHILD = textwrap.dedent(
    """
    import json, os, sys, time
    from pathlib import Path
    os.sched_setaffinity(0, json.loads(sys.argv[1]))
    from spot.sweep import cpus
    status, stop, how = Path(sys.argv[2]), Path(sys.argv[3]), sys.argv[4]
    with cpus.trial_cpus(1, poll_s=0.05, wait_s=20, how=how) as share:
        while not stop.exists():
            tmp = status.with_suffix(".tmp")
            tmp.write_text(json.dumps({"aff": sorted(os.sched_getaffinity(0)), "own": sorted(share.own),
                                       "mean": share.mean_cpus()}))
            tmp.replace(status)
            time.sleep(0.02)
    status.write_text(json.dumps({"aff": sorted(os.sched_getaffinity(0)), "own": [], "closed": True}))
    """
)


class Trial:
    def __init__(self, tmp: Path, name: str, how: str = "follow") -> None:
        self.status, self.stop = tmp / f"{name}.json", tmp / f"{name}.stop"
        script = tmp / "child.py"
        script.write_text(CHILD)
        env = {**os.environ, "SPOT_CPU_SLOTS_DIR": str(tmp / "slots"), "PYTHONPATH": str(ROOT)}
        self.proc = subprocess.Popen(
            [sys.executable, str(script), json.dumps(CPUS), str(self.status), str(self.stop), how], env=env
        )

    def state(self) -> dict:
        try:
            return json.loads(self.status.read_text())
        except (OSError, ValueError):
            return {}

    def end(self) -> None:
        self.stop.touch()
        assert self.proc.wait(timeout=60) == 0


def wait_for(cond, what: str, timeout: float = 60.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return
        time.sleep(0.05)
    raise AssertionError(f"not within {timeout} s: {what}")


@needs_two
def test_a_trial_alone_gets_every_cpu_and_two_trials_get_disjoint_single_cpus(tmp_path):
    a = Trial(tmp_path, "a")
    try:
        wait_for(lambda: a.state().get("aff") == CPUS and len(a.state()["own"]) == 1, "A alone on both CPUs")
        b = Trial(tmp_path, "b")
        try:
            # B gets a slot of its own (A gives back what it borrowed) and A narrows to its own slot
            wait_for(lambda: len(b.state().get("own", [])) == 1, "B claims a slot")
            wait_for(lambda: a.state()["aff"] == a.state()["own"], "A back on its own slot")
            for _ in range(10):  # and it stays so while both run (A does not borrow B's slot back)
                sa, sb = a.state(), b.state()
                assert sb["aff"] == sb["own"] and sa["aff"] == sa["own"]
                assert len(sa["aff"]) == len(sb["aff"]) == 1 and set(sa["aff"]).isdisjoint(sb["aff"])
                time.sleep(0.1)
        finally:
            b.end()
        wait_for(lambda: a.state()["aff"] == CPUS, "A on both CPUs again once B ended")
        assert 1.0 < a.state()["mean"] < 2.0  # part of its time on one CPU, part on two
    finally:
        a.end()
    assert a.state() == {"aff": CPUS, "own": [], "closed": True}  # released; the allowed CPUs again
    assert not list((tmp_path / "slots").glob("borrowed-*")) and not list((tmp_path / "slots").glob("want-*"))


@needs_two
def test_two_trials_started_together_get_disjoint_cpus(tmp_path):
    a, b = Trial(tmp_path, "a"), Trial(tmp_path, "b")
    try:
        wait_for(lambda: len(a.state().get("own", [])) == 1 and len(b.state().get("own", [])) == 1, "both claim")
        wait_for(lambda: a.state()["aff"] == a.state()["own"] and b.state()["aff"] == b.state()["own"], "pinned")
        assert set(a.state()["own"]).isdisjoint(b.state()["own"])
    finally:
        a.end()
        b.end()


@needs_two
def test_pinned_mode_keeps_the_claimed_cpu(tmp_path):
    a = Trial(tmp_path, "a", how="pinned")
    try:
        wait_for(lambda: len(a.state().get("own", [])) == 1, "A claims")
        time.sleep(0.5)  # ten of the watcher's looks in the follow modes
        assert a.state()["aff"] == a.state()["own"] and a.state()["mean"] == pytest.approx(1.0)
    finally:
        a.end()


def test_mode_reads_the_variable(monkeypatch):
    monkeypatch.delenv(cpus.MODE_VAR, raising=False)
    assert cpus.mode() == "pinned"
    monkeypatch.setenv(cpus.MODE_VAR, "follow")
    assert cpus.mode() == "follow"
    monkeypatch.setenv(cpus.MODE_VAR, "all")
    with pytest.raises(SpotError, match=r"SPOT_TRIAL_THREADS='all': expected one of pinned, follow, follow-eigen"):
        cpus.mode()


def test_xla_cpus_sets_the_pool_for_the_follow_modes(monkeypatch, tmp_path):
    monkeypatch.delenv("NPROC", raising=False)
    assert cpus.Share(tmp_path, [0], {}, "pinned").xla_cpus(1) == 1 and "NPROC" not in os.environ  # the node
    held = {0: open(tmp_path / "cpu0", "w")}  # noqa: SIM115 - a claimed slot's open file
    assert cpus.Share(tmp_path, [0, 1, 2], held, "pinned").xla_cpus(1) == 1 and "NPROC" not in os.environ
    # no slot (a fractional CPU, or none free): the pool of a pinned trial, not of the whole node
    assert cpus.Share(tmp_path, [0, 1, 2], {}, "pinned").xla_cpus(1) == 1 and os.environ["NPROC"] == "1"
    held[0].close()
    monkeypatch.delenv("NPROC")
    assert cpus.Share(tmp_path, [0, 1, 2], {}, "follow").xla_cpus(1) == 1 and os.environ["NPROC"] == "2"
    assert cpus.Share(tmp_path, [0, 1, 2], {}, "follow-eigen").xla_cpus(1) == 2
    assert [cpus.pool_size(c, node) for c, node in ((1, 1), (1, 2), (1, 16), (3, 4), (4, 16))] == [1, 2, 2, 4, 8]


def test_a_trial_borrows_at_most_its_pools_cpus_and_gives_them_back_when_wanted(monkeypatch, tmp_path):
    pinned: list[list[int]] = []
    monkeypatch.setattr(cpus, "set_affinity", lambda c: pinned.append(sorted(c)))  # (CPU numbers of a 4-CPU node)
    own = cpus.claim(tmp_path, [0, 1, 2, 3], 1, wait_s=0)
    share = cpus.Share(tmp_path, [0, 1, 2, 3], own, "follow")
    assert share.look() and share.cpus() == [0, 1] and pinned == [[0, 1]]  # 2 of 4: twice its own
    assert (tmp_path / "borrowed-1").read_text() == str(os.getpid())
    assert not share.look()  # nothing changed
    (tmp_path / f"want-{os.getpid()}").write_text(str(os.getpid()))  # a starting trial wants slots
    assert share.look() and share.cpus() == [0] and pinned[-1] == [0] and not (tmp_path / "borrowed-1").exists()
    (tmp_path / f"want-{os.getpid()}").unlink()
    (tmp_path / "want-999999999").write_text("999999999")  # a dead process's want: removed, not obeyed
    assert share.look() and share.cpus() == [0, 1] and not (tmp_path / "want-999999999").exists()
    share.close()
    assert pinned[-1] == [0, 1, 2, 3] and not list(tmp_path.glob("borrowed-*"))
    assert len(cpus.claim(tmp_path, [0, 1, 2, 3], 4, wait_s=0)) == 4  # every slot free again


IQL = textwrap.dedent(
    """
    import hashlib, json, os, sys
    os.sched_setaffinity(0, json.loads(sys.argv[1]))
    from spot import runtime
    runtime.configure()  # spot's XLA flags, as in a trial
    import jax, numpy as np
    from spot.batches import Transitions
    from spot.config import IQLConfig
    from spot.policy import iql
    rng = np.random.default_rng(0)
    n = 4096
    data = Transitions(obs=rng.standard_normal((n, 11), np.float32), act=rng.uniform(-1, 1, (n, 3)).astype(np.float32),
                       rew=rng.standard_normal(n, np.float32), next_obs=rng.standard_normal((n, 11), np.float32),
                       mask=np.ones(n, np.float32))
    cfg = IQLConfig(chunk=20)
    key = jax.random.key(0)
    state, _ = iql.make_train_chunk(cfg)(iql.init_state(key, 11, 3, cfg), 20, data, key)
    leaves = [np.asarray(x).tobytes() for x in jax.tree_util.tree_leaves(state) if hasattr(x, "dtype")
              and not jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)]
    print(len(jax.devices()), hashlib.sha256(b"".join(leaves)).hexdigest())
    """
)


@needs_two
def test_the_follow_pool_leaves_a_1_cpu_trials_numbers_unchanged(tmp_path):
    """A 1-CPU trial in ``follow`` mode (XLA pool of 2 threads, on 2 CPUs or narrowed to 1)
    computes the same IQL updates, to the bit, as a pinned one (pool of 1 thread on 1 CPU). (Without
    spot's XLA flags the pool size changes the compiled program: outer-dimension partitions.)"""
    script = tmp_path / "iql.py"
    script.write_text(IQL)
    env = {k: v for k, v in os.environ.items() if k not in ("NPROC", "XLA_FLAGS")}
    env.update(PYTHONPATH=str(ROOT), XLA_FLAGS="--xla_cpu_multi_thread_eigen=false", SPOT_CACHE_DIR=str(tmp_path))

    def run(cpu_list: list[int], nproc: str | None) -> str:
        e = {**env, **({"NPROC": nproc} if nproc else {})}
        out = subprocess.run([sys.executable, str(script), json.dumps(cpu_list)], env=e, capture_output=True, text=True)
        assert out.returncode == 0, out.stderr[-2000:]
        return out.stdout.split()[-1]

    pinned = run(CPUS[:1], None)
    assert run(CPUS, "2") == pinned and run(CPUS[:1], "2") == pinned


def test_a_trial_asking_for_a_fraction_of_a_cpu_claims_no_slot_and_stays_where_the_os_puts_it(monkeypatch, tmp_path):
    monkeypatch.setenv("SPOT_CPU_SLOTS_DIR", str(tmp_path / "slots"))
    monkeypatch.delenv("NPROC", raising=False)
    before = os.sched_getaffinity(0)
    with cpus.trial_cpus(1, how="pinned", claim_slots=False) as share:
        assert share.own == {} and os.sched_getaffinity(0) == before
        assert not list((tmp_path / "slots").glob("cpu*"))  # no slot file locked
        if len(before) > 1:
            assert share.xla_cpus(1) == 1 and os.environ["NPROC"] == "1"
    monkeypatch.delenv("NPROC", raising=False)


def test_a_trial_sharing_the_cores_had_the_cpu_it_used_and_a_pinned_one_its_slots(tmp_path):
    from spot.sweep.trial import _cpus_had

    shared = cpus.Share(tmp_path, [0, 1], {}, "pinned")  # no slot on a 2-CPU node: shared as the OS schedules
    assert _cpus_had(shared, 1, cpu_s=30.0, wall_s=45.0) == pytest.approx(2 / 3)
    whole = cpus.Share(tmp_path, [0], {}, "pinned")  # a 1-CPU node: the trial had all of it
    assert _cpus_had(whole, 1, cpu_s=10.0, wall_s=40.0) == pytest.approx(1.0, rel=1e-3)
