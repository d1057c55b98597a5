"""Checkpoint selection for Chae's DQN (``agent.chae.select``): the validation draw a checkpoint is scored on during
training, the choice of ``best.pt``, and the rescoring of the kept checkpoints on a draw of their own."""

from __future__ import annotations

from types import SimpleNamespace

from ...artifacts import AgentId
from ...checkpoints import read_checkpoint
from ...common import StageError
from .evaluate import bank, run_policy
from .observe import family_env
from .policies import policy_from_state
from .report import summarise


def validated_path(run_dir, episode: int):
    """Where ``agent.chae.select.keep`` keeps the checkpoint validated after ``episode`` episodes."""
    return run_dir / "validated" / f"episode{int(episode):05d}.pt"


class Validation:
    """``agent.chae.select``'s validation draw (``bank`` on its own seed), driven greedily by a checkpoint; ``sel``: the
    typed ``agent.chae.select``."""

    def __init__(self, sel, env):
        self.ttcs = sel.ttcs
        self.entries = bank(SimpleNamespace(seed=sel.seed, trials=sel.trials, ttcs=self.ttcs))
        self.env = env

    def score(self, policy, episode: int) -> dict:
        """Bump rate per TTC (%), the worst of them, and Scenario 2's unnecessary stops (%)."""
        rows = run_policy(self.env, policy, self.entries, leave=False)
        s = summarise(rows, self.ttcs)["policies"][policy.name]
        bumps = {str(t): rate for t, rate in s["bump_rate"].items()}
        return {
            "episode": int(episode),
            "bump_rate": bumps,
            "max_bump_rate": max(bumps.values()),
            "unnecessary_stop_rate": s["unnecessary_stop_rate"],
        }


def selected(scores: list[dict], max_bump: float) -> dict | None:
    """The validation score ``best.pt`` holds: among the checkpoints bumping in at most ``max_bump`` % at every
    TTC, the one with the fewest unnecessary stops; if none, the one bumping least (fewer stops breaking ties).
    The earliest wins a tie, so a later checkpoint replaces it only by doing strictly better."""

    def key(s):
        safe = s["max_bump_rate"] <= max_bump
        return (0, s["unnecessary_stop_rate"]) if safe else (1, s["max_bump_rate"], s["unnecessary_stop_rate"])

    return min(scores, key=key) if scores else None


def rescore_shortlist(scores: list[dict], k: int, max_bump: float, max_stops: float, ttc: float) -> list[dict]:
    """Training's validation scores inside both bars (bumps <= ``max_bump`` % at every TTC, needless stops <=
    ``max_stops`` %), the ``k`` bumping least at ``ttc`` (then fewer stops, then later checkpoints first)."""
    inside = [s for s in scores if s["max_bump_rate"] <= max_bump and s["unnecessary_stop_rate"] <= max_stops]
    return sorted(inside, key=lambda s: (s["bump_rate"][str(ttc)], s["unnecessary_stop_rate"], -s["episode"]))[:k]


def room(score: dict, max_bump: float, max_stops: float) -> float:
    """How close a checkpoint comes to the bars: max(bumps / max_bump, stops / max_stops); below 1 is inside both."""
    return max(score["bump_rate"] / max_bump, score["unnecessary_stop_rate"] / max_stops)


def rescore_choice(rescored: list[dict], max_bump: float, max_stops: float) -> dict | None:
    """The rescored checkpoint with the most room under the bars, the later on a tie."""
    key = lambda s: (room(s, max_bump, max_stops), -s["episode"])  # noqa: E731
    return min(rescored, key=key) if rescored else None


def member_found(rescored: dict | None, sel) -> bool:
    """Whether the rescoring chose a checkpoint inside both bars on its draw (``agent.chae.select.extend`` stops);
    ``sel``: the typed ``agent.chae.select``."""
    chosen = (rescored or {}).get("chosen")
    return chosen is not None and room(chosen, sel.max_bump, sel.max_stops) <= 1.0


def rescore_kept(cfg, agent_id: AgentId, run_dir, scores: list[dict], sel=None, cache: dict | None = None) -> dict:
    """``agent.chae.select.rescore``: the shortlisted kept checkpoints of the run in ``run_dir`` on the rescoring draw
    (``sel``: the run's select settings, with float bars and TTCs and int counts, default the typed
    ``agent.chae.select`` of ``cfg``) at ``sel.rescore_ttcs`` (None: ``ttcs[0]``).
    Returns the draw, every shortlisted checkpoint's bumps per TTC, their highest and the needless stops, and the
    chosen one (None: no candidate). ``cache`` (str(episode) -> entry) holds checkpoints already rescored on this
    draw, and takes the new ones."""

    from ...config import validate

    sel = sel or validate(cfg).agent.chae.select
    corner, max_bump, max_stops = sel.ttcs[0], sel.max_bump, sel.max_stops
    ttcs = getattr(sel, "rescore_ttcs", None) or [corner]
    entries = bank(SimpleNamespace(seed=sel.rescore_seed, trials=sel.rescore_trials, ttcs=ttcs))
    env, rescored = None, []
    cache = {} if cache is None else cache
    for score in rescore_shortlist(scores, sel.rescore, max_bump, max_stops, corner):
        if str(score["episode"]) in cache:
            rescored.append(cache[str(score["episode"])])
            continue
        path = validated_path(run_dir, score["episode"])
        if not path.exists():
            raise StageError(f"{path} is missing: rescoring reads the checkpoints agent.chae.select.keep=true keeps")
        policy = policy_from_state(cfg, agent_id, read_checkpoint(path))
        env = env or family_env(cfg, camera=policy.see.camera, end_on_bump=False)
        s = summarise(run_policy(env, policy, entries, leave=False), ttcs)["policies"][policy.name]
        cache[str(score["episode"])] = {
            "episode": score["episode"],
            "bump_rate": max(s["bump_rate"].values()),  # the highest over the TTCs: what room() weighs
            "bump_rates": {str(t): s["bump_rate"][t] for t in ttcs},
            "unnecessary_stop_rate": s["unnecessary_stop_rate"],
        }
        rescored.append(cache[str(score["episode"])])
    if env is not None:
        env.close()
    chosen = rescore_choice(rescored, max_bump, max_stops)
    return {
        "seed": sel.rescore_seed,
        "trials": sel.rescore_trials,
        "ttc": corner,
        "ttcs": ttcs,
        "rescored": rescored,
        "chosen": chosen,
    }
