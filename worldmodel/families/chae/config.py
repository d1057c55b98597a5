"""Family chae's config sections: ``agent.chae`` (its DQN's training and checkpoint selection) and
``evaluate.chae``. The family declares them (``Family.agent_config``, ``eval_config``); the schema has them from
the registry."""

from __future__ import annotations

from dataclasses import dataclass, field

from ...banks import seed_problems
from ...common import Checked, ConfigValueError
from ...common import positive_fields as _positive

# the scripted policies of its evaluation, in the order their rows are written (``policies.SCRIPTED``)
SCRIPTED_POLICIES = ("braking", "ttc_braking", "latest_safe_braking", "closing_braking")


@dataclass
class SelectConfig(Checked):
    """Checkpoint selection for Chae's DQN (``agent.chae.select``; ``worldmodel/families/chae/``). Every ``every``
    episodes once ``start`` of the run has passed, the greedy agent drives a validation draw of Chae's trials
    (``trials`` Scenario-1 trials at each TTC of ``ttcs`` and as many Scenario-2 trials, seeded by ``seed``: never
    the evaluation's ``evaluate.chae.seed``), and ``best.pt`` keeps the checkpoint that, among those bumping in at
    most ``max_bump`` % at every TTC, stops needlessly least (else: the one that bumps least); evaluation loads it.
    Chae's two metrics, not the reward, choose it: the reward does not tell a needless stop from a pass at 10-30
    km/h, and successive checkpoints of one run differ there (docs/results/chae/)."""

    every: int = 250  # episodes between validations; 0 = off, evaluation loads last.pt
    start: float = 0.25  # the share of agent.chae.episodes before the first validation
    seed: int = 99
    trials: int = 200
    ttcs: list[float] = field(default_factory=lambda: [1.5, 1.7, 1.9])
    max_bump: float = 1.0  # %, at each TTC
    max_stops: float = 5.0  # %, needless stops: with max_bump, the bars that rescoring's candidates are inside
    # keep every validated checkpoint as validated/episodeNNNNN.pt (2 MB each), to choose again on a larger draw
    # (rescore below, or experiments/chae_reselect.py) without retraining
    keep: bool = False
    # after the run, this many kept checkpoints inside both bars that bump least at ttcs[0] drive a larger draw
    # (seeded by ``rescore_seed``), and best.pt becomes the one with the most room under both bars; 0 = off
    rescore: int = 0
    rescore_seed: int = 98
    rescore_trials: int = 300  # Scenario-1 trials per TTC of the rescoring draw, and as many in Scenario 2
    # s, the TTCs the rescoring draw drives, weighed by their highest bump rate; null = ttcs[0] alone, whose choices
    # bumped at TTC 2.5-3.7 s instead (docs/results/chae/); dqn_chae adds 2.5-3.5 s
    rescore_ttcs: list[float] | None = None
    # if the rescored choice is not inside both bars, train ``extend`` more episodes (the scale's) and choose again,
    # at most ``extend_blocks`` times (the preset's; 0 = off): the runs swing to the end (docs/results/chae/)
    extend: int = 1000
    extend_blocks: int = 0

    @classmethod
    def as_recorded(cls, values: dict, settings: dict) -> None:
        if not (values.get("extend") and values.get("extend_blocks")):
            values.pop("extend", None)  # off: the run's length as before the option
            values.pop("extend_blocks", None)
        if not values.get("rescore"):
            for key in ("keep", "rescore", "rescore_seed", "rescore_trials", "rescore_ttcs", "max_stops"):
                values.pop(
                    key, None
                )  # no rescoring: best.pt chosen as before the option (keeping files changes nothing)

    def problems(self):
        for err in _positive(self, "trials"):
            yield ConfigValueError(f"chae.select.{err.key}", err.value, err.requirement)
        yield from seed_problems(self, "seed", "chae.select.")
        yield from seed_problems(self, "rescore_seed", "chae.select.")
        if self.seed < 0:
            yield ConfigValueError("chae.select.seed", self.seed, "it must be >= 0")
        if self.every < 0:
            yield ConfigValueError("chae.select.every", self.every, "it must be >= 0 episodes (0 = off)")
        if not 0.0 <= self.start <= 1.0:
            yield ConfigValueError("chae.select.start", self.start, "it must be a share of the run, in [0, 1]")
        if not self.ttcs or any(not 0.0 < float(t) < 5.0 for t in self.ttcs):
            yield ConfigValueError("chae.select.ttcs", list(self.ttcs), "use a non-empty list of TTCs in (0, 5) s")
        if not 0.0 <= self.max_bump <= 100.0:
            yield ConfigValueError("chae.select.max_bump", self.max_bump, "it must be a rate in [0, 100] %")
        if not 0.0 <= self.max_stops <= 100.0:
            yield ConfigValueError("chae.select.max_stops", self.max_stops, "it must be a rate in [0, 100] %")
        if self.rescore < 0:
            yield ConfigValueError("chae.select.rescore", self.rescore, "it must be >= 0 checkpoints (0 = off)")
        if self.rescore and not self.keep:
            yield ConfigValueError(
                "chae.select.rescore",
                self.rescore,
                "it reads the kept checkpoints back: set agent.chae.select.keep=true too",
            )
        if self.rescore and self.rescore_seed == self.seed:
            yield ConfigValueError(
                "chae.select.rescore_seed", self.rescore_seed, "it must differ from agent.chae.select.seed (a new draw)"
            )
        yield from _positive(self, "rescore_trials")
        if self.extend < 0:
            yield ConfigValueError("chae.select.extend", self.extend, "it must be >= 0 episodes per block (0 = off)")
        if self.extend_blocks < 0:
            yield ConfigValueError("chae.select.extend_blocks", self.extend_blocks, "it must be >= 0 blocks")
        if self.extend and self.extend_blocks and not self.rescore:
            yield ConfigValueError(
                "chae.select.extend",
                self.extend,
                "it trains on until the rescoring finds a member: set agent.chae.select.rescore too",
            )
        if self.extend and self.extend_blocks and self.every and self.extend % self.every:
            yield ConfigValueError(
                "chae.select.extend", self.extend, f"use a multiple of agent.chae.select.every ({self.every}) episodes"
            )
        if self.rescore_ttcs is not None and (
            not self.rescore_ttcs or any(not 0.0 < float(t) < 5.0 for t in self.rescore_ttcs)
        ):
            yield ConfigValueError(
                "chae.select.rescore_ttcs", list(self.rescore_ttcs), "use null or a non-empty list of TTCs in (0, 5) s"
            )


@dataclass
class ChaeAgentConfig(Checked):
    """Chae et al.'s DQN (``agent=dqn_chae``, family chae; worldmodel/families/chae/): how long it trains, what it is
    trained on, and the checkpoint it keeps."""

    episodes: int = 6000  # training episodes (~40 steps each)
    # s, the training TTCs, U(lo, hi); evaluation keeps its own. The paper's 1.5-4 s; dqn_chae trains from 1.3 s, so
    # that TTC 1.5 s, the bar's edge, is not training's edge (docs/results/chae/)
    ttc_range: list[float] = field(default_factory=lambda: [1.5, 4.0])
    # m, std of the noise on the pedestrian's position in Chae's state (the paper: "slight"); a checkpoint records
    # it. 0.1 keeps older runs current; dqn_chae sets 0.05, where Chae's Table I points (docs/results/chae/)
    noise_m: float = 0.1
    select: SelectConfig = field(default_factory=SelectConfig)  # which checkpoint best.pt keeps

    @classmethod
    def as_recorded(cls, values: dict, settings: dict) -> None:
        """``select`` shapes only a run of a learner that chooses its checkpoint on a validation draw, with
        ``select.every`` set (0: as before the option)."""
        from ...registry import families

        agent = settings.get("agent") or {}
        chooses = any(
            f.selects_checkpoints and settings.get("reward") in f.rewards and agent.get("learner") in f.learners
            for f in families()
        )
        if not (chooses and (values.get("select") or {}).get("every")):
            values.pop("select", None)

    def problems(self):
        for err in _positive(self, "episodes"):
            yield ConfigValueError(f"chae.{err.key}", err.value, err.requirement)
        ttcs = [float(t) for t in self.ttc_range]
        if len(ttcs) != 2 or not 0.0 < ttcs[0] < ttcs[1] <= 5.0:
            yield ConfigValueError(
                "chae.ttc_range",
                list(self.ttc_range),
                "use [lo, hi] with 0 < lo < hi <= 5 s (beyond 5 s the trigger would lie behind the ego)",
            )
        if not 0.0 <= self.noise_m <= 1.0:
            yield ConfigValueError(
                "chae.noise_m", self.noise_m, "it must be in [0, 1] m (0: the exact relative position)"
            )


@dataclass
class ChaeEvalConfig(Checked):
    """Chae et al.'s evaluation on family chae (worldmodel/families/chae/): Table I's bump rate per TTC, Scenario 2's
    unnecessary stops, stopping distances, and contact, impact speed and injury."""

    trials: int = 200  # seeded Scenario-1 trials per TTC (the paper: 10,000), and Scenario-2 trials
    ttcs: list[float] = field(default_factory=lambda: [round(0.9 + 0.2 * i, 1) for i in range(16)])  # 0.9 .. 3.9
    seed: int = 2017  # the validation draw (evaluate.bank=validation); the test draw is worldmodel/banks.py's
    # k >= 2: also evaluate ensembles of k consecutive seeds, greedy on their mean Q, which damps the runs' swings
    # (0: runs alone); 3: two ensembles in three inside both bars, single runs three in nine (docs/results/chae/)
    ensemble: int = 3
    # false: only the ensembles drive the trials (their members still load), for a large draw such as Table I's
    # 1,000 trials per TTC, where each run alone would cost as much again per seed
    singles: bool = True
    # scripted policies beside every dqn agent (SCRIPTED_POLICIES; built in families/chae/). Fewer for
    # a large draw whose scripted rows are already known: they are deterministic, the same trials give the same rows
    policies: list[str] = field(default_factory=lambda: list(SCRIPTED_POLICIES))

    def problems(self):
        yield from _positive(self, "trials")
        yield from seed_problems(self, "seed", "chae.")
        if not self.singles and not self.ensemble:
            yield ConfigValueError(
                "chae.singles", self.singles, "with no ensembles (chae.ensemble=0) no agent would drive"
            )
        if not self.ttcs or any(t <= 0 for t in self.ttcs):
            yield ConfigValueError("ttcs", list(self.ttcs), "give positive TTCs in seconds")
        if any(p not in SCRIPTED_POLICIES for p in self.policies):
            yield ConfigValueError("chae.policies", list(self.policies), f"use some of {', '.join(SCRIPTED_POLICIES)}")
        if self.ensemble == 1 or self.ensemble < 0:
            yield ConfigValueError("chae.ensemble", self.ensemble, "give 0 (none) or the members per ensemble, >= 2")
