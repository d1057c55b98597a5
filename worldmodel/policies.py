"""Which policy a name denotes, for every bank that runs them (``evaluate``, ``ncap``): the scripted ones
(``braking``, ``oracle``, ``exact_chooser``) and every trained agent's key, each acting as it was trained."""

from __future__ import annotations

from . import artifacts, loading, registry
from .artifacts import AgentId
from .config import oracle_settings
from .report import MODEL_COLUMNS

NO_MODELS = dict.fromkeys(MODEL_COLUMNS, "")


def make_oracle(cfg, brake_first: int | None = None, brake_until_pixels: int | None = None):
    """The privileged planner of ``evaluate.oracle``; with ``brake_first`` k, the perception ceiling that brakes
    straight for its first k frames, named ``oracle_brakek``; with ``brake_until_pixels`` k, the camera's cap that
    brakes straight until the hazard covers k pixels of the frame, named ``oracle_pixelsk`` (it needs the camera)."""
    from envs.planner import PrivilegedPlanner

    settings = oracle_settings(cfg)
    if brake_until_pixels is not None:
        if int(brake_until_pixels) < 1:
            raise ValueError(f"oracle_pixels{brake_until_pixels}: the hazard must cover at least 1 pixel")
        return PrivilegedPlanner.from_settings(**{**settings, "brake_until_pixels": int(brake_until_pixels)})
    if brake_first is None:
        return PrivilegedPlanner.from_settings(**settings)
    planner = PrivilegedPlanner.from_settings(**{**settings, "brake_first": int(brake_first)})
    planner.name = f"oracle_brake{int(brake_first)}"
    return planner


EXACT_CHOOSER = "exact_chooser"  # the chooser's decision rule on exact costs: the ceiling of agent.learner=chooser


def make_exact_chooser(cfg):
    """The chooser (``agent.chooser``'s candidates and window) acting on the true costs, read from the simulator."""
    from envs.chooser import ExactCosts, ManoeuvreChooser, decide_steps_for

    from .chooser import cfg_chooser

    c, step_s = cfg_chooser(cfg), cfg.env.step_s
    candidates = c.candidates(step_s)
    return ManoeuvreChooser(
        candidates, ExactCosts(candidates), decide_steps_for(c.decide_s, step_s), c.margin, name=EXACT_CHOOSER
    )


def policy_for(cfg, name: str):
    """(policy, training seed, model hashes) for a scripted policy's name or an agent's key."""
    from envs import StraightLineBraking

    if name == "braking":
        return StraightLineBraking(), 0, NO_MODELS
    if name == "oracle":
        return make_oracle(cfg), 0, NO_MODELS
    if name.startswith("oracle_brake") and name[len("oracle_brake") :].isdigit():
        return make_oracle(cfg, brake_first=int(name[len("oracle_brake") :])), 0, NO_MODELS
    if name.startswith("oracle_pixels") and name[len("oracle_pixels") :].isdigit():
        return make_oracle(cfg, brake_until_pixels=int(name[len("oracle_pixels") :])), 0, NO_MODELS
    if name == EXACT_CHOOSER:
        return make_exact_chooser(cfg), 0, NO_MODELS
    return learned_policy(cfg, AgentId.parse(name))


def learned_policy(cfg, agent: AgentId, state: dict | None = None):
    """(policy, training seed, model hashes) for a trained agent, rebuilt by its learner (``registry.LEARNERS``);
    ``state``: its checkpoint, if the caller has already loaded it (they are large: the replay memory is in them)."""
    from .common import decision_device

    device = decision_device(cfg)
    state = loading.load_agent_state(cfg, agent) if state is None else state
    # each agent acts as it was trained: its own input (speed or not, or the true state) and its own action map
    if state.get("obs") == "privileged":  # bound to each episode's env by rollout; no world model, no camera
        from .agent_obs import PrivilegedEncoder

        encoder = PrivilegedEncoder(device=device)
    else:
        encoder = loading.load_world_model(cfg, **loading.agent_input(state, cfg.vae.latent_dim), device=device)
    learner = registry.learner_module(state.get("learner", "ddpg"))
    policy = learner.build_policy(agent.policy, encoder, state, device=device)
    return policy, agent.seed, loading.models_of(cfg, agent)


def env_overrides(policy) -> dict:
    """Env settings a policy needs beyond the experiment's (a chooser reading the narrow second camera)."""
    return dict(getattr(policy, "env_overrides", None) or {})


def porav_policies(cfg):
    """(policy, seed, needs the camera, car tests too) for the paper's family: braking, the planner, every trained
    agent."""
    names = [p for p in ("braking", "oracle") if p in cfg.evaluate.policies]
    names += [a.key for a in artifacts.trained_agents(cfg)]
    out = []
    for name in names:
        policy, seed, _ = policy_for(cfg, name)
        # an agent on the true state (obs=privileged) says it needs no camera
        out.append((policy, seed, getattr(policy, "needs_camera", name not in ("braking", "oracle")), True))
    return out
