# worldenv: `make pipeline` runs the whole method, `make test` the tests.
# Every target depends on `setup`, so a fresh clone needs nothing typed first.
SHELL := /bin/bash
PYTHON_VERSION ?= 3.12.1
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
TASK ?= libero_goal
SCALE ?= small
EXP ?= outputs/$(TASK)-$(SCALE)
export MUJOCO_GL ?= egl
export HF_HUB_OFFLINE := 1
export TOKENIZERS_PARALLELISM := false

.PHONY: setup test test-fast faults smoke pipeline refit exploration rl-real rl-figures suites suites-table suites-pro suites-pro-table eval-release research-checkpoints act-checkpoint act-post-trained es-post-trained fidelity bench cost-model expert-table tensorboard clean

setup: $(STAMP)

# Re-runs only when pyproject.toml changes (idempotent).
$(STAMP): pyproject.toml
	@if [ ! -x $(PY) ]; then \
	  base="$$(pyenv prefix $(PYTHON_VERSION) 2>/dev/null)/bin/python"; \
	  [ -x "$$base" ] || base="$$(command -v python3.12)"; \
	  [ -n "$$base" ] || { echo "Python 3.12 not found (pyenv $(PYTHON_VERSION) or python3.12)"; exit 1; }; \
	  "$$base" -m venv $(VENV); \
	fi
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	# Two distributions write `cv2`; the headless one (pinned in pyproject.toml) is installed last to win.
	$(PY) -m pip install -q --force-reinstall --no-deps "$$(grep -o 'opencv-python-headless==[0-9.]*' pyproject.toml)"
	$(PY) -m pip check
	touch $(STAMP)

# Test files run in parallel (pytest-xdist), each whole on one worker so that its module fixtures
# (a tiny experiment's models) are built once: TEST_WORKERS=0 runs them in this process.
TEST_WORKERS ?= 2
test: setup
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile -m "not fault_full" tests

# The fault suite alone (also part of `make test`), with its matrix: case, outcome, seconds.
faults: setup
	$(PY) -m pytest -q -m fault tests --fault-matrix

test-fast: setup
	$(PY) -m pytest -q -m "not sim and not slow" tests

# Measure the scripted expert on the benchmark's fixed init states of every task of a suite
# (physics only) and print the per-task table: make expert-table TASK=libero_object N_INIT=50
N_INIT ?= 50
expert-table: setup
	$(PY) -m stages.collect +task=$(TASK) scale=$(SCALE) episodes_per_task=0 \
	  expert_eval.init_states=$(N_INIT) experiment_dir=outputs/expert-table/$(TASK)

# The pipeline so far, in one experiment directory; each stage finds its inputs through
# $(EXP)/manifest.jsonl and skips work already done (re-running resumes).
STAGE_ARGS = +task=$(TASK) scale=$(SCALE) experiment_dir=$(EXP)
# Collections go on for 32 steps after success: the reflector's positive frames. IMAGINATION: where LOOP's imagined
# rollouts start (starts: the paper's episode starts; keyframes: real keyframes, a bounded horizon and the paired-replay
# guard, conf/imagination/); LOOP_ARGS: further post_train_loop settings (here and in `make refit`).
IMAGINATION ?= starts
LOOP_ARGS ?=
pipeline: setup
	$(PY) -m stages.collect $(STAGE_ARGS) source=expert post_success_steps=32
	$(PY) -m stages.train_policy $(STAGE_ARGS)
	$(PY) -m stages.collect $(STAGE_ARGS) source=policy post_success_steps=32
	$(PY) -m stages.train_worldsim $(STAGE_ARGS)
	$(PY) -m stages.train_reflector $(STAGE_ARGS)
	# does the imagined env judge like the real one? (the SFT policy's imagined rollouts, paired replay)
	$(PY) -m stages.evaluate_imagination $(STAGE_ARGS)
	$(PY) -m stages.post_train_loop $(STAGE_ARGS) imagination=$(IMAGINATION) $(LOOP_ARGS)
	# termination=all: each episode once to the horizon, oracle / fixed / reflector read off it
	for policy in sft post_trained; do \
	  $(PY) -m stages.evaluate $(STAGE_ARGS) policy_from=$$policy termination=all || exit 1; done

# One refit round of the imagined route (after `make pipeline`): the post-trained policy's own rollouts
# (REFIT_EPISODES per task, real episodes counted in the manifest) collect into a folder of their own; the world
# model and the reflector are refit on every collection; LOOP goes on from the post-trained policy. REFIT_ARGS
# reach the world model (e.g. init_from=<record> to go on from the last one instead of from scratch),
# REFIT_REFLECTOR_ARGS the reflector's (eta_folds=0 eta=<the last one's>: keep the threshold chosen before). The
# refit round's policy ends on the benchmark's init states as the pipeline's do.
REFIT_EPISODES ?= 20
REFIT_REFLECTOR_ARGS ?=
refit: setup
	$(PY) -m stages.collect $(STAGE_ARGS) source=policy policy_from=post_trained post_success_steps=32 \
	  episodes_per_task=$(REFIT_EPISODES)
	$(PY) -m stages.train_worldsim $(STAGE_ARGS) policy_collections=all $(REFIT_ARGS)
	$(PY) -m stages.train_reflector $(STAGE_ARGS) policy_collections=all $(REFIT_REFLECTOR_ARGS)
	$(PY) -m stages.post_train_loop $(STAGE_ARGS) policy_from=post_trained policy_collections=all \
	  imagination=$(IMAGINATION) $(LOOP_ARGS)
	$(PY) -m stages.evaluate $(STAGE_ARGS) policy_from=post_trained termination=all

# Verdict fidelity and the world model as a policy evaluator: each policy at each Laplace noise scale acts
# in imagination, its actions are replayed in the real simulator (needs the pipeline's stages up to
# train_reflector). make fidelity FIDELITY_POLICIES=sft,post_trained
FIDELITY_POLICIES ?= sft
FIDELITY_NOISE ?= 1.0,0.5,2.0,3.0,4.0
fidelity: setup
	$(PY) -m stages.evaluate_imagination $(STAGE_ARGS) 'policies=[$(FIDELITY_POLICIES)]' 'noise_scales=[$(FIDELITY_NOISE)]'

# The pipeline on the three suites (goal, object, spatial), then the cross-suite table (outputs/suites/suites.md).
SUITES ?= libero_goal libero_object libero_spatial
suites: setup
	for t in $(SUITES); do $(MAKE) pipeline TASK=$$t SCALE=$(SCALE) EXP=outputs/$$t-$(SCALE) || exit 1; done
	$(PY) -m stages.suites outputs/suites $(foreach t,$(SUITES),$(t)=outputs/$(t)-$(SCALE))

# The same table from the evaluations kept in the repository (results/suites.yaml names them):
# results/suites.md, no simulator, seconds.
suites-table: setup
	$(PY) -m stages.suites --kept results/suites.yaml

# A suite's Table 1 row from its released checkpoints (checkpoints/<suite>/sft and post_trained, where
# released), without retraining: every termination on the first RELEASE_INIT benchmark init states, judged
# by the released reflector (checkpoints/<suite>/reflector); without one, oracle termination only.
SUITE ?= libero_goal
RELEASE_INIT ?= 50
eval-release: setup
	@if [ -d checkpoints/$(SUITE)/reflector ]; then term="termination=all reflector_from=checkpoints/$(SUITE)/reflector"; \
	else term="termination=oracle"; echo "checkpoints/$(SUITE)/reflector: not released, so oracle termination only"; fi; \
	for policy in sft post_trained; do \
	  folder=$$policy; \
	  if [ -d checkpoints/$(SUITE)/$$folder ]; then \
	    echo "evaluating checkpoints/$(SUITE)/$$folder as $$policy ($$term)"; \
	    $(PY) -m stages.evaluate +task=$(SUITE) experiment_dir=outputs/release-$(SUITE) \
	      policy_from=checkpoints/$(SUITE)/$$folder policy_label=$$policy $$term init_states=$(RELEASE_INIT) || exit 1; \
	  else echo "checkpoints/$(SUITE)/$$folder: not released"; fi; done

# The perturbed-suite table for the released policies: each released sft / post_trained of each suite on the
# perturbed suites the benchmark registers for it (LIBERO-PRO: <suite>_swap, _lan, _object, _task), oracle
# termination, the source suite's step limit, the first PRO_INIT init states per task (evaluations resume and
# reuse finished jobs); then results/suites-pro/suites_pro.md (and .json) beside each suite's own evaluation (make
# eval-release), kept in the repository as results/suites.md is; keep the evaluations too (analysis.keep), and
# `make suites-pro-table` writes the table from every kept one.
# LeRobot's ACT where released (checkpoints/<suite>/act_sft, act_post_trained: `make act-checkpoint act-post-trained`)
# is evaluated the same way into outputs/release-<suite>-act and gets rows of its own; so is the true-reward ES
# policy (checkpoints/libero_spatial/es_post_trained: `make es-post-trained`) into outputs/release-<suite>-es, paired
# with the project's SFT.
# make suites-pro PRO_SUITES=libero_spatial PRO_INIT=10
PRO_SUITES ?= $(SUITES)
PRO_PERTURBATIONS ?= swap lan object task
PRO_INIT ?= 50
suites-pro: setup
	@for suite in $(PRO_SUITES); do for release in "" act_ es_; do for p in $(PRO_PERTURBATIONS); do \
	  for policy in sft post_trained; do folder=checkpoints/$$suite/$$release$$policy; \
	  exp=outputs/release-$$suite$${release:+-$${release%_}}; \
	  if [ -d $$folder ]; then \
	    echo "evaluating $$folder on $${suite}_$$p"; \
	    $(PY) -m stages.evaluate +task=$$suite experiment_dir=$$exp policy_from=$$folder \
	      policy_label=$$policy eval_suite=$${suite}_$$p termination=oracle init_states=$(PRO_INIT) || exit 1; \
	  elif [ -z "$$release" ]; then echo "$$folder: not released"; fi; done; done; done; done
	$(PY) -m stages.suites_pro results/suites-pro $(foreach t,$(PRO_SUITES),$(t)=outputs/release-$(t)) \
	  $$(for t in $(PRO_SUITES); do for r in act es; do [ -d outputs/release-$$t-$$r ] && \
	    echo $$t:$$(echo $$r | tr a-z A-Z)=outputs/release-$$t-$$r; done; done)

# The same table from the evaluations kept in the repository (results/<suite>/evaluate-*, kept with analysis.keep):
# every kept oracle evaluation of a released checkpoint on a perturbed suite; no simulator, seconds.
suites-pro-table: setup
	$(PY) -m stages.suites_pro --kept results/suites-pro $(foreach t,$(PRO_SUITES),$(t)=results/$(t))

# The research variants (checkpoints/README.md, "Research variants"): out of the tree, each kept for one
# figure; extracted here at their paths from the commit that last held them (needs the full history).
RESEARCH_REV = 34160b4
RESEARCH_CHECKPOINTS = libero_goal/sft_imagined_proprio libero_goal/worldsim_open_loop \
  libero_goal/worldsim_open_loop_gpu libero_goal/worldsim_open_loop_refit libero_goal/reflector_imagined \
  libero_goal/reflector_latent_pairs libero_goal/reflector_pairs libero_goal/reflector_pairs_refit \
  libero_goal/reflector_pairs_starts libero_spatial/real_reference_seed1 libero_spatial/real_reference_seed2
research-checkpoints:
	@git cat-file -e $(RESEARCH_REV)^{commit} 2>/dev/null || { echo "commit $(RESEARCH_REV) is not in this clone: \
	fetch the full history (git fetch --unshallow) first"; exit 1; }
	@for f in $(RESEARCH_CHECKPOINTS); do git archive $(RESEARCH_REV) checkpoints/$$f | tar -x && echo "checkpoints/$$f"; done
	@git archive $(RESEARCH_REV) checkpoints/libero_goal/sft | \
	  tar -x --transform 's|^checkpoints/libero_goal/sft|checkpoints/libero_goal/sft_first_recipe|' && \
	  echo "checkpoints/libero_goal/sft_first_recipe (the first SFT recipe, the folder sft until it was replaced)"

# The imagined route's data on a fresh machine (results/imagined_route.md): the expert demos, the released SFT
# policy's exploration rollouts at three Laplace noise scales (EXPLORE_EPISODES per task: 100 is the 1,000-rollout
# collection, about 8 hours on 2 cores: 2 episodes a minute measured alone), and 3 unseen rollouts per task
# collected apart (seed 1, data/unseen) for the keyframe checks. Every collection resumes episode by episode: the
# same command goes on. EXPLORE_WORKERS=1 leaves a core to a training beside it (the workers do not decide the
# episodes).
EXPLORE_EPISODES ?= 100
EXPLORE_WORKERS ?= 2
exploration: setup
	$(PY) -m stages.collect $(STAGE_ARGS) source=expert post_success_steps=32 workers=2
	$(PY) -m stages.collect $(STAGE_ARGS) source=policy policy_from=checkpoints/$(TASK)/sft \
	  episodes_per_task=$(EXPLORE_EPISODES) 'noise_scale=[1.0,1.6,2.5]' post_success_steps=32 lerobot_export=false \
	  workers=$(EXPLORE_WORKERS)
	$(PY) -m stages.collect +task=$(TASK) scale=$(SCALE) experiment_dir=$(EXP)-unseen data_dir=data/unseen seed=1 \
	  source=policy policy_from=checkpoints/$(TASK)/sft episodes_per_task=3 'noise_scale=[1.0,1.6,2.5]' \
	  post_success_steps=32 lerobot_export=false workers=$(EXPLORE_WORKERS)

# LeRobot's ACT for libero_spatial (checkpoints/README.md): 31.6 MB, so kept in the history, not the tree; extracted
# at its path (git-ignored) from the commit that holds it (a shallow clone needs `git fetch --unshallow` first).
ACT_REV = a7298d5
act-checkpoint:
	@git cat-file -e $(ACT_REV)^{commit} 2>/dev/null || { echo "commit $(ACT_REV) is not in this clone: \
	fetch the full history (git fetch --unshallow) first"; exit 1; }
	@git archive $(ACT_REV) checkpoints/libero_spatial/act_sft | tar -x && echo "checkpoints/libero_spatial/act_sft"

# ACT post-trained (results/lerobot_native.md): ACT's SFT moved by its real-route ES campaign, whose ledger the
# repository keeps (per iteration: contexts, direction seeds, outcomes), so the policy is rebuilt here instead of kept
# as a second 31.6 MB checkpoint (the run's own weights to float32 rounding: at most 3e-8 apart, where ES moved
# them about 1e-2); written at its path (git-ignored).
ACT_LEDGER = results/rl_recipes/es_many_pairs_act_sft_seed0_ledger
ACT_ITERATIONS ?= 20
act-post-trained: setup act-checkpoint
	$(PY) -m analysis.ledger_policy --policy checkpoints/libero_spatial/act_sft --ledger $(ACT_LEDGER) \
	  --upto $(ACT_ITERATIONS) --out checkpoints/libero_spatial/act_post_trained

# The project's libero_spatial SFT post-trained by the real route's ES with the true reward (77.8 % on the 500,
# results/rl_campaign.md), rebuilt from its kept ledger like ACT's (7.4 MB; written at its path, git-ignored).
ES_LEDGER = results/rl_recipes/es_many_pairs_seed0_ledger
es-post-trained: setup
	$(PY) -m analysis.ledger_policy --policy checkpoints/libero_spatial/sft --ledger $(ES_LEDGER) \
	  --upto 20 --out checkpoints/libero_spatial/es_post_trained

# LOOP with the true reward in the real simulator from the released SFT policy (the RL recipe's campaign,
# results/rl_campaign.md): resumable, the same command continues from the last iteration.
# make rl-real TASK=libero_spatial [RECIPE=es_many_pairs SEED=0 RL_ITERATIONS=20 EVAL_EVERY=4 RL_POLICY=... RL_ARGS=...]
# (the default: weight-space ES, 32 pairs on 4 starts of one task an iteration, the tasks in turn, 256 episodes each:
# libero_spatial 57.8 -> 77.8 % after 20 iterations; RECIPE=es_by_task: 8 pairs on 16 starts, 70.6 %; with
# RL_ARGS=rl.es_ledger_from=results/rl_recipes/<run>_ledger: kept current by the run, so a fresh machine goes on from it)
RECIPE ?= es_many_pairs
SEED ?= 0
RL_ITERATIONS ?= 20
EVAL_EVERY ?= 4
RL_ARGS ?=
RL_POLICY ?= checkpoints/$(TASK)/sft
rl-real: setup
	$(PY) -m stages.post_train_loop +task=$(TASK) scale=$(SCALE) experiment_dir=$(EXP) env=real rl=$(RECIPE) \
	  policy_from=$(RL_POLICY) rl.iterations=$(RL_ITERATIONS) eval.every=$(EVAL_EVERY) eval.init_states=0 \
	  eval.validation=100 eval.workers=2 seed=$(SEED) $(RL_ARGS)

# The real-route campaign's figures and tables from what the repository keeps (ledgers under results/rl_recipes/,
# evaluations under results/libero_spatial/): no simulator, a minute. docs/results.md shows them.
SPATIAL_KEPT := results/libero_spatial
SFT_SPATIAL := $(SPATIAL_KEPT)/evaluate-021c9f3e0a3b $(SPATIAL_KEPT)/evaluate-56b93ed13412 $(SPATIAL_KEPT)/evaluate-af65e977e8f9 $(SPATIAL_KEPT)/evaluate-6d17c27737c4
ES_BUDGET := --policy "LOOP (PPO), real simulator" 1280 $(SPATIAL_KEPT)/evaluate-d9a6ed3eb608 \
  --policy "ES one task per iteration" 1280 $(SPATIAL_KEPT)/evaluate-213421144515 \
  --policy "ES one task per iteration" 2560 $(SPATIAL_KEPT)/evaluate-a1679beabb59 \
  --policy "ES one task per iteration" 5120 $(SPATIAL_KEPT)/evaluate-87ee37bbd5f8 \
  --policy "ES 32 pairs on 4 starts, seed 0" 1280 $(SPATIAL_KEPT)/evaluate-738d309c6db6 \
  --policy "ES 32 pairs on 4 starts, seed 0" 2560 $(SPATIAL_KEPT)/evaluate-6a0a84546fe6 \
  --policy "ES 32 pairs on 4 starts, seed 0" 5120 $(SPATIAL_KEPT)/evaluate-58f66194214b \
  --policy "ES 32 pairs on 4 starts, seed 1" 2560 $(SPATIAL_KEPT)/evaluate-07ebdb4d1bb3 \
  --policy "ES 32 pairs on 4 starts, seed 1" 5120 $(SPATIAL_KEPT)/evaluate-73403c6f62a8 \
  --policy "random move, the real route's size" 0 $(SPATIAL_KEPT)/evaluate-770e1227729b \
  --policy "random move, ES one task's size" 0 $(SPATIAL_KEPT)/evaluate-ac139645c064 \
  --policy "random move, ES 32 pairs' size" 0 $(SPATIAL_KEPT)/evaluate-6577d5ecd3d8 \
  --policy "random move, ES 32 pairs' size" 0 $(SPATIAL_KEPT)/evaluate-1b9385e7fb20 \
  --policy "random move, ES 32 pairs' size" 0 $(SPATIAL_KEPT)/evaluate-4cc15e642a96
ES_RUNS := es_by_task_seed0 es_suite_seed0 es_task4_seed0 es_every_task_seed0 es_many_pairs_seed0 es_many_pairs_seed1
rl-figures: setup
	$(PY) -m analysis.budget - --start $(SFT_SPATIAL) $(ES_BUDGET) --json results/rl_recipes/budget_libero_spatial_es.json \
	  --plot docs/img/budget_libero_spatial_es.png --tasks-plot docs/img/tasks_libero_spatial_es.png
	$(PY) -m analysis.rl_curves $(foreach r,$(ES_RUNS),--run $(r)=results/rl_recipes/$(r)_ledger) \
	  --json results/rl_recipes --figure docs/img/rl_curves_es.png --markdown results/rl_recipes/curves_es.md

# The same pipeline on the tiny task and scale, with the imagined route of the peers (keyframes, the guard) and one
# refit round: minutes, proves the plumbing. The tiny models' imagined verdicts all agree, so group filtering would
# drop every group and the guard would never see an update: the smoke keeps every group (rl.filter_groups=false).
# Its refit round keeps the reflector's eta.
# LOOP's own real evaluations (eval.every; tested in tests/stages/post_train_loop) are left to the evaluate stage
# after it: they were most of the smoke's LOOP time, and CI is kept under 25 minutes.
SMOKE_ROUTE = IMAGINATION=keyframes LOOP_ARGS="rl.filter_groups=false eval.every=0"
smoke:
	$(MAKE) pipeline TASK=tiny SCALE=tiny EXP=outputs/smoke $(SMOKE_ROUTE)
	$(MAKE) refit TASK=tiny SCALE=tiny EXP=outputs/smoke $(SMOKE_ROUTE) REFIT_EPISODES=1 \
	  REFIT_REFLECTOR_ARGS=eta_folds=0

# Training curves of every run of an experiment (TensorBoard event files in each run's work dir).
tensorboard: setup
	$(VENV)/bin/tensorboard --logdir $(EXP) --port $${PORT:-6006}

bench: setup
	$(PY) -m benchmarks.bench

# What each training stage costs per step at scale=small and scale=paper on this machine, and the
# hours a whole run needs (docs/scaling.md#what-paper-scale-costs).
cost-model: setup
	$(PY) -m benchmarks.training_cost --scales small paper --json docs/cost_model.json

clean:
	rm -rf outputs/* data/*
