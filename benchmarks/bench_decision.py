"""Decision latency: 64x64 class map -> action (VAE encode + one LSTM step + actor), one torch thread, batch 1.

    python -m benchmarks.bench_decision [--decisions 2000] [--warmup 200] [--tiny]

Times exactly what the evaluation loop calls per frame, ``LearnedPolicy.act(obs, info)`` from
``worldmodel.agent_obs`` (the ``FastDecision`` + ``FastActor`` path of ``worldmodel.models.fast_decision``),
wrapping untrained models of the real sizes:
``SegVAE`` (latent 128), ``WorldRNN`` (LSTM 512, MDN head with 5 Gaussians) and the DDPG ``Actor`` (400-300) on
the 256-d input [z_t, zhat_{t+1}]. Weights do not change the cost of a dense forward pass, so untrained models
time the same as trained ones.

The inputs are real frames rendered by the simulator (``UrbanCollisionEnv(camera=True)``, scenarios from
``sample_scenario(default_rng(k))``, action [0, 0]); they are rendered before timing and fed in order, with the
recurrent state reset at each new scenario (outside the timed call). Also reported:

* ``parts``: each stage of the same decision loop, timed inline (so each runs with the caches the previous
  stages left, as inside ``act``; isolated micro-benchmarks of one stage in a tight loop look faster);
* ``reference``: the modules' own path (``SegVAE.encode`` -> ``WorldRNN.step`` -> ``predict`` -> ``Actor``),
  which is what ``act`` ran before the fast path, with oneDNN off and on, measured in the same run and so under
  the same machine load;
* the top 15 operators by self CPU time from ``torch.profiler`` and the top 15 Python functions by own time from
  ``cProfile``, so a reader can see what bounds the latency.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import os
import pstats
import sys
import time
from pathlib import Path

import numpy as np

from .common import write

TARGET_P50_MS = 1.0
PROJECT_ROOT = Path(__file__).resolve().parent.parent


class _Hold:
    """Keeps speed and lane: frames of the scenario as it unfolds, without any manoeuvre."""

    name = "hold"

    def reset(self, seed=None) -> None:
        pass

    def act(self, obs, info) -> np.ndarray:
        return np.zeros(2, np.float32)


def render_frames(scenarios: int, steps: int) -> list[list[tuple[dict, dict]]]:
    """Per scenario, the (obs, info) pairs an agent would see: the reset frame, then frames under [0, 0]."""
    from envs import UrbanCollisionEnv, sample_scenario
    from envs.rollout import rollout

    env = UrbanCollisionEnv(camera=True)
    episodes = []
    for k in range(scenarios):
        frames = []

        def keep(obs, info, frames=frames):
            frames.append(({"seg": obs["seg"].copy(), "speed": obs["speed"].copy()}, info))

        rollout(
            env,
            _Hold(),
            sample_scenario(np.random.default_rng(k)),
            on_reset=keep,
            on_step=lambda obs, action, reward, info, keep=keep: keep(obs, info),
            max_steps=steps - 1,
        )
        episodes.append(frames)
    env.close()
    return episodes


def build_policy(latent: int = 128, hidden: int = 512, gaussians: int = 5, actor_hidden=(400, 300)):
    import torch

    from worldmodel.agent_obs import LearnedPolicy, WorldModelEncoder
    from worldmodel.models.ddpg import Actor
    from worldmodel.models.vae import SegVAE

    try:
        from worldmodel.models.rnn import WorldRNN
    except ImportError as err:
        raise SystemExit(
            f"bench_decision needs worldmodel.models.rnn.WorldRNN, which is not importable: {err}"
        ) from err

    torch.manual_seed(0)
    vae = SegVAE(num_classes=13, latent_dim=latent)
    rnn = WorldRNN(latent_dim=latent, action_dim=2, hidden=hidden, head="mdn", gaussians=gaussians)
    encoder = WorldModelEncoder(vae, rnn, use_speed=False)
    actor = Actor(obs_dim=encoder.dim, act_dim=2, hidden=tuple(actor_hidden))
    policy = LearnedPolicy("bench", encoder, actor)
    if encoder.path != "fast":
        raise SystemExit(
            "the fast decision path failed its self-test on this torch build (see the warning above); "
            "this benchmark measures that path"
        )
    sizes = {
        "decision_path": encoder.path,
        "latent_dim": latent,
        "lstm_hidden": hidden,
        "mdn_gaussians": gaussians,
        "actor_hidden": list(actor_hidden),
        "obs_dim": encoder.dim,
        "parameters": {
            "vae_encoder": _params(vae, ("enc", "fc_mu", "fc_logvar")),
            "rnn": _params(rnn),
            "actor": _params(actor),
        },
        "weights_read_per_decision_mb": round(_weight_bytes(policy) / 2**20, 2),
    }
    return policy, sizes


def _weight_bytes(policy) -> int:
    """Bytes of weights one decision streams through (what bounds it once the arithmetic is cheap)."""
    f = policy.encoder.decision
    tensors = [f.enc1_table, f.fc_mu_wt, f.fc_mu_b, f.lstm_wt, f.lstm_b, f.head_wt, f.head_b]
    tensors += [t for layer in policy.decide.layers for t in layer[:2]]
    # oneDNN's packed copies are opaque tensors; they hold the same numbers as the convolutions' parameters
    tensors += [t for conv in (f.vae.enc2, f.vae.enc3, f.vae.enc4) for t in (conv.weight, conv.bias)]
    return sum(t.numel() * t.element_size() for t in tensors)


def _params(module, prefixes=None) -> int:
    return int(
        sum(p.numel() for n, p in module.named_parameters() if prefixes is None or n.startswith(tuple(prefixes)))
    )


def _stats_ms(ns: np.ndarray) -> dict:
    ms = ns / 1e6
    return {
        "n": int(ms.size),
        "p50_ms": float(np.median(ms)),
        "p95_ms": float(np.percentile(ms, 95)),
        "p99_ms": float(np.percentile(ms, 99)),
        "mean_ms": float(ms.mean()),
        "min_ms": float(ms.min()),
        "max_ms": float(ms.max()),
    }


def _feed(episodes):
    """Endless (new_episode, obs, info) over the rendered episodes, in order."""
    while True:
        for frames in episodes:
            for j, (obs, info) in enumerate(frames):
                yield j == 0, obs, info


def time_decisions(policy, episodes, n: int, warmup: int) -> np.ndarray:
    feed = _feed(episodes)
    times = np.empty(n, np.int64)
    clock = time.perf_counter_ns
    for i in range(-warmup, n):
        new, obs, info = next(feed)
        if new:
            policy.reset()
        t0 = clock()
        policy.act(obs, info)
        dt = clock() - t0
        if i >= 0:
            times[i] = dt
    return times


def time_parts(policy, episodes, n: int, warmup: int) -> dict:
    """Each stage of ``policy.act``, timed inline in the same order on the same frames and states.

    Mirrors ``FastDecision.encode`` + ``FastActor`` stage by stage; the result is checked against ``act``.
    """
    import torch

    fast, actor = policy.encoder.decision, policy.decide
    clock = time.perf_counter_ns
    keys = ("input_check", "vae_encode", "lstm_step", "mdn_predict", "actor", "decision_total")
    out = {k: np.empty(n, np.int64) for k in keys}
    feed = _feed(episodes)
    with torch.inference_mode():
        for i in range(-warmup, n):
            new, obs, _ = next(feed)
            if new:
                fast.reset()
            t0 = clock()
            fast._load(obs["seg"], None)
            t1 = clock()
            fast._encode_mu()
            t2 = clock()
            fast._lstm_step()
            t3 = clock()
            fast._predict()
            t4 = clock()
            action = actor(fast.out)[0].numpy().astype(np.float32)
            t5 = clock()
            fast.note_action(action)
            if i >= 0:
                for k, dt in zip(keys, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4, t5 - t0)):
                    out[k][i] = dt
    _check_parts_match_act(policy, episodes)
    return {k: _stats_ms(v) for k, v in out.items()}


def _check_parts_match_act(policy, episodes) -> None:
    """The staged loop above must compute what ``act`` computes (guards against the mirror drifting)."""
    fast = policy.encoder.decision
    frames = episodes[0][:5]
    policy.reset()
    want = [policy.act(obs, None) for obs, _ in frames]
    fast.reset()
    for (obs, _), w in zip(frames, want):
        fast._load(obs["seg"], None)
        fast._encode_mu()
        fast._lstm_step()
        fast._predict()
        got = policy.decide(fast.out)[0].numpy().copy()
        fast.note_action(got)
        if not np.array_equal(got, w):
            raise AssertionError("bench_decision's staged loop no longer matches LearnedPolicy.act")


def time_reference(policy, episodes, n: int, warmup: int) -> dict:
    """The modules' own batch-1 path (the pre-``FastDecision`` ``act``), with oneDNN off and on."""
    import torch

    enc = policy.encoder
    vae, rnn, actor = enc.vae, enc.rnn, policy.actor
    clock = time.perf_counter_ns
    keys = ("vae_encode", "lstm_step", "mdn_predict", "actor", "decision_total")
    result = {}
    for onednn in (False, True):
        out = {k: np.empty(n, np.int64) for k in keys}
        feed = _feed(episodes)
        with torch.inference_mode(), torch.backends.mkldnn.flags(enabled=onednn):
            for i in range(-warmup, n):
                new, obs, _ = next(feed)
                if new:
                    state, a = rnn.initial_state(1), torch.zeros(1, 2)
                t0 = clock()
                z, _ = vae.encode(torch.from_numpy(np.ascontiguousarray(obs["seg"])).unsqueeze(0))
                t1 = clock()
                o, state = rnn.step(z, a, state)
                t2 = clock()
                zhat = rnn.predict(o)
                t3 = clock()
                a = actor(torch.cat([z, zhat], dim=1))
                a[0].numpy().astype(np.float32)  # act() returns a numpy copy
                t4 = clock()
                if i >= 0:
                    for k, dt in zip(keys, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t4 - t0)):
                        out[k][i] = dt
        result["onednn_on" if onednn else "onednn_off"] = {k: _stats_ms(v) for k, v in out.items()}
    return result


def torch_profile(policy, episodes, n: int, rows: int = 15) -> str:
    from torch.profiler import ProfilerActivity, profile

    feed = _feed(episodes)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(n):
            new, obs, info = next(feed)
            if new:
                policy.reset()
            policy.act(obs, info)
    return prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=rows)


def python_profile(policy, episodes, n: int, rows: int = 15) -> str:
    feed = _feed(episodes)
    items = [next(feed) for _ in range(n)]
    prof = cProfile.Profile()
    prof.enable()
    for new, obs, info in items:
        if new:
            policy.reset()
        policy.act(obs, info)
    prof.disable()
    buf = io.StringIO()
    pstats.Stats(prof, stream=buf).sort_stats("tottime").print_stats(rows)
    text = buf.getvalue().strip().replace(sys.prefix + "/", "").replace(str(PROJECT_ROOT) + "/", "")
    return "\n".join(line.rstrip() for line in text.splitlines())


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--decisions", type=int, default=2000)
    ap.add_argument("--warmup", type=int, default=200)
    ap.add_argument("--scenarios", type=int, default=10, help="scenarios rendered for input frames")
    ap.add_argument("--steps", type=int, default=40, help="frames rendered per scenario (at most)")
    ap.add_argument("--profile-decisions", type=int, default=300)
    ap.add_argument(
        "--tiny", action="store_true", help="seconds-long check that the benchmark works (not a measurement)"
    )
    args = ap.parse_args(argv)
    if args.tiny:
        args.decisions, args.warmup, args.scenarios, args.steps, args.profile_decisions = 50, 10, 2, 10, 20

    import warnings

    import torch

    # time_reference toggles oneDNN, which makes torch mention Intel-GPU TF32 support (irrelevant on CPU)
    warnings.filterwarnings("ignore", message="TF32 acceleration on top of oneDNN")
    torch.set_num_threads(1)
    try:
        torch.set_num_interop_threads(1)
    except RuntimeError:  # already set (e.g. run after another benchmark in the same process)
        pass

    load = os.getloadavg()
    episodes = render_frames(args.scenarios, args.steps)
    policy, sizes = build_policy()
    frames = sum(len(f) for f in episodes)
    print(
        f"[decision] {frames} rendered frames from {len(episodes)} scenarios; timing {args.decisions} decisions "
        f"after {args.warmup} warm-up, torch threads = {torch.get_num_threads()}"
    )

    total = _stats_ms(time_decisions(policy, episodes, args.decisions, args.warmup))
    parts = time_parts(policy, episodes, args.decisions, args.warmup)
    reference = time_reference(policy, episodes, args.decisions, args.warmup)
    load_end = os.getloadavg()
    prof_torch = torch_profile(policy, episodes, args.profile_decisions)
    prof_py = python_profile(policy, episodes, args.profile_decisions)
    print(
        f"[decision] p50 {total['p50_ms']:.3f} ms, p95 {total['p95_ms']:.3f} ms, mean {total['mean_ms']:.3f} ms "
        f"(target p50 <= {TARGET_P50_MS} ms); parts p50: "
        + ", ".join(f"{k} {v['p50_ms']:.3f}" for k, v in parts.items())
    )
    print(
        "[decision] module path (before FastDecision) p50: "
        + ", ".join(f"{name} {r['decision_total']['p50_ms']:.3f} ms" for name, r in reference.items())
    )

    result = {
        "tiny": bool(args.tiny),
        "params": {
            "decisions": args.decisions,
            "warmup": args.warmup,
            "scenarios": args.scenarios,
            "steps_per_scenario": args.steps,
            "distinct_frames": frames,
            "profile_decisions": args.profile_decisions,
            "batch": 1,
        },
        "command": " ".join(["python -m benchmarks.bench_decision", *(argv if argv is not None else sys.argv[1:])]),
        "loadavg_at_start": [round(x, 2) for x in load],
        "loadavg_at_end": [round(x, 2) for x in load_end],
        "torch_threads": torch.get_num_threads(),
        "torch_interop_threads": torch.get_num_interop_threads(),
        "models": sizes,
        "target_p50_ms": TARGET_P50_MS,
        "decision": total,
        "parts": parts,
        "reference": reference,
        "profile_torch_self_cpu_top15": prof_torch,
        "profile_python_tottime_top15": prof_py,
    }
    print(write("decision", result))
    return result


if __name__ == "__main__":
    main()
