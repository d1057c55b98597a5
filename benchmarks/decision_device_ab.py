"""50,000 batch-1 DDPG decisions on the CPU, for timing the device setting's moves with benchmarks/ab.py.

    python -m benchmarks.ab -n 5 --a ".venv/bin/python -m benchmarks.decision_device_ab device" \
        --b ".venv/bin/python -m benchmarks.decision_device_ab plain"

``plain`` decides as DDPG.act did before the device setting (no move to the device and back); ``device`` calls
DDPG.act as it is (benchmarks/RESULTS.md).
"""

import sys

import numpy as np
import torch

from worldmodel.models.ddpg import DDPG, DDPGConfig

torch.set_num_threads(1)
agent = DDPG(257, 2, DDPGConfig(), seed=0)
obs = np.random.default_rng(0).normal(size=257).astype(np.float32)
if sys.argv[1] == "plain":

    def act(o):
        with torch.inference_mode():
            a = agent.actor(torch.as_tensor(o, dtype=torch.float32)).numpy()
        return np.clip(a, -1.0, 1.0).astype(np.float32, copy=False)
else:

    def act(o):
        return agent.act(o, explore=False)


for _ in range(50_000):
    act(obs)
