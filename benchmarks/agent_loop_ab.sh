#!/bin/bash
# One smoke R1 agent of 3,000 steps (checkpoints every 1,000), trained by the code in checkout $1 on the smoke world
# model under $2 (an experiment `t` built by collect, train_vae and train_rnn at scale=smoke), in a fresh run folder.
# For timing the DDPG loop of two checkouts against each other with `python -m benchmarks.ab` (benchmarks/RESULTS.md).
set -u
venv="$(cd "$(dirname "$0")/.." && pwd)/.venv"
cd "$1"; d=$(mktemp -d); cp -r "$2/runs" "$d/runs"
"$venv/bin/python" -m worldmodel.train_agent paths.data_root="$2/data" paths.runs_root="$d/runs" experiment=t \
  scale=smoke threads=1 reward=r1 agent.total_steps=3000 agent.checkpoint_every=1000 >/dev/null 2>&1
rc=$?; rm -rf "$d"; exit $rc
