"""Write a synthetic dataset in the D4RL hdf5 layout, for memory and speed benchmarks at D4RL size.

Observations are a bounded random walk (Hopper's 11 dims by default), actions uniform in [-1, 1],
the reward a noisy function of the observation, episodes of ``--episode-length`` steps ending in a
timeout. The file name decides the evaluation env (``hopper-...-v2.hdf5`` evaluates in Hopper).
Not a dataset to learn from: a stand-in with the real sizes and layout.

    python scripts/make_synthetic_d4rl.py /tmp/big/hopper-medium-replay-v2.hdf5 --transitions 1000000
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from spot.data import formats
from spot.data.dataset import RawDataset


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("path", type=Path)
    parser.add_argument("--transitions", type=int, default=1_000_000)
    parser.add_argument("--episode-length", type=int, default=1000)
    parser.add_argument("--obs-dim", type=int, default=11)
    parser.add_argument("--act-dim", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    n, rng = args.transitions, np.random.default_rng(args.seed)
    obs = np.cumsum(rng.normal(scale=0.05, size=(n, args.obs_dim)).astype(np.float32), axis=0) % 3.0
    timeouts = np.zeros(n, bool)
    timeouts[args.episode_length - 1 :: args.episode_length] = True
    raw = RawDataset(
        observations=obs,
        actions=rng.uniform(-1, 1, (n, args.act_dim)).astype(np.float32),
        rewards=(obs[:, min(5, args.obs_dim - 1)] + 0.1 * rng.normal(size=n)).astype(np.float32),
        terminals=np.zeros(n, bool),
        timeouts=timeouts,
        name=args.path.stem,
    )
    args.path.parent.mkdir(parents=True, exist_ok=True)
    formats.write_d4rl_hdf5(
        raw,
        args.path,
        {
            "name": args.path.stem,
            "source": "file",
            "note": "synthetic, for benchmarks (scripts/make_synthetic_d4rl.py)",
        },
    )
    print(f"wrote {n} transitions to {args.path}")


if __name__ == "__main__":
    main()
