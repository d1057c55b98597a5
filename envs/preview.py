"""Write a GIF (or a PNG strip) of one episode: segmentation view and bird's-eye view side by side.

python -m envs.preview --out preview.gif --hazard pedestrian --ttc 1.0 --speed 20 --policy braking
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from .env import UrbanCollisionEnv
from .policies import NoisyAutopilot, StraightLineBraking
from .rollout import rollout
from .scenario import ScenarioSpec


class _Hold:
    name = "hold"

    def reset(self, seed=None):
        pass

    def act(self, obs, info):
        return np.zeros(2, dtype=np.float32)


POLICIES = {"braking": StraightLineBraking, "autopilot": NoisyAutopilot, "hold": _Hold}


def record(
    spec: ScenarioSpec, policy_name: str = "braking", max_steps: int | None = None, road_user_cover: bool = False
) -> tuple[list, dict]:
    env = UrbanCollisionEnv(camera=True, render_mode="rgb_array", road_user_cover=road_user_cover)
    frames = []
    episode = rollout(
        env,
        POLICIES[policy_name](),
        spec,
        on_reset=lambda obs, info: frames.append(env.render()),
        on_step=lambda obs, action, reward, info: frames.append(env.render()),
        max_steps=max_steps,
    )
    env.close()
    return frames, episode.info.get("outcome", {})


def save(frames: list, out: Path, fps: int = 15) -> None:
    from PIL import Image  # only the preview needs pillow

    out.parent.mkdir(parents=True, exist_ok=True)
    if out.suffix.lower() == ".png":
        picks = frames[:: max(1, len(frames) // 6)][:6]
        Image.fromarray(np.concatenate(picks, axis=0)).save(out)
    else:
        images = [Image.fromarray(f) for f in frames]
        images[0].save(out, save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("runs/preview/episode.gif"))
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--hazard", choices=["pedestrian", "car", "both", "none"], default="pedestrian")
    ap.add_argument("--ttc", type=float, default=1.0)
    ap.add_argument("--speed", type=float, default=15.0)
    ap.add_argument("--cars", type=int, default=6)
    ap.add_argument("--pedestrians", type=int, default=6)
    ap.add_argument("--policy", choices=sorted(POLICIES), default="braking")
    ap.add_argument(
        "--view", choices=["paper64", "cover64"], default="paper64", help="how the frame draws road users (conf/view/)"
    )
    args = ap.parse_args(argv)
    spec = ScenarioSpec(
        seed=args.seed,
        ttc=args.ttc,
        ego_speed=args.speed,
        n_cars=args.cars,
        n_pedestrians=args.pedestrians,
        p_pedestrian=1.0 if args.hazard in ("pedestrian", "both") else 0.0,
        p_car=1.0 if args.hazard in ("car", "both") else 0.0,
    )
    frames, outcome = record(spec, args.policy, road_user_cover=args.view == "cover64")
    save(frames, args.out)
    print(f"wrote {args.out} ({len(frames)} frames); outcome: {outcome}")


if __name__ == "__main__":
    main()
