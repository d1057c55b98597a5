# Two commands do everything: `make run` (the whole pipeline at scale=quick) and `make test`.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
EXPERIMENT ?= quick
# more overrides for run, headline and peers: `make peers ARGS=plan=true` lists each step's state, running nothing
ARGS ?=

.PHONY: setup run test lint bench preview mutation headline peers ncap clean-venv

setup: $(VENV)/.installed

$(VENV)/.installed: requirements.lock requirements-dev.lock pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q -r requirements-dev.lock
	$(PY) -m pip install -q --no-deps -e .
	touch $@

run: setup
	$(PY) -m worldmodel.pipeline experiment=$(EXPERIMENT) scale=quick $(ARGS)

# The paper's family at paper scale, as one experiment (docs/results/porav/README.md): one world model; the paper's
# DDPG with R1 and R2, the best DDPG-actor variant (dag), the chooser, the two-camera chooser and the counterfactual-
# cost actor, three seeds each; evaluated on the validation bank, then once on the sealed test bank (recorded in
# docs/results/ledger.csv; an evaluation there after the first needs ARGS=evaluate.retest=true, and adds a row).
# About 4.5 hours on 2 cores, the counterfactual actor's 10 min a seed included (projected from each stage's recorded
# time in docs/results/porav/ and the speed-ups in benchmarks/RESULTS.md); resumable: run it again to continue. launcher=slurm spreads it over a cluster.
HEADLINE := experiment=headline scale=paper agents=[ddpg,dag,chooser,chooser_tele,counterfactual] seeds=[0,1,2] \
	banks=[validation,test] demos.episodes=500 evaluate.policies=[braking,oracle,oracle_brake1,oracle_brake2]

headline: setup
	$(PY) -m worldmodel.pipeline $(HEADLINE) $(ARGS)

# The peer systems as their reports validated them (docs/results/chae/, kim/, merola/), at quick scale with their own
# world model for the camera agents: Merola's DDQN and its nine-action exact-return learner; Kim's LIDAR agents (goal-unaware, goal-aware, planner-taught),
# the LIDAR chooser, the counterfactual-cost DDPG and the world-model agent; Chae's DQN as three ensembles of three
# seeds. Each family on its validation bank, then once on its sealed test bank. agents=[] leaves the paper's family
# out, so this never touches the Porav test bank. About 9 hours on 2 cores (the counterfactual-cost DDPG: about
# 15 min of it; Merola's exact-return learner about 10 min); resumable: run it again to continue where it stopped.
PEERS_RUN := experiment=peers scale=quick agents=[] peers=[merola,counterfactual_merola,kim,ddpg_kim_fd,kim_chooser,counterfactual_kim,ddpg_wm_kim,chae] \
	seeds=[0,1,2] banks=[validation,test] evaluate.chae.trials=1000 evaluate.chae.singles=false

peers: setup
	$(PY) -m worldmodel.pipeline $(PEERS_RUN) $(ARGS)

# The Euro NCAP bank for every policy of both experiments, after `make headline` and `make peers` (docs/results/ncap/):
# the paper's policies taking over at TTC 1.5 s and at 0.75 s, the peers driving from the start, Chae's agents as the
# three ensembles its report judges.
ncap: setup
	$(PY) -m worldmodel.ncap experiment=headline scale=paper
	$(PY) -m worldmodel.ncap experiment=headline scale=paper ncap.takeover_ttc_s=0.75
	$(PY) -m worldmodel.ncap experiment=peers scale=quick evaluate.chae.singles=false

# Two workers, one per core; a file's tests stay on one worker, so module-scoped fixtures (the smoke pipeline) are
# built once.
test: setup lint
	$(PY) -m pytest -q -n 2 --dist loadfile

lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

bench: setup
	$(PY) -m benchmarks.run

# Mutation testing of the core numeric modules (tests/README.md): not part of CI, 5-7 minutes on 2 cores.
mutation: setup
	$(PY) -m pip install -q -r requirements-mutation.lock
	$(PY) tests/mutation.py

preview: setup
	$(PY) -m envs.preview --out runs/preview/episode.gif

clean-venv:
	rm -rf $(VENV)
