"""The tags of the project's named random streams: one constant per stream, in one place.

A stream is ``np.random.default_rng([seed, TAG, index...])``: a seed (the run's ``seed``, an evaluation bank's seed
or a scenario's own ``spec.seed``), the stream's tag, and the indices that pick one draw (an episode, a DAgger
round, an epoch and batch). The tag keeps one purpose's draws apart from another's under the same seed, so a new
stream takes a new tag from here, never a value already listed. Every value is the one the code has always used:
changing one changes every result drawn from it.

Shared values. Four values serve more than one stream; that is safe only because another component of their seeds
differs. Note that numpy's ``SeedSequence`` pads a list shorter than four words with zeros, so ``[s, t]``, ``[s, t,
0]`` and ``[s, t, 0, 0]`` are the same stream: a shorter list alone does not keep two streams apart.

* 2020: ``KIM_NEUTRAL_CARS`` is keyed by a scenario's own seed (drawn from [0, 2**31 - 1)), ``KIM_TRAINING_EPISODES``
  by the run's seed; they meet only for a scenario whose seed equals the run seed (its neutral cars then reuse the
  draws of training episode 0's scenario).
* 2022: ``MEROLA_JUNCTION_DISTANCE`` is keyed by a scenario's own seed (as for 2020, it meets the run-seed streams
  only for a scenario whose seed equals the run seed), ``MEROLA_TRAINING_EPISODES`` and ``KIM_DAGGER_SCENARIOS`` by
  the run's; those two (``[seed, 2022, episode]`` and ``[seed, 2022, round, e]``) belong to different families'
  runs, which never draw each other's scenarios.
* 1: ``KIM_BANK_CROSSING`` is ``[bank seed, k, 1]`` with k < 3, ``KIM_COUNTERFACTUAL_PROPOSALS`` the fifth word of
  ``[label seed, 7779, r, e, 1]``: their second words (k and 7779) always differ.
* 77: ``CHOOSER_MINIBATCHES`` is ``[seed, 77]``, ``RNN_OPEN_LOOP_START`` is ``[seed, epoch, batch, 77]``: their
  fourth words (0 and 77) always differ.

A tag can also equal an index in the same place, under the same seed: the collection's ``[seed, i]`` is
``CHOOSER_MINIBATCHES``' ``[seed, 77]`` at episode 77, and ``RECORDING_BRANCHES``' ``[seed, i, 3571]`` is episode 3571
of the stream tagged i for i = 1717, 1729, 2020, 2021 or 2022 (collection episodes the paper scale's 2,400 reach). Such
pairs reuse the same bits for unrelated draws in different stages (a scenario and minibatch indices, a branch plan and a
training scenario). The chae bank's Scenario 1, ``[bank seed, TTC in hundredths]``, meets ``CHAE_BANK_SCENARIO_2`` only
at a TTC of 0.02 s. ``RNN_VALIDATION_INPUTS`` is added to the run seed for a torch generator, whose training epochs use
run seed * 1000 + epoch: they meet only for run seed 0 at epoch 99. The evaluation banks' seeds (``evaluate.kim.seed``
2020, ``evaluate.merola.seed`` 2022) are seeds, not tags: they come first in their lists.
"""

from __future__ import annotations

# ----------------------------------------------------------------------------- the pipeline's episodes' scenarios
# [run seed, TAG, episode] unless said otherwise
AGENT_EPISODE_SEEDS = 1729  # train_agent: training episode i's env seed (a scenario from the paper's distributions)
AGENT_FOCUS_EPISODES = 4242  # train_agent: whether training episode i is from the focus mix, and its scenario if so
DAGGER_SCENARIOS = 5151  # imitation: DAgger round r's episode e's focus-mix scenario, [run seed, TAG, r, e]
DEMO_SCENARIOS = 31337  # demonstrate: the planner's demonstration episode i's focus-mix scenario
CHOOSER_LABEL_EPISODES = 8128  # chooser: labelled episode i's focus-mix scenario
# counterfactual actor: round r's labelled episode e's focus-mix scenario and its proposed shifts, [seed, TAG, r, e]
COUNTERFACTUAL_LABEL_EPISODES = 6151
DREAM_BRANCH_SCENARIOS = 6007  # dreams: held-out branch point k's scenario, from the paper's distributions
CHAE_TRAINING_EPISODES = 1717  # chae peer: training episode i's scenario and observation-noise seed
MEROLA_TRAINING_EPISODES = 2022  # merola peer: training episode i's scenario
# the kim peer's training_scenario(cfg, TAG, ...): [run seed, TAG, ...]
KIM_TRAINING_EPISODES = 2020  # training episode i's scenario
KIM_DEMO_SCENARIOS = 2021  # the planner's demonstration episode i's scenario
KIM_DAGGER_SCENARIOS = 2022  # DAgger round r's episode e's scenario, [run seed, TAG, r, e]
KIM_STUDENT_SCENARIOS = 7777  # experiments/kim_student.py: the students' episodes
KIM_CHOOSER_LABELS = 7778  # agent=kim_chooser (worldmodel/families/kim/chooser.py): its labelled episodes
# agent=counterfactual_kim (worldmodel/families/kim/counterfactual.py): round r's labelled episode e's scenario
# [label seed, TAG, r, e], and its proposed shifts [label seed, TAG, r, e, KIM_COUNTERFACTUAL_PROPOSALS]
KIM_COUNTERFACTUAL_LABELS = 7779
KIM_COUNTERFACTUAL_PROPOSALS = 1  # the fifth word of the proposals' stream, under KIM_COUNTERFACTUAL_LABELS
# agent=counterfactual_merola (worldmodel/families/merola/counterfactual.py): round r's labelled episode e's scenario,
# [label seed, TAG, r, e]
MEROLA_COUNTERFACTUAL_LABELS = 7780

# ----------------------------------------------------------------------------- datasets and training draws
RECORDING_BRANCHES = 3571  # recording: whether episode i branches, at which step, and the branch's actions, [s, i, TAG]
DATASET_SPLIT = 7919  # recording: which of a dataset's episodes are held out for validation, [seed, TAG]
RNN_OPEN_LOOP_START = 77  # train_rnn: the open-loop dream's first step in batch b of an epoch, [s, epoch, b, TAG]
RNN_VALIDATION_INPUTS = 99  # train_rnn: the held-out loss's sampled inputs; torch seed run seed + TAG, not a list
CHOOSER_MINIBATCHES = 77  # chooser: the scorer's minibatches, [run seed, TAG]
# counterfactual actor: round r's minibatches of phase p (0 the critic, 1 the actor), [run seed, TAG, r, p]
COUNTERFACTUAL_MINIBATCHES = 6152

# ----------------------------------------------------------------------------- evaluation banks: [bank seed, ...]
CHAE_BANK_SCENARIO_2 = 2  # chae: Scenario 2's trials (Scenario 1's: [bank seed, TTC in hundredths of a second])
KIM_BANK_CROSSING = 1  # kim: scenario k's impact offsets, [bank seed, k, TAG] (its other fields: [bank seed, k])

# ----------------------------------------------------------------------------- the simulator: [spec.seed, TAG]
KIM_NEUTRAL_CARS = 2020  # envs/kim.py: the neutral cars (follower's headway, free lanes, oncoming traffic)
KIM_BUILDING_HEIGHTS = 14  # envs/kim.py: the heights of the building boxes the camera draws (render_placements)
MEROLA_JUNCTION_DISTANCE = 2022  # envs/merola.py: how far ahead the junction lies, where the scenario leaves it open
