"""robosuite Lift and Can demonstrations from scripted operators, in the style of robomimic's ph/mh sets.

robomimic v0.1 (Mandlekar et al., 2021, arXiv:2108.03298, Sec. 3) recorded human teleoperation:
``ph`` = 200 successful demonstrations of one proficient operator; ``mh`` = 300 demonstrations of
six operators of mixed skill, two each rated "better", "okay" and "worse", 50 demonstrations each.
Both hold completed demonstrations only (failed rollouts appear only in the machine-generated sets).
Nothing can be downloaded here, so scripted operators stand in for the humans:

* The controller is a phase machine over the robomimic ``low_dim`` observation (object position
  and ``robot0_eef_pos``/``robot0_eef_quat``/``robot0_gripper_qpos``). Lift: above the cube,
  descend, close, lift. Can: above the can, descend, close, lift over the bin wall, carry over the
  can's quadrant of the target bin, lower, open, retreat. A missed grasp (fingers closed on
  nothing) or a dropped object sends it back to the first phase, as a human would regrasp.
* Actions are the 7-D OSC_POSE deltas + gripper of :func:`spot.envs.make_env`'s env:
  ``clip(gain · (target − eef), ±speed)`` for position, a P term that holds the initial
  (downward) gripper orientation for rotation, AR(1) Gaussian noise on both, gripper ±1.
* Operators differ in action noise, speed and gain, the std of a per-phase offset of every
  target ("sloppy" targets), the arrival tolerance, hesitation pauses (a per-step chance of
  holding still for a few steps), and how many fumbles (missed grasps, drops) they take before
  abandoning an attempt, as a teleoperator resets a botched demo. ``ph`` has one low-noise
  operator; ``mh`` six
  (:data:`MH_OPERATORS`), two per skill level, equal numbers of demonstrations each.

Episodes run in the evaluation env (:func:`spot.envs.make_env`: Panda, composite OSC_POSE, 20 Hz,
sparse reward, horizon 500, robomimic observation, Lift 49-D / Can 53-D) and end at the first
success, as the evaluation episodes do; the success step has reward 1 and ``terminals = 1``, every
other step reward 0. Attempts abandoned or still unsuccessful at the horizon are discarded (and
counted in the card's success rates); an operator keeps attempting until it has its share of
demonstrations. Success rates over 20 attempts per operator are in docs/datasets.md.

Each step also records robosuite's dense staged reward of the state it reached
(``infos/dense_reward``, :meth:`spot.envs._RobosuiteEnv.staged_reward`: the env's own reward with
``reward_shaping=True``; Lift (reach + grasp) / 2.25, Can max(reach, grasp, lift, hover), 1 at the
success step), which ``labels.score=dense`` makes the scripted teacher compare: with the sparse
reward nearly every pair of segments of successful demonstrations ties. ``rewards`` stays sparse.

Sizes (demonstrations ph / mh): ``tiny`` 3 / 6 (tests), ``small`` 40 / 60, ``paper`` 200 / 300
(robomimic's). Deterministic for a seed: each operator draws placements and noise from its own
generator spawned from the seed, :func:`spot.envs.make_env` builds the env with the global numpy
RNG seeded (robosuite draws Lift's cube size from it), and MuJoCo is deterministic.

``RECIPE_VERSION`` is stored in the card; :func:`spot.data.registry.build` rebuilds a cached build
whose card has another version (builds from before version 2 lack the dense reward).

Differences from robomimic: scripted instead of human operators; demos end at their first
success step; robosuite 1.5.1 and its observation layout rather than the ``offline_study``
branch (in particular Can's ``object`` block is [Can_to_eef_pos, Can_to_eef_quat, Can_pos,
Can_quat], not robomimic v0.1's order; :func:`spot.data.formats.read_robomimic_hdf5` reorders
real robomimic Can files to match).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from importlib.metadata import version
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

import spot
from spot import SpotError
from spot.data.dataset import DENSE_REWARD_KEY, RawDataset, raw_from_episodes
from spot.envs import ROBOSUITE_HORIZON, make_env

RECIPE_VERSION = 2  # bump when a change here alters the datasets (2: infos/dense_reward)
SIZES = {"tiny": {"ph": 3, "mh": 6}, "small": {"ph": 40, "mh": 60}, "paper": {"ph": 200, "mh": 300}}
TASKS = ("lift", "can")
MAX_ATTEMPTS_FACTOR = 10  # give up when an operator needs more than this many attempts per demo


@dataclass(frozen=True)
class Operator:
    """One scripted operator. Positions in metres; actions in the env's [-1, 1] units."""

    name: str
    skill: str  # "proficient" (ph) or robomimic's "better" / "okay" / "worse" (mh)
    noise: float  # std of the AR(1) noise added to the position action
    rot_noise: float  # std of the AR(1) noise added to the rotation action
    noise_corr: float  # AR(1) coefficient of both noises (human jitter is correlated in time)
    gain: float  # position action per metre of error
    speed: float  # largest |position action| per axis
    jitter: float  # std of the offset drawn for every target at each phase entry
    tol: float  # distance to a target that counts as arrived
    pause_prob: float  # per-step chance of starting a hesitation pause
    pause_steps: tuple[int, int]  # pause length range [low, high)
    grip_steps: int  # steps the gripper is held closed (or open) before moving on
    max_fumbles: int  # the attempt is abandoned at the next fumble (missed grasp or drop)


PROFICIENT = Operator(
    "ph",
    "proficient",
    noise=0.03,
    rot_noise=0.01,
    noise_corr=0.5,
    gain=12.0,
    speed=1.0,
    jitter=0.002,
    tol=0.01,
    pause_prob=0.0,
    pause_steps=(1, 2),
    grip_steps=8,
    max_fumbles=3,
)
MH_OPERATORS = (
    Operator("better_operator_1", "better", 0.08, 0.03, 0.7, 12.0, 1.0, 0.004, 0.010, 0.005, (3, 8), 8, 3),
    Operator("better_operator_2", "better", 0.10, 0.03, 0.7, 9.0, 0.8, 0.005, 0.012, 0.010, (3, 8), 9, 3),
    Operator("okay_operator_1", "okay", 0.20, 0.06, 0.8, 8.0, 0.8, 0.008, 0.015, 0.015, (5, 15), 10, 2),
    Operator("okay_operator_2", "okay", 0.25, 0.06, 0.8, 14.0, 1.0, 0.009, 0.015, 0.020, (5, 15), 8, 2),
    Operator("worse_operator_1", "worse", 0.28, 0.08, 0.8, 8.0, 0.7, 0.010, 0.020, 0.030, (8, 25), 12, 1),
    Operator("worse_operator_2", "worse", 0.32, 0.08, 0.8, 15.0, 1.0, 0.011, 0.020, 0.030, (8, 25), 7, 1),
)

# Geometry of the scripts (metres, world frame; Lift's table top z = 0.8, Can's bin floors z = 0.82
# with walls and dividers up to z = 0.9).
_HOVER = 0.08  # approach height above the object's centre
_GRASP_DZ = {"lift": -0.005, "can": 0.01}  # grasp point relative to the object's centre
_LIFT_Z = 1.0  # eef height after lifting (a grasped can's bottom then clears the bin walls)
_RELEASE_Z = 0.91  # eef height at which the can is released over the target bin
# The can's quadrant of the target bin spans x 0.10..0.30, y 0.28..0.53 behind 9 cm dividers; its
# centre (0.1975, 0.4025) is at the edge of the Panda's reach with the gripper pointing down, so
# the scripts aim 5 cm inside the quadrant's corner nearest the robot.
_PLACE_SHIFT = np.array([-0.045, -0.07])
_SLIP = 0.05  # object farther than this from the gripper while carried = dropped
_ROT_GAIN = 2.0  # rotation action per radian of orientation error (action 1 = 0.5 rad)


def _obs_layout(task: str) -> dict[str, slice]:
    """Slices of the flat robomimic observation of :func:`spot.envs.make_env` (robosuite 1.5.1)."""
    n_obj = {"lift": 10, "can": 14}[task]
    obj_pos = slice(0, 3) if task == "lift" else slice(7, 10)  # cube_pos | Can_pos
    eef = n_obj + 28  # after object and joint pos/cos/sin/vel (7 each)
    return {
        "object_pos": obj_pos,
        "eef_pos": slice(eef, eef + 3),
        "eef_quat": slice(eef + 3, eef + 7),
        "gripper_qpos": slice(eef + 7, eef + 9),
    }


def _rotation_error(quat: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Axis-angle (world frame) that rotates orientation ``quat`` onto ``ref`` (both xyzw)."""
    v0, w0 = -quat[:3], quat[3]  # conjugate of quat
    v1, w1 = ref[:3], ref[3]
    v = w1 * v0 + w0 * v1 + np.cross(v1, v0)  # ref * conj(quat)
    w = w1 * w0 - v1 @ v0
    if w < 0:  # the short way round
        v, w = -v, -w
    sin = np.linalg.norm(v)
    return np.zeros(3) if sin < 1e-9 else v / sin * 2.0 * np.arctan2(sin, w)


class _Script:
    """One operator's phase machine for one episode (host-side, stateful by nature)."""

    def __init__(
        self, task: str, op: Operator, rng: np.random.Generator, place_xy: np.ndarray | None, obs0: np.ndarray
    ) -> None:
        self.task, self.op, self.rng, self.place_xy = task, op, rng, place_xy
        self.idx = _obs_layout(task)
        self.ref_quat = obs0[self.idx["eef_quat"]].copy()
        self.noise = np.zeros(6)
        self.pause = 0
        self.fumbles = 0
        self._enter("above")

    def _enter(self, phase: str) -> None:
        self.phase, self.count = phase, 0
        self.offset = self.op.jitter * self.rng.standard_normal(3)
        self.anchor: np.ndarray | None = None

    def _target(self, obj: np.ndarray, eef: np.ndarray) -> tuple[np.ndarray, float]:
        """Position target and gripper command of the current phase."""
        task, p = self.task, self.phase
        if p == "above":
            return obj + [0.0, 0.0, _HOVER] + self.offset, -1.0
        if p == "descend":
            return obj + [0.0, 0.0, _GRASP_DZ[task]] + self.offset * [1, 1, 0.3], -1.0
        if p == "reopen":  # missed grasp: open and back up
            return eef + [0.0, 0.0, 0.03], -1.0
        if self.anchor is None:
            self.anchor = eef.copy()
        if p == "close":
            return self.anchor, 1.0
        if p == "lift":
            return np.array([*self.anchor[:2], _LIFT_Z]) + self.offset, 1.0
        if p == "carry":
            return np.array([*self.place_xy, _LIFT_Z]) + self.offset, 1.0
        if p == "lower":
            return np.array([*self.place_xy, _RELEASE_Z]) + self.offset, 1.0
        if p == "release":
            return self.anchor, -1.0
        return np.array([*self.anchor[:2], _LIFT_Z]), -1.0  # "retreat"

    def _advance(self, obj: np.ndarray, eef: np.ndarray, fingers: float, err: float) -> None:
        op, p = self.op, self.phase
        self.count += 1
        # The OSC tracks with a few mm of steady-state error under load: after 30 steps in a phase,
        # close enough counts.
        arrived = err < op.tol or (self.count > 30 and err < 2.5 * op.tol)
        held = np.linalg.norm(obj - eef) < _SLIP
        if p in ("lift", "carry", "lower") and not held:
            self.fumbles += 1
            self._enter("above")
        elif p == "above" and arrived:
            self._enter("descend")
        elif p == "descend" and (arrived or self.count > 60):
            self._enter("close")
        elif p == "close" and self.count >= op.grip_steps:
            # Panda fingers closed on nothing read a gap below ~1 cm.
            self._enter("lift" if fingers > 0.01 else "reopen")
        elif p == "reopen" and self.count >= op.grip_steps:
            self.fumbles += 1
            self._enter("above")
        elif p == "lift" and self.task == "can" and eef[2] > _LIFT_Z - 0.03:
            self._enter("carry")
        elif p == "carry" and np.linalg.norm((self.place_xy + self.offset[:2]) - eef[:2]) < 2 * op.tol:
            self._enter("lower")
        elif p == "lower" and arrived:
            self._enter("release")
        elif p == "release" and self.count >= op.grip_steps:
            self._enter("retreat")
        elif p == "retreat" and arrived:  # released, but not a success (e.g. on a divider)
            self.fumbles += 1
            self._enter("above")

    def act(self, obs: np.ndarray) -> np.ndarray:
        obj, eef = obs[self.idx["object_pos"]], obs[self.idx["eef_pos"]]
        qpos = obs[self.idx["gripper_qpos"]]
        target, grip = self._target(obj, eef)
        self._advance(obj, eef, float(qpos[0] - qpos[1]), float(np.linalg.norm(target - eef)))
        target, grip = self._target(obj, eef)
        op = self.op
        eps = self.rng.standard_normal(6) * np.repeat([op.noise, op.rot_noise], 3)
        self.noise = op.noise_corr * self.noise + np.sqrt(1 - op.noise_corr**2) * eps
        if self.pause == 0 and self.rng.random() < op.pause_prob:
            self.pause = int(self.rng.integers(*op.pause_steps))
        action = np.zeros(7)
        if self.pause > 0:  # hesitation: hold still (hand jitter only)
            self.pause -= 1
            action[:6] = 0.3 * self.noise
        else:
            action[:3] = np.clip(op.gain * (target - eef), -op.speed, op.speed) + self.noise[:3]
            rot_err = _rotation_error(obs[self.idx["eef_quat"]], self.ref_quat)
            action[3:6] = _ROT_GAIN * rot_err + self.noise[3:]
        action[6] = grip
        return np.clip(action, -1.0, 1.0)


def run_episode(env: Any, task: str, op: Operator, rng: np.random.Generator) -> tuple[dict[str, np.ndarray], bool, int]:
    """One attempt of ``op`` in ``env`` (a :func:`spot.envs.make_env` robosuite env).

    Returns the episode in the :func:`raw_from_episodes` layout (ending at the first success,
    or at the horizon with a timeout; ``infos["dense_reward"]`` is robosuite's staged reward of
    each step's next state), whether it succeeded, and its number of fumbles.
    """
    obs, _ = env.reset(seed=int(rng.integers(2**31)))
    place_xy = None
    if task == "can":
        inner = env.unwrapped._env
        place_xy = inner.target_bin_placements[inner.object_to_id["can"], :2] + _PLACE_SHIFT
    script = _Script(task, op, rng, place_xy, obs)
    steps: dict[str, list] = {"observations": [], "actions": [], "rewards": [], "next_observations": []}
    dense = []
    success = truncated = False
    while not (success or truncated or script.fumbles > op.max_fumbles):
        action = script.act(obs)
        next_obs, reward, success, truncated, _ = env.step(action)
        for key, value in zip(steps, (obs, action, reward, next_obs), strict=True):
            steps[key].append(value)
        dense.append(env.unwrapped.staged_reward())
        obs = next_obs
    n = len(steps["rewards"])
    episode = {k: np.asarray(v) for k, v in steps.items()}
    episode["infos"] = {DENSE_REWARD_KEY: np.asarray(dense, dtype=np.float32)}
    episode["terminals"] = np.zeros(n, dtype=bool)
    episode["terminals"][-1] = success
    episode["timeouts"] = np.zeros(n, dtype=bool)
    episode["timeouts"][-1] = not success
    return episode, success, script.fumbles


def operators(kind: str) -> tuple[Operator, ...]:
    """The operators of ``"ph"`` or ``"mh"``."""
    return (PROFICIENT,) if kind == "ph" else MH_OPERATORS


def build(name: str, size: str, seed: int, cache_dir: Path, progress: bool = True) -> tuple[RawDataset, dict[str, Any]]:
    """Build ``lift-ph``, ``lift-mh``, ``can-ph`` or ``can-mh`` with scripted operators.

    Args:
      name: ``"<task>-<ph|mh>"`` with task ``lift`` or ``can``.
      size: ``"tiny"``, ``"small"`` or ``"paper"`` (see :data:`SIZES`).
      seed: seed of everything random in the build.
      cache_dir: unused; this recipe keeps no intermediate artifacts (common recipe signature).
      progress: show a tqdm bar over demonstrations.

    Returns:
      The raw dataset (successful demonstrations only, each ending in a terminal success step;
      per-episode ``episode_operator`` and ``episode_skill`` in ``metadata``) and its card.
    """
    del cache_dir
    task, _, kind = name.partition("-")
    if task not in TASKS or kind not in ("ph", "mh"):
        raise SpotError(
            f"unknown robosuite dataset '{name}'; expected one of "
            f"{', '.join(f'{t}-{k}' for t in TASKS for k in ('ph', 'mh'))}"
        )
    if size not in SIZES:
        raise SpotError(f"unknown size '{size}' for dataset '{name}'; expected one of {', '.join(SIZES)}")
    start = time.perf_counter()
    ops = operators(kind)
    total = SIZES[size][kind]
    per_op = [total // len(ops) + (i < total % len(ops)) for i in range(len(ops))]
    rngs = [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(len(ops))]
    env = make_env(name, seed)  # seeds the global numpy RNG robosuite builds the model with
    episodes, op_names, skills, fumbles = [], [], [], []
    attempts = dict.fromkeys((o.name for o in ops), 0)
    failures = {o.name: {"abandoned": 0, "horizon": 0} for o in ops}
    bar = tqdm(total=total, desc=f"robosuite {name} ({size})", disable=not progress)
    try:
        for op, n, rng in zip(ops, per_op, rngs, strict=True):
            done = 0
            while done < n:
                if attempts[op.name] >= MAX_ATTEMPTS_FACTOR * n:
                    raise SpotError(
                        f"robosuite recipe '{name}': operator {op.name} succeeded {done} "
                        f"times in {attempts[op.name]} attempts; expected {n}"
                    )
                ep, success, fumbled = run_episode(env, task, op, rng)
                attempts[op.name] += 1
                if not success:
                    failures[op.name]["horizon" if len(ep["rewards"]) == ROBOSUITE_HORIZON else "abandoned"] += 1
                    continue
                episodes.append(ep)
                op_names.append(op.name)
                skills.append(op.skill)
                fumbles.append(fumbled)
                done += 1
                bar.update()
    finally:
        bar.close()
        env.close()

    raw = raw_from_episodes(
        episodes, name=f"{name}-{size}", metadata={"episode_operator": op_names, "episode_skill": skills}
    )
    lengths = np.array([len(ep["rewards"]) for ep in episodes])
    dense_returns = np.array([ep["infos"][DENSE_REWARD_KEY].sum() for ep in episodes], dtype=np.float64)
    names, skill_arr, fumbles = np.array(op_names), np.array(skills), np.array(fumbles)
    levels = list(dict.fromkeys(o.skill for o in ops))

    def stats(x: np.ndarray) -> dict[str, float]:
        return {"mean": float(x.mean()), "std": float(x.std()), "min": float(x.min()), "max": float(x.max())}

    card = {
        "recipe": "scripted-robosuite",
        "name": name,
        "env": {"lift": "Lift", "can": "PickPlaceCan"}[task],
        "size": size,
        "seed": seed,
        "robot": "Panda",
        "controller": "composite OSC_POSE (robosuite default for Panda), 20 Hz",
        "horizon": ROBOSUITE_HORIZON,
        "episodes": len(episodes),
        "transitions": len(raw),
        "obs_dim": int(raw.observations.shape[1]),
        "act_dim": int(raw.actions.shape[1]),
        "successful_only": True,
        "recipe_version": RECIPE_VERSION,
        "rewards": "sparse: 1 at the success step (the last of each demo), else 0",
        "infos": {
            DENSE_REWARD_KEY: "robosuite's staged reward (reward_shaping=True) of each step's "
            "next state, in [0, 1]; 1 at success"
        },
        "dense_reward_return": stats(dense_returns),
        "operators": [asdict(o) for o in ops],
        "episodes_per_operator": {o.name: int((names == o.name).sum()) for o in ops},
        "attempts_per_operator": attempts,
        "success_rate_per_operator": {o.name: float((names == o.name).sum() / attempts[o.name]) for o in ops},
        "failures_per_operator": failures,
        "success_rate_per_skill": {
            s: float((skill_arr == s).sum() / sum(attempts[o.name] for o in ops if o.skill == s)) for s in levels
        },
        "success_rate": float(len(episodes) / sum(attempts.values())),
        "episode_length": stats(lengths),
        "episode_length_per_operator": {o.name: float(lengths[names == o.name].mean()) for o in ops},
        "episode_length_per_skill": {s: float(lengths[skill_arr == s].mean()) for s in levels},
        "fumbles_per_demo_per_operator": {o.name: float(fumbles[names == o.name].mean()) for o in ops},
        "build_time_s": round(time.perf_counter() - start, 2),
        "versions": {"spot": spot.__version__, **{p: version(p) for p in ("robosuite", "mujoco", "numpy")}},
    }
    return raw, card
