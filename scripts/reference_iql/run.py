"""Train the reference IQL on a spot locomotion file and evaluate it as spot does (a cross-check).

usage: run.py REF_DIR FILE.hdf5 SEED STEPS OUT.csv [EVAL_EVERY]

REF_DIR holds ikostrikov/implicit_q_learning (scripts/reference_iql/setup.sh). The training is
the reference's train_offline.py on D4RL, with the data read from FILE (a spot hdf5 file with
observations, actions, rewards, terminals, next_observations) instead of d4rl: actions clipped to
1 - 1e-5, episodes split where the next row does not continue the last one or at a terminal,
rewards divided by the range of episode returns and multiplied by 1000, the mujoco config
(expectile 0.7, temperature 3, 256x256, lr 3e-4, tau 0.005, discount 0.99, no dropout), the
actor's cosine schedule over STEPS, batches of 256 drawn with numpy. Evaluation: gymnasium
Hopper-v5 or Walker2d-v5 (from the file's name; Walker2d in the `walker2d.xml` model that spot's
data were recorded in, as spot.envs makes it) with the deterministic action (temperature 0),
10 episodes every EVAL_EVERY (default 10000) updates and 30 after the last, scored with D4RL's
reference returns. OUT gets one row per evaluation: step, score, mean episode length, episodes,
elapsed seconds.
"""

import os
import sys
import time

import flax
import h5py
import numpy as np

REF = {"hopper": (-20.272305, 3234.3), "walker2d": (1.629008, 4592.3)}  # D4RL's random / expert returns


def load(path):
    with h5py.File(path, "r") as f:
        d = {k: f[k][:] for k in ("observations", "actions", "rewards", "terminals", "next_observations")}
    obs = d["observations"].astype(np.float32)
    nxt = d["next_observations"].astype(np.float32)
    act = np.clip(d["actions"], -1 + 1e-5, 1 - 1e-5).astype(np.float32)
    rew = d["rewards"].astype(np.float32)
    masks = 1.0 - d["terminals"].astype(np.float32)
    dones = np.zeros_like(rew)
    dones[:-1] = (np.linalg.norm(obs[1:] - nxt[:-1], axis=1) > 1e-6) | (d["terminals"][:-1] == 1)
    dones[-1] = 1
    ends = np.flatnonzero(dones)
    returns = np.add.reduceat(rew, np.r_[0, ends[:-1] + 1])
    rew = rew / (returns.max() - returns.min()) * 1000.0
    print(f"{path}: {len(rew)} rows, {len(ends)} episodes, returns {returns.min():.1f}..{returns.max():.1f}")
    return obs, act, rew, masks, nxt


def make_env(name):
    import gymnasium as gym

    if name == "hopper":
        return gym.make("Hopper-v5")
    xml = os.path.join(os.path.dirname(gym.__file__), "envs", "mujoco", "assets", "walker2d.xml")
    return gym.make("Walker2d-v5", xml_file=xml)


def evaluate(agent, env, episodes, seed, ref):
    returns, lengths = [], []
    for e in range(episodes):
        o, _ = env.reset(seed=seed + e)
        done, total, length = False, 0.0, 0
        while not done:
            a = agent.sample_actions(o.astype(np.float32), temperature=0.0)
            o, r, term, trunc, _ = env.step(a)
            total, length, done = total + r, length + 1, term or trunc
        returns.append(total)
        lengths.append(length)
    return 100 * (np.mean(returns) - ref[0]) / (ref[1] - ref[0]), float(np.mean(lengths))


def main(ref_dir, path, seed, steps, out, every=10000):
    name = os.path.basename(path).split("-")[0]
    if name not in REF:
        sys.exit(f"{path}: expected a hopper-* or walker2d-* file (its name says which env evaluates it)")
    sys.path.insert(0, ref_dir)
    flax.config.update("flax_return_frozendict", True)  # the reference unpacks FrozenDict.pop
    from common import Batch
    from learner import Learner

    obs, act, rew, masks, nxt = load(path)
    np.random.seed(seed)
    agent = Learner(
        seed,
        obs[:1],
        act[:1],
        max_steps=steps,
        actor_lr=3e-4,
        value_lr=3e-4,
        critic_lr=3e-4,
        hidden_dims=(256, 256),
        discount=0.99,
        expectile=0.7,
        temperature=3.0,
        dropout_rate=None,
        tau=0.005,
    )
    env, t0 = make_env(name), time.time()
    with open(out, "w") as fh:
        fh.write("step,score,length,episodes,elapsed_s\n")
        for i in range(1, steps + 1):
            idx = np.random.randint(len(rew), size=256)
            agent.update(Batch(obs[idx], act[idx], rew[idx], masks[idx], nxt[idx]))
            if i % every == 0 or i == steps:
                n = 30 if i == steps else 10
                score, length = evaluate(agent, env, n, 10_000 * seed + i, REF[name])
                fh.write(f"{i},{score:.2f},{length:.1f},{n},{time.time() - t0:.0f}\n")
                fh.flush()
                print(i, round(score, 2), length, round(time.time() - t0), flush=True)


if __name__ == "__main__":
    a = sys.argv[1:]
    if len(a) not in (5, 6):
        sys.exit(__doc__)
    main(a[0], a[1], int(a[2]), int(a[3]), a[4], *(int(x) for x in a[5:]))
