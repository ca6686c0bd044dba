#!/usr/bin/env bash
# scripts/reference_iql/setup.sh DIR: a cross-check environment for the reference IQL
# (github.com/ikostrikov/implicit_q_learning, the IQL that the PT repo and SGPbrl vendor), outside
# spot. DIR gets a venv (DIR/venv) and the reference's files at a pinned commit (DIR/ref), with the
# two changes that newer jax needs: jax.tree_multimap -> jax.tree_util.tree_map (learner.py) and
# the unused 'distribution' entry dropped from static_argnames (policy.py). tensorflow-probability's
# jax substrate does not import under jax 0.10, hence the older jax/flax pins here.
# Then: DIR/venv/bin/python scripts/reference_iql/run.py DIR/ref FILE.hdf5 SEED STEPS OUT.csv
set -euo pipefail
dir=${1:?usage: setup.sh DIR}
commit=09d700248117881a75cb21f0adb95c6c8a694cb2
mkdir -p "$dir"
python3 -m venv "$dir/venv"
"$dir/venv/bin/pip" install -q -U pip
"$dir/venv/bin/pip" install -q "jax==0.4.30" "jaxlib==0.4.30" "flax==0.8.5" "optax==0.2.3" \
  "tensorflow-probability==0.24.0" "numpy<2" "gymnasium[mujoco]==1.4.0" "mujoco==3.3.0" h5py
if [ ! -d "$dir/ref" ]; then
  git clone -q https://github.com/ikostrikov/implicit_q_learning "$dir/ref"
fi
git -C "$dir/ref" checkout -q "$commit"
sed -i 's/jax\.tree_multimap/jax.tree_util.tree_map/' "$dir/ref/learner.py"
sed -i "s/static_argnames=('actor_def', 'distribution')/static_argnames=('actor_def',)/" "$dir/ref/policy.py"
echo "reference IQL at $commit in $dir/ref; python: $dir/venv/bin/python"
