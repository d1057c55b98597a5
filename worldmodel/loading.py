"""Loading what earlier stages wrote, checked: the datasets, the VAE, the LSTM and the agents' checkpoints, each
held to the identities of the inputs it was built from (docs/design.md §9). A stale or broken input stops the
caller with the file and the command that rebuilds it (``allow_stale=true`` loads it anyway, with a warning).
Where each artifact lives, and what its identity is, is ``worldmodel/artifacts.py``."""

from __future__ import annotations

import logging
from pathlib import Path

from .artifacts import (
    DATASETS,
    AgentId,
    actor_id,
    check_output,
    dataset_sha256,
    demos_dir,
    file_identity,
    legacy_identities,
    manifest_path,
    refuse_unless_allowed_stale,
    rnn_dir,
    rnn_id,
    rollouts_dir,
    short,
    vae_dir,
    vae_id,
    world_model_inputs,
)
from .common import StageError, load_checkpoint, stage_command
from .config.recorded import inputs_as_recorded

log = logging.getLogger(__name__)


def check_inputs(cfg, what: str, path: Path, state: dict, inputs: dict[str, Path], rebuild: str) -> None:
    """Compare the input identities recorded in a checkpoint (``state``) with the current ``inputs`` files.

    Inputs whose file is absent are not compared (data may be deleted after training). A mismatch is a
    StageError naming both files and how to rebuild, or a warning under ``allow_stale=true``.
    """
    current = {name: (dataset_sha256 if name in DATASETS else file_identity)(file) for name, file in inputs.items()}
    recorded = inputs_as_recorded((state.get("provenance") or {}).get("inputs", {}), current)
    legacy = legacy_identities(inputs)
    stale = [
        name
        for name, now in current.items()
        if now is not None and recorded.get(name) not in (now, legacy.get(name, now))
    ]
    if not stale:
        return
    details = "; ".join(
        f"it was built on {name} {short(recorded.get(name)) or '(unrecorded)'}, but {inputs[name]} "
        f"is now {short(current[name])}"
        for name in stale
    )
    message = (
        f"{what} {path} is stale: {details}. Rebuild it with `{rebuild}` (or run "
        f"`python -m worldmodel.pipeline experiment={cfg.experiment}`, which rebuilds every stale stage), "
        "or pass allow_stale=true to load it anyway."
    )
    refuse_unless_allowed_stale(cfg, message)


def open_rollouts(cfg):
    from .data import CorruptDataError, RolloutStore

    root = rollouts_dir(cfg)
    if not manifest_path(cfg).exists():
        raise StageError(f"no complete rollout dataset at {root}. Run `{stage_command('collect', cfg)}` first.")
    try:
        return RolloutStore(root)
    except CorruptDataError as err:
        raise StageError(str(err)) from err


def open_demos(cfg):
    """The planner demonstrations of ``worldmodel.demonstrate``, checked to hold ``demos.episodes`` episodes."""
    from .data import CorruptDataError, RolloutStore

    root = demos_dir(cfg)
    n = cfg.demos.episodes
    make = f"{stage_command('demonstrate', cfg)} demos.episodes={n}"
    if not (root / "manifest.json").exists():
        raise StageError(f"no complete planner demonstrations at {root}. Run `{make}` first.")
    try:
        store = RolloutStore(root)
    except CorruptDataError as err:
        raise StageError(str(err)) from err
    if len(store.episodes("train")) + len(store.episodes("validation")) != n:
        raise StageError(f"{root} does not hold demos.episodes={n} episodes: delete it and run `{make}`")
    return store


def build_vae(vae):
    """The VAE that the config section ``vae`` describes, freshly initialised."""
    from .models.vae import SegVAE

    return SegVAE(num_classes=vae.num_classes, latent_dim=vae.latent_dim, channels=vae.channels)


def build_rnn(vae, rnn):
    """The LSTM that the config sections ``rnn`` and ``vae`` (its latent size) describe, freshly initialised."""
    from .models.rnn import WorldRNN

    return WorldRNN(
        latent_dim=vae.latent_dim,
        action_dim=2,
        hidden=rnn.hidden,
        head=rnn.head,
        gaussians=rnn.gaussians,
        residual=rnn.residual,
    )


def check_vae_architecture(state: dict, vae, path: Path) -> None:
    """Refuse a VAE checkpoint whose latent size or channels differ from the config section ``vae``'s (a checkpoint
    that names no channels has World Models' 32)."""
    for key, have in (("latent_dim", state["latent_dim"]), ("channels", state.get("channels", 32))):
        if have != vae[key]:
            raise StageError(
                f"{path} has vae.{key}={have} but the config says vae.{key}={vae[key]}. Set vae.{key}={have} or "
                "retrain the VAE."
            )


def check_rnn_architecture(state: dict, vae, rnn, path: Path) -> None:
    """Refuse an LSTM checkpoint whose shape settings differ from the config sections ``vae`` and ``rnn``, naming
    the key."""
    for key, want in (
        ("latent_dim", vae.latent_dim),
        ("hidden", rnn.hidden),
        ("head", rnn.head),
        ("residual", rnn.residual),
    ):
        have = state.get(key)
        if have != want:
            raise StageError(
                f"{path} has {key}={have!r} but the config says {want!r}. "
                "Use the checkpoint's value, or delete the LSTM run and retrain it."
            )


def load_vae(cfg, which: str = "best"):
    """The trained VAE (eval mode) and its path; a clear error if missing, of the wrong size, or stale."""
    path = vae_dir(cfg) / f"{which}.pt"
    check_output(cfg, path, "The VAE checkpoint", stage_command("train_vae", cfg))
    state = load_checkpoint(path, "VAE checkpoint", "train_vae", cfg)
    check_vae_architecture(state, cfg.vae, path)
    check_inputs(cfg, "The VAE", path, state, {"rollouts": manifest_path(cfg)}, stage_command("train_vae", cfg))
    model = build_vae(cfg.vae)
    model.load_state_dict(state["model"])
    return model.eval(), path


def load_rnn(cfg, which: str = "best"):
    """The trained LSTM (eval mode) and its path; a clear error if missing, of the wrong size, or trained on
    another VAE than the current one."""
    path = rnn_dir(cfg) / f"{which}.pt"
    check_output(cfg, path, "The LSTM checkpoint", stage_command("train_rnn", cfg))
    state = load_checkpoint(path, "LSTM checkpoint", "train_rnn", cfg)
    check_rnn_architecture(state, cfg.vae, cfg.rnn, path)
    check_inputs(cfg, "The LSTM", path, state, {"vae": vae_dir(cfg) / "best.pt"}, stage_command("train_rnn", cfg))
    model = build_rnn(cfg.vae, cfg.rnn)
    model.load_state_dict(state["model"])
    return model.eval(), path


def load_world_model(cfg, use_speed: bool | None = None, frame_view: bool | None = None, device=None):
    """VAE + LSTM behind the agent's observation encoder (with speed as ``use_speed``, default ``agent.use_speed``,
    and the frame's hazard profiles as ``frame_view``, default ``agent.frame_view``), on ``device`` (default: the
    CPU, where single decisions are fastest to date)."""
    from .agent_obs import WorldModelEncoder

    vae, rnn = (load(cfg, "best")[0].to(device or "cpu") for load in (load_vae, load_rnn))
    return WorldModelEncoder(
        vae,
        rnn,
        use_speed=cfg.agent.use_speed if use_speed is None else use_speed,
        frame_view=cfg.agent.frame_view if frame_view is None else frame_view,
    )


def agent_input(state: dict, latent_dim: int) -> dict:
    """The encoder settings an agent's checkpoint was trained with: ``load_world_model``'s keyword arguments (older
    checkpoints tell speed in their input by its size)."""
    speed = bool(state.get("use_speed", state["obs_dim"] == 2 * int(latent_dim) + 1))
    return {"use_speed": speed, "frame_view": bool(state.get("frame_view", False))}


def load_actor(cfg, agent: AgentId, which: str = "last", state: dict | None = None):
    """A trained actor (eval mode) and its checkpoint (``state``, if the caller has already loaded it); refuses one
    built on another VAE or LSTM. Another learner's checkpoint (a chooser's, a counterfactual actor's) has no
    DDPG actor: the actor returned is None."""
    from .models.ddpg import Actor

    state = load_agent_state(cfg, agent, which) if state is None else state
    if state.get("learner", "ddpg") != "ddpg":
        return None, state
    actor = Actor(state["obs_dim"], 2, tuple(state["actor_hidden"]))
    actor.load_state_dict(state["agent"]["actor"])
    return actor.eval(), state


def load_agent_state(cfg, agent: AgentId, which: str = "last") -> dict:
    """An agent's checkpoint, after checking that it was built on the current VAE and LSTM."""
    path = agent.dir(cfg) / f"{which}.pt"
    rebuild = f"python -m worldmodel.train_agent experiment={cfg.experiment} reward={agent.reward} seed={agent.seed}"
    check_output(cfg, path, f"The {agent.key} agent checkpoint", rebuild)
    state = load_checkpoint(path, f"{agent.key} agent checkpoint", "train_agent", cfg)
    files = {"vae": vae_dir(cfg) / "best.pt", "rnn": rnn_dir(cfg) / "best.pt"}
    inputs = {name: files[name] for name, _ in world_model_inputs(state.get("obs", "worldmodel"))}
    check_inputs(cfg, f"The agent {agent.key}", path, state, inputs, rebuild)
    return state


def models_of(cfg, agent: AgentId) -> dict[str, str]:
    """Short hashes of the VAE, LSTM and actor behind an agent's decisions (for evaluation rows); empty for a part
    its observation does not read (none of the world model for ``obs=privileged``, whether set on the command line
    or as a preset's own input), as the ledger names them (``families.common.models_of``)."""
    from .config import agent_preset

    reads = {name for name, _ in world_model_inputs(agent.obs or agent_preset(cfg, agent.variant).obs)}
    return {
        "vae_sha": short(vae_id(cfg)) if "vae" in reads else "",
        "rnn_sha": short(rnn_id(cfg)) if "rnn" in reads else "",
        "actor_sha": short(actor_id(cfg, agent)),
    }
