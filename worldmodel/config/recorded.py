"""What a run's config hash covers: a stage's settings in the layout the recorded runs were hashed with.

Options added to a section at their off value, keys removed or moved since a run was recorded, and keys that only
another learner reads are brought back to that layout before hashing (``artifacts.provenance``), so a change of
the config's shape alone never makes a recorded run stale. A change of what a run computes must change its hash.
The rules for a family's own sections (``agent.<section>``, ``evaluate.<section>``) are declared with the family
(``Family.hashed_as``, ``hashed_defaults``, ``removed_eval_keys``: worldmodel/registry.py); the rest are here.
"""

from __future__ import annotations

from .. import registry

RECORDED_WORKERS = 2  # the chooser's labelling processes in the runs recorded while the count was hashed
RNN_MEASUREMENT_KEYS = ("effect_points", "effect_horizon", "horizon_episodes")
# Keys added to a config section after runs were recorded: at these values they mean what their absence meant, so
# they are left out of the hash and older runs stay current.
ADDED_DEFAULTS = {
    "env": {"step_s": 1.0 / 15.0, "tele_fov_deg": None, "lateral_exit_m": 25.0},  # and env.family: the default
    "agent": {"obs": "worldmodel", "paper_obs": "worldmodel", "lidar_scans": 0, "lidar_rays": 36},
}
# DQN options added after runs were recorded, with the value that leaves the learner as it was before them.
DQN_OPTIONS_OFF = {"value_rescale": False, "trauma_weight_final": None}
# Counterfactual-actor options added after runs were recorded, with the value that leaves the learner as it was.
COUNTERFACTUAL_OPTIONS_OFF = {"critic_obs": "actor", "search": 0}
# Keys removed from a config section after runs were recorded, with the one value they ever had in a run: they are
# put back before hashing, so those runs stay current. (Removed keys that were also added defaults simply stay out.)
REMOVED_KEYS = {("agent", "dqn"): {"trauma_lead": 0}}


def _removed_keys() -> dict:
    families = {("evaluate", f.section): f.removed_eval_keys for f in registry.families() if f.removed_eval_keys}
    return {**REMOVED_KEYS, **families}


def _added_defaults() -> dict:
    agent = {k: v for f in registry.families() for k, v in f.hashed_defaults.items()}
    return {
        "env": {**ADDED_DEFAULTS["env"], "family": registry.default().name},
        "agent": {**ADDED_DEFAULTS["agent"], **agent},
    }


def _legacy_layout(agent) -> None:
    """Each family's section back at the flat agent keys the runs before the sections were hashed with
    (``Family.hashed_as``). A flat key two families moved into one old name (Kim's and Merola's total_steps were
    one key, peer_total_steps) is that of the family whose observations the agent has, else of the first declared."""
    if not isinstance(agent, dict):
        return
    families = [f for f in registry.families() if f.section]
    sections = {f.section: agent.pop(f.section, None) or {} for f in families}
    put = set()
    for f in families:
        own = agent.get("obs") in f.observations
        for key, old in f.hashed_as.items():
            if key in sections[f.section] and (old not in put or own):
                agent[old] = sections[f.section][key]
                put.add(old)


def as_recorded(settings: dict) -> dict:
    """``settings`` (a stage's config sections, plain dicts) as the runs recorded so far hashed them: moved keys
    back at their old names, added options at their off values left out, removed keys put back."""
    _legacy_layout(settings.get("agent"))
    for (section, sub), removed in _removed_keys().items():
        part = settings.get(section, {})
        part = part.get(sub) if isinstance(part, dict) else None
        if isinstance(part, dict):
            for key, value in removed.items():
                part.setdefault(key, value)
    agent = settings.get("agent")
    for learner in registry.LEARNERS.values():  # keys only one learner reads (Learner.own_keys) shape no other
        if isinstance(agent, dict) and agent.get("learner") != learner.name:
            for key in learner.own_keys:
                agent.pop(key, None)
    dqn = agent.get("dqn") if isinstance(agent, dict) else None
    if isinstance(dqn, dict):
        for key, off in DQN_OPTIONS_OFF.items():
            if key in dqn and dqn[key] == off:
                dqn.pop(key)  # off: the DQN as before the option
    counterfactual = agent.get("counterfactual") if isinstance(agent, dict) else None
    if isinstance(counterfactual, dict):
        if not counterfactual.get("search"):
            counterfactual.pop("search_weight", None)  # read only by the search
        for key, off in COUNTERFACTUAL_OPTIONS_OFF.items():
            if key in counterfactual and counterfactual[key] == off:
                counterfactual.pop(key)  # off: the learner as before the option
    chooses = isinstance(agent, dict) and any(
        f.selects_checkpoints and settings.get("reward") in f.rewards and agent.get("learner") in f.learners
        for f in registry.families()
    )
    if isinstance(agent, dict) and not (chooses and agent.get("select", {}).get("every")):
        agent.pop("select", None)  # only Chae's DQN chooses its checkpoint on a validation draw; 0 = as before
    select = agent.get("select") if isinstance(agent, dict) else None
    if isinstance(select, dict) and not (select.get("extend") and select.get("extend_blocks")):
        select.pop("extend", None)  # off: the run's length as before the option
        select.pop("extend_blocks", None)
    if isinstance(select, dict) and not select.get("rescore"):
        for key in ("keep", "rescore", "rescore_seed", "rescore_trials", "rescore_ttcs", "max_stops"):
            select.pop(key, None)  # no rescoring: best.pt chosen as before the option (keeping files changes nothing)
    chooser = agent.get("chooser") if isinstance(agent, dict) else None
    for key in ("min_brake_cost", "static_penalty"):
        if isinstance(chooser, dict) and not chooser.get(key):
            chooser.pop(key, None)  # off: the chooser as before the option
    if isinstance(chooser, dict) and chooser.get("label_seed", 0) is None:
        chooser.pop("label_seed")  # each seed its own labels, as before the option
    if isinstance(chooser, dict) and chooser.get("mask_camera") == "wide":
        chooser.pop("mask_camera")  # the world model's camera, as before the second one
    evaluate = settings.get("evaluate")
    if isinstance(evaluate, dict) and evaluate.get("family", registry.default().name) == registry.default().name:
        evaluate.pop("family", None)  # the paper's bank, as before the families existed
        for section in registry.sections():
            evaluate.pop(section, None)
    for section, defaults in _added_defaults().items():
        values = settings.get(section)
        if isinstance(values, dict):
            for key, default in defaults.items():
                if key in values and values[key] == default:
                    values.pop(key)
    return settings


def inputs_as_recorded(recorded: dict, current: dict) -> dict:
    """The input identities a run recorded (``recorded``), against the ``current`` ones: an agent that sees the
    frozen VAE's means of its frames (``obs=frames_vae``, Merola's) recorded no input before the VAE became one, so
    a record without any input is taken as built on the current VAE. Every such run on disk was trained on the VAE
    of its experiment, which nothing rebuilt; from now on the VAE is recorded and a new one makes the agent stale."""
    if not recorded and set(current) == {"vae"}:
        return dict(current)
    return recorded
