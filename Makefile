# kpcn: every target creates the environment it needs first, so each works on a fresh clone.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
KPCN   := $(BIN)/kpcn
SET    ?= default
RUN    ?= default
# extra options for each stage, e.g. make train TRAIN_ARGS="--steps 2000"
RENDER_ARGS ?=
SHARD_ARGS  ?=
TRAIN_ARGS  ?=
RESAMPLE_ARGS ?=
STUDY_ARGS  ?=
INPUTS_ARGS ?=
COMPARE_ARGS ?=
BENCH_ARGS  ?=
# the shipped model, its configuration in one place: make model trains it (every input set) into $(MODEL_RUN),
# evaluates it and ships it to models/$(MODEL), the model 'kpcn denoise' uses without --run. MODEL is
# kpcn_keras/config.py's DEFAULT_MODEL; VALIDATION, other renderers' frames (kpcn_keras/studies/config.py's
# VALIDATION_FRAMES, as make quality measures them), is evaluated where it is there.
# MODEL_ARGS must suit every input set (no --shared or --compositor: a no-split network has one branch).
# It trains on the quality study's data lever (kpcn_keras/studies/config.py MORE_DATA: 8 scenes per family,
# inputs 2-64 spp), the set make quality renders as $(MODEL_SET), held out the scenes make train holds out.
MODEL      ?= $(shell sed -n 's/^DEFAULT_MODEL = "\(.*\)".*/\1/p' kpcn_keras/config.py)
# As long as held-out error falls: each network stops 20 epochs (1000 steps) after its best and keeps it; 12000
# steps is a cap (where the shipped networks stopped: their card, docs/results/13-training-longer.md). Without synthetic fireflies:
# the shipped networks were trained so (make model-tune adds them), and make model resumes them
MODEL_ARGS ?= --preset cpu --steps 12000 --decay-steps 12000 --patience 20 --fireflies 0
MODEL_RUN  ?= runs/model
MODEL_SET  ?= $(SET)-r14bdd0f2
MODEL_RENDER_ARGS ?= --per-family 8 --input-spp 2,4,8,16,32,64
MODEL_SHARD_ARGS  ?= --val-scenes $(subst $(eval) ,$(comma),$(foreach f,boxes caustics cornell fireflies indirect outdoor spheres textures,$(f)-002))
comma := ,
VALIDATION ?= $(shell sed -n 's/^VALIDATION_FRAMES = (\(.*\))/\1/p' kpcn_keras/studies/config.py | tr -d '",')

QUALITY_ARGS ?=

.PHONY: addon world world-set world-tune modes ship-modes cycles-dev blender-report adapt-report aux-study modes-report cycles-validation model-speed venv render references shards train train-inputs model model-tune resample resample-study inputs-study quality evaluate figures compare bench test test-all test-oldest clean docs time-train

# torch is pinned for installs (constraints.txt) to the local CPU build; pyproject states the range.
$(KPCN): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --disable-pip-version-check -c constraints.txt -e '.[test]'
	touch $(KPCN)

venv: $(KPCN)

render: $(KPCN)
	$(KPCN) render --set $(SET) $(RENDER_ARGS)

# how converged the set's references are: data/renders/$(SET)/convergence.{md,json,png}
references: render
	$(KPCN) references --set $(SET)

shards: render
	$(KPCN) shards --set $(SET) $(SHARD_ARGS)

train: shards
	$(KPCN) train --set $(SET) --run runs/$(RUN) $(TRAIN_ARGS)
	$(KPCN) evaluate --run runs/$(RUN)
	$(KPCN) figures --run runs/$(RUN)

# a network for each input set but the full one (docs/training.md §6), for renders without a diffuse/specular
# split or variance layers: shards/$(SET).<inputs> and runs/$(RUN)/inputs/<inputs>; the names from prep/inputs.py
train-inputs: render
	for inputs in $$($(BIN)/python -c 'from prep.inputs import INPUT_SETS; print(*INPUT_SETS[1:])'); do \
		$(KPCN) shards --set $(SET) --inputs $$inputs $(SHARD_ARGS) && \
		$(KPCN) train --set $(SET) --run runs/$(RUN) --inputs $$inputs $(TRAIN_ARGS) || exit 1; \
	done

# the shipped model (docs/training.md §7): one command trains it, resuming an interrupted training where it stopped
# (a run folder resumes by itself), then evaluates it and ships it with its card; run it again after an interrupt
model: $(KPCN)
	$(BIN)/pip install --quiet --disable-pip-version-check -c constraints.txt -e '.[oidn]' || \
		echo "kpcn: pyoidn not installed: the model's tables go without OIDN"
	$(KPCN) render --set $(MODEL_SET) $(MODEL_RENDER_ARGS)
	for inputs in $$($(BIN)/python -c 'from prep.inputs import INPUT_SETS; print(*INPUT_SETS)'); do \
		$(KPCN) shards --set $(MODEL_SET) --inputs $$inputs $(MODEL_SHARD_ARGS) && \
		$(KPCN) train --set $(MODEL_SET) --run $(MODEL_RUN) --inputs $$inputs $(MODEL_ARGS) || exit 1; \
	done
	$(call evaluate_and_ship,$(MODEL_RUN))

# a model run $(1) evaluated on the held-out and the VALIDATION frames and shipped to models/$(MODEL)
define evaluate_and_ship
	$(KPCN) evaluate --run $(1)
	frames=$$(for f in $(VALIDATION); do [ -e "$$f" ] && echo "$$f"; done); \
	if [ -n "$$frames" ]; then $(KPCN) evaluate --run $(1) --out $(1)/eval-validation $$frames; fi
	$(KPCN) ship --run $(1) --out models/$(MODEL)
endef

# after make model: the fine-tuning that makes the shipped model (docs/training.md §7), each network trained on
# from make model's own (--init $(MODEL_RUN)) where a measurement found it gains (docs/results/17-cycles-fine-tuning.md, docs/results/18-synthetic-fireflies.md):
# - the full network with synthetic fireflies (the default) at a low learning rate, then its albedo network
#   (TUNE_ARGS; docs/results/20-albedo-network.md) into $(MODEL_RUN)-tuned;
# - the no-variance network, the one that denoises Blender Cycles' frames (Cycles writes no variance), on Cycles'
#   own frames too: random scenes rendered by kpcn render-cycles with bpy in a venv of its own ($(BPY_VENV): bpy
#   5.0.1 wants Python 3.11 and numpy < 2) into data/cycles/$(CYCLES_SET), made a render set by kpcn
#   import-renders, joined with $(MODEL_SET)'s
#   renders as $(MODEL_SET)-$(CYCLES_SET), cut without variance, trained into $(MODEL_RUN)-$(CYCLES_SET).
# $(MODEL_RUN)-shipped is the tuned full run with make model's no-split networks and the Cycles-trained
# no-variance one in its inputs/ (hard links), evaluated and shipped. Each step resumes or is skipped when done;
# more scenes (--scenes) mean a new CYCLES_SET.
TUNE_ARGS  ?= --preset cpu --lr 3e-4 --steps 6000 --decay-steps 6000 --albedo-steps 3000
BPY_PYTHON ?= python3.11
BPY_VENV   := .venv-bpy
# the add-on is tested in CI on bpy 5.0.1; BPY_VERSION=4.5.3 (in a clone of its own) runs its tests on Blender 4.5
BPY_VERSION ?= 5.0.1
CYCLES_SET ?= cycles
CYCLES_RENDER_ARGS ?= --scenes 0:48 --res 128 --spp 4,8,16,32,64 --ref-spp 2048
CYCLES_VAL_SCENES  ?= room-024,studio-025,ground-026
CYCLES_TRAIN_ARGS  ?= --preset cpu --lr 3e-4 --steps 6000 --decay-steps 6000
MODEL_MIX := $(MODEL_SET)-$(CYCLES_SET)

$(BPY_VENV)/bin/python:
	$(BPY_PYTHON) -m venv $(BPY_VENV)
	$(BPY_VENV)/bin/pip install --quiet --disable-pip-version-check 'numpy<2' 'bpy==$(BPY_VERSION)'

model-tune: $(KPCN) $(BPY_VENV)/bin/python
	$(KPCN) train --set $(MODEL_SET) --inputs full --run $(MODEL_RUN)-tuned --init $(MODEL_RUN) $(TUNE_ARGS)
	$(KPCN) render-cycles data/cycles/$(CYCLES_SET) --blender-python $(BPY_VENV)/bin/python $(CYCLES_RENDER_ARGS)
	[ -d data/renders/$(CYCLES_SET) ] || $(KPCN) import-renders data/cycles/$(CYCLES_SET) --set $(CYCLES_SET)
	mkdir -p data/renders/$(MODEL_MIX)
	ln -f data/renders/$(MODEL_SET)/*.exr data/renders/$(CYCLES_SET)/*.exr data/renders/$(MODEL_MIX)/
	$(KPCN) shards --set $(MODEL_MIX) --inputs no-variance $(MODEL_SHARD_ARGS),$(CYCLES_VAL_SCENES)
	$(KPCN) train --set $(MODEL_MIX) --inputs no-variance --run $(MODEL_RUN)-$(CYCLES_SET) --init $(MODEL_RUN) \
		$(CYCLES_TRAIN_ARGS)
	rm -rf $(MODEL_RUN)-shipped && cp -al $(MODEL_RUN)-tuned $(MODEL_RUN)-shipped
	rm -rf $(MODEL_RUN)-shipped/eval $(MODEL_RUN)-shipped/eval-validation && mkdir $(MODEL_RUN)-shipped/inputs
	cp -al $(MODEL_RUN)/inputs/no-split $(MODEL_RUN)/inputs/no-split-no-variance $(MODEL_RUN)-shipped/inputs/
	cp -al $(MODEL_RUN)-$(CYCLES_SET)/inputs/no-variance $(MODEL_RUN)-shipped/inputs/
	$(call evaluate_and_ship,$(MODEL_RUN)-shipped)

# The Cycles world (docs/training.md §6): scenes of the effect catalogue rendered by kpcn render-cycles into
# $(WORLD), growing run after run: stop it any time, the same command goes on where it stopped.
WORLD ?= data/cycles/world
WORLD_RENDER_ARGS ?= --scenes 0:400 --res 128 --spp 4,16,64 --ref-spp 1024
world: $(KPCN) $(BPY_VENV)/bin/python
	$(KPCN) render-cycles $(WORLD) --blender-python $(BPY_VENV)/bin/python $(WORLD_RENDER_ARGS)

# The shipped model's no-variance network (the one that serves Cycles frames) trained on from where it is, on the
# world's finished scenes beside make model's renders, as long as the held-out error falls (early stopping keeps
# the best). The finished scenes become render set world-<N>; WORLD_SET names an earlier one, to resume its
# training after the world grew. Held out: make model's scenes and every eighth of the world's (the first, the
# ninth, ...). The run is runs/$(WORLD_SET); docs/training.md §6. WORLD_BESIDE= (empty) trains on the world alone.
WORLD_SET ?= world-$(shell $(BIN)/python -c 'import sys; from prep.imported import finished_scenes; print(len(finished_scenes(sys.argv[1])))' $(WORLD) 2>/dev/null)
WORLD_TRAIN_ARGS ?= --preset cpu --lr 3e-4 --steps 12000 --decay-steps 12000 --patience 20
WORLD_BESIDE ?= $(MODEL_SET)
WORLD_MIX := $(if $(WORLD_BESIDE),$(WORLD_BESIDE)-)$(WORLD_SET)
WORLD_HELD_OUT = $(if $(WORLD_BESIDE),$(filter-out --val-scenes,$(MODEL_SHARD_ARGS)))
WORLD_VAL_SCENES = --val-scenes $$(echo $(WORLD_HELD_OUT) \
		$$(ls data/renders/$(WORLD_SET) | sed -n 's/-[0-9]*spp.exr$$//p' | sort -u | awk 'NR % 8 == 1') \
		| tr ' ' '\n' | grep . | paste -sd,)
# the world's finished scenes as render set $(WORLD_SET), beside $(WORLD_BESIDE)'s renders as $(WORLD_MIX)
world-set: $(KPCN)
	$(if $(WORLD_BESIDE),$(KPCN) render --set $(WORLD_BESIDE) $(MODEL_RENDER_ARGS))
	[ -d data/renders/$(WORLD_SET) ] || $(KPCN) import-renders $(WORLD) --set $(WORLD_SET)
	$(if $(WORLD_BESIDE),mkdir -p data/renders/$(WORLD_MIX) && \
		ln -f data/renders/$(WORLD_BESIDE)/*.exr data/renders/$(WORLD_SET)/*.exr data/renders/$(WORLD_MIX)/)

world-tune: world-set
	$(KPCN) shards --set $(WORLD_MIX) --inputs no-variance $(WORLD_VAL_SCENES)
	$(KPCN) train --set $(WORLD_MIX) --inputs no-variance --run runs/$(WORLD_SET) --init models/default \
		$(WORLD_TRAIN_ARGS)

# The quality modes besides balanced (make model's networks; kpcn denoise --quality, docs/training.md §7): each mode's
# networks trained from its preset on its auxiliaries (config.QUALITY_PRESETS, config.QUALITY_AUXILIARIES; high from
# the shipped networks, config.QUALITY_INIT) into
# $(MODEL_RUN)-<mode> ($(MODEL_RUN)-<mode>-aux-<method> where they are prefiltered), for every input set, as long as
# the held-out error falls; the no-variance networks, which serve Cycles frames, first and on the Cycles world beside
# make model's renders (make world-tune's set, $(WORLD_MIX): WORLD_SET=world-<N> resumes one after the world grew),
# the others on make model's. Each set is cut once for each auxiliaries a mode asks for. Resumes where it stopped.
# make ship-modes then ships them into models/$(MODEL) beside its balanced networks.
MODES ?= fast high
MODES_ARGS ?= --steps 12000 --decay-steps 12000 --patience 20
# shell words: a mode's auxiliaries method (its value in config.QUALITY_AUXILIARIES) and its run folder
mode_aux = $$($(BIN)/python -c 'import sys; from kpcn_keras.config import QUALITY_AUXILIARIES as a; print(a[sys.argv[1]])' $(1))
mode_run = $(MODEL_RUN)-$(1)$$(aux=$(call mode_aux,$(1)); [ $$aux = raw ] || echo -aux-$$aux)
mode_preset = $$($(BIN)/python -c 'import sys; from kpcn_keras.config import QUALITY_PRESETS as p; print(p[sys.argv[1]])' $(1))
# --init models/$(MODEL) for a mode that starts from the shipped networks (config.QUALITY_INIT), nothing otherwise
mode_init = $$($(BIN)/python -c 'import sys; from kpcn_keras.config import QUALITY_INIT as i; sys.argv[1] in i and print("--init", sys.argv[2])' $(1) models/$(MODEL))
# true for a mode mixed with OIDN's frame (config.QUALITY_OIDN_MIX): its weight is fit on MIX_FRAMES, frames of
# scenes neither trained on nor judged: a draw of the Cycles validation split apart from the judged one (make
# cycles-dev) for the networks that serve Cycles frames, make model's held-out scenes' inputs for the full ones;
# MIX_FRAMES= (empty) leaves the mode unmixed
mode_mixed = $(BIN)/python -c 'import sys; from kpcn_keras.config import QUALITY_OIDN_MIX as m; sys.exit(sys.argv[1] not in m)' $(1)
CYCLES_DEV ?= data/cycles/dev
MIX_FRAMES ?= $(CYCLES_DEV) $(wildcard $(foreach s,$(subst $(comma), ,$(filter-out --val-scenes,$(MODEL_SHARD_ARGS))),data/renders/$(MODEL_SET)/$(s)-000[0-6][0-9]spp.exr))
modes: world-set $(if $(filter $(CYCLES_DEV),$(MIX_FRAMES)),cycles-dev)
	for inputs in no-variance $$($(BIN)/python -c 'from prep.inputs import INPUT_SETS; print(*INPUT_SETS)' \
			| tr ' ' '\n' | grep -vx no-variance); do \
		if [ $$inputs = no-variance ]; then set=$(WORLD_MIX); held="$(WORLD_VAL_SCENES)"; \
		else set=$(MODEL_SET); held="$(MODEL_SHARD_ARGS)"; fi; \
		for mode in $(MODES); do \
			$(KPCN) shards --set $$set --inputs $$inputs $$held --auxiliaries $(call mode_aux,$$mode) || exit 1; \
			$(KPCN) train --set $$set --run $(call mode_run,$$mode) --inputs $$inputs \
				--auxiliaries $(call mode_aux,$$mode) --preset $(call mode_preset,$$mode) $(call mode_init,$$mode) \
				$(MODES_ARGS) || exit 1; \
		done; \
	done
	for mode in $(MODES); do \
		$(if $(MIX_FRAMES),! $(call mode_mixed,$$mode) || $(KPCN) mix-oidn --run $(call mode_run,$$mode) $(MIX_FRAMES) || exit 1;) \
		$(KPCN) evaluate --run $(call mode_run,$$mode) || exit 1; \
	done

# the trained modes shipped beside models/$(MODEL)'s balanced networks: the model as it is (hard links, in
# runs/$(MODEL)-balanced) shipped again with them over models/$(MODEL), which kpcn ship replaces whole or not at all
ship-modes: $(KPCN)
	rm -rf runs/$(MODEL)-balanced && mkdir -p runs && cp -al models/$(MODEL) runs/$(MODEL)-balanced
	$(KPCN) ship --run runs/$(MODEL)-balanced $$(for mode in $(MODES); do echo --mode $$mode=$(call mode_run,$$mode); done) \
		--out models/$(MODEL)

# error-based resampling rounds on the trained run (RESAMPLE_ARGS="--rounds 5"); it continues runs/$(RUN)
resample: shards
	$(KPCN) train --set $(SET) --run runs/$(RUN) $(TRAIN_ARGS)
	$(KPCN) resample --run runs/$(RUN) $(RESAMPLE_ARGS)
	$(KPCN) evaluate --run runs/$(RUN)
	$(KPCN) figures --run runs/$(RUN)

# error rounds against variance sampling alone, several seeds: reports/resample.{md,json,png}
resample-study: shards
	$(KPCN) resample-study --set $(SET) $(STUDY_ARGS)

# a network per input set for the same seconds (INPUTS_ARGS="--budget 300 --frames DIR ..."), on held-out frames
# and other renderers' frames beside OIDN and Blender: reports/inputs.{md,json,png}
inputs-study: shards
	$(BIN)/pip install --quiet --disable-pip-version-check -c constraints.txt -e '.[oidn]'
	$(KPCN) inputs-study --set $(SET) $(INPUTS_ARGS)

# each lever for beating OIDN, alone and combined, for the same seconds (QUALITY_ARGS="--budget 600 --levers ..."),
# on held-out frames and the validation frames (../shared/validation/blender, ../shared/fixtures/mitsuba) beside
# OIDN and Blender's own denoiser: reports/quality.{md,json,png}; a lever with a render set of its own renders it
quality: shards
	$(BIN)/pip install --quiet --disable-pip-version-check -c constraints.txt -e '.[oidn]'
	$(KPCN) quality --set $(SET) $(QUALITY_ARGS)

# the held-out Cycles validation set (kpcn cycles-validation: 12 scenes of the catalogue's validation split, inputs
# at 4, 16, 64 spp, Blender's own denoised frame of each, 2048-spp references, the sha256 of each file in its
# manifest): rendered where it is missing, resumed where it stopped, then checked against its checksums
CYCLES_VALIDATION ?= data/cycles/validation
CYCLES_VALIDATION_ARGS ?=
cycles-validation: $(KPCN) $(BPY_VENV)/bin/python
	$(KPCN) cycles-validation $(CYCLES_VALIDATION) --blender-python $(BPY_VENV)/bin/python $(CYCLES_VALIDATION_ARGS)
	$(KPCN) cycles-validation $(CYCLES_VALIDATION) --verify

# another draw of the validation split, for what is designed or fit on Cycles frames (the OIDN mix's weight, the
# adaptation guard): 8 scenes at 16 spp, each with Blender's own denoised frame, never a scene of the judged set
cycles-dev: $(KPCN) $(BPY_VENV)/bin/python
	$(KPCN) cycles-validation $(CYCLES_DEV) --blender-python $(BPY_VENV)/bin/python --seed 1 --scenes 8 --spp 16
	$(KPCN) cycles-validation $(CYCLES_DEV) --verify

# the shipped model (BLENDER_ARGS="--model before=models/default --model after=RUN" for several) on the held-out
# Cycles validation set (rendered first where it is not there) beside Blender's own denoised frame and both OIDN
# modes: reports/blender.{md,json,png}. BLENDER_FRAMES=../shared/validation/blender is the further check.
BLENDER_FRAMES ?= $(CYCLES_VALIDATION)
blender-report: $(KPCN) $(if $(filter $(CYCLES_VALIDATION),$(BLENDER_FRAMES)),cycles-validation)
	$(BIN)/pip install --quiet --disable-pip-version-check -c constraints.txt -e '.[oidn]'
	$(BIN)/python -m kpcn_keras.studies.blender_report $(BLENDER_FRAMES) $(BLENDER_ARGS)

# the shipped model adapted to each Cycles validation frame's two halves (10, 30, 60, 120 s of one run; at 16, then 4
# and 64 spp) beside Blender's own denoiser on one render of all the samples, the targets checked, what adapting
# costs at 1920x1080; then the same on kpcn's own scenes in pairs (ADAPT_PROJECT: one scene per family at a seed no
# model trained on, rendered here) against the better OIDN mode: reports/adapt.{md,json,png}. Long (2+ minutes a
# frame); run again, it resumes (the renders too).
ADAPT_ARGS ?=
ADAPT_PROJECT_SEED ?= 53
ADAPT_PROJECT ?= data/renders/adapt-project
adapt-report: $(KPCN) cycles-validation
	$(BIN)/pip install --quiet --disable-pip-version-check -c constraints.txt -e '.[oidn]'
	$(KPCN) render --set $(notdir $(ADAPT_PROJECT)) --out $(patsubst %/,%,$(dir $(ADAPT_PROJECT))) --pair --input-spp 16 --per-family 1 \
		--seed $(ADAPT_PROJECT_SEED)
	$(BIN)/python -m kpcn_keras.studies.adapt_report $(CYCLES_VALIDATION) --more $(ADAPT_PROJECT) $(ADAPT_ARGS)

# the shipped model (AUX_ARGS="--model RUN" for another) on the held-out Cycles validation set with its auxiliary
# inputs raw, from the scene's 64-spp render (the oracle), OIDN-prefiltered and NLM-prefiltered, beside Blender's own
# denoised frame: reports/aux.{md,json,png} (docs/results/26-clean-auxiliaries.md)
aux-study: $(KPCN) cycles-validation
	$(BIN)/pip install --quiet --disable-pip-version-check -c constraints.txt -e '.[oidn]'
	$(KPCN) aux-study $(CYCLES_VALIDATION) $(AUX_ARGS)

# kpcn's quality modes beside OIDN's: each mode of models/$(MODEL) and OIDN at fast, balanced and high (prefiltered
# and plain) timed on a 1920x1080 frame made of SPEED_SOURCE, in one process, alternately (run it on an idle machine:
# it is a timing): reports/mode_costs.json; then error (reports/blender.json, from make blender-report with
# BLENDER_ARGS="--model default=models/$(MODEL)") against those seconds: reports/modes.{png,json}
modes-report: $(KPCN)
	$(BIN)/pip install --quiet --disable-pip-version-check -c constraints.txt -e '.[oidn]'
	$(BIN)/python -m kpcn_keras.studies.mode_costs --model models/$(MODEL) --frame $(SPEED_SOURCE) --out reports/mode_costs.json
	$(BIN)/python -m kpcn_keras.studies.modes_plot --costs reports/mode_costs.json --errors reports/blender.json --out reports

evaluate: $(KPCN)
	$(KPCN) evaluate --run runs/$(RUN)

figures: $(KPCN)
	$(KPCN) figures --run runs/$(RUN)

# every configuration for the same training seconds (COMPARE_ARGS="--budget 60"): reports/compare.{md,json,png};
# with Intel Open Image Denoise (the optional extra pyoidn) as the row to beat
compare: shards
	$(BIN)/pip install --quiet --disable-pip-version-check -c constraints.txt -e '.[oidn]'
	$(KPCN) compare --set $(SET) $(COMPARE_ARGS)

# what accuracy costs in time: reports/accuracy_time.{md,json,png} (BENCH_ARGS="--full" for the full ladder);
# with Intel Open Image Denoise (the optional extra pyoidn) as the curve to beat
bench: shards
	$(BIN)/pip install --quiet --disable-pip-version-check -c constraints.txt -e '.[oidn]'
	$(KPCN) bench --set $(SET) $(BENCH_ARGS)

# the fast suite: every test not marked slow, one worker process per core, each taking whole test files (a
# file's module fixtures are built once) in the order of tests/conftest.py, longest first
PYTEST_PARALLEL := -n auto --dist loadfile --no-loadscope-reorder
test: $(KPCN)
	$(BIN)/python -m pytest -q $(PYTEST_PARALLEL) -m "not slow"

# everything, the slow tests too (subprocesses, kills and resumes, trainings, renders, kernel compiles): what CI runs
test-all: $(KPCN)
	$(BIN)/python -m pytest -q $(PYTEST_PARALLEL) --durations=30

# the training tests on the oldest Keras that pyproject.toml allows, in an environment of its own
KERAS_OLDEST := $(shell sed -n 's/.*"keras>=\([0-9.]*\)".*/\1/p' pyproject.toml)
# .venv's packages (torch among them) are seen from .venv-oldest through a .pth file, after its own: pip installs
# the oldest keras (and what it needs otherwise) into .venv-oldest alone and leaves .venv as it is
test-oldest: $(KPCN)
	$(PYTHON) -m venv .venv-oldest
	$(BIN)/python -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])' > \
		"$$(.venv-oldest/bin/python -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')/kpcn-venv.pth"
	.venv-oldest/bin/pip install --quiet --disable-pip-version-check -c constraints.txt 'keras==$(KERAS_OLDEST)' -e '.[test]'
	.venv-oldest/bin/python -c 'from importlib.metadata import version as v; from packaging.version import Version as V; assert V(v("keras")) == V("$(KERAS_OLDEST)"), v("keras")'
	.venv-oldest/bin/python -m pytest -q $(PYTEST_PARALLEL) tests/test_train.py tests/test_models.py tests/test_layers.py tests/test_train_phases.py tests/test_albedo_network.py

clean:
	rm -rf data runs shards/*/

# the Blender add-on (blender/kpcn_addon, docs/blender.md) as the extension zip Blender 4.2+ installs:
# $(ADDON_DIST)/kpcn-blender-<version>.zip, the version from its blender_manifest.toml (the standard library alone)
ADDON_DIST ?= dist
addon:
	$(PYTHON) blender/build.py --out $(ADDON_DIST)

# every subcommand's --help written into docs/commands.md §4 (tests/test_docs.py checks it is up to date)
docs: $(KPCN)
	$(BIN)/python -m kpcn_keras.helpdoc

# make train timed from a fresh clone of the committed HEAD, nothing reused: reports/make_train.{json,md},
# the figure the README gives for it (it takes as long as make train)
time-train: $(KPCN)
	$(BIN)/python -m kpcn_keras.studies.fresh_clone --out reports

# the speed section of the shipped model's card timed again on this machine (idle: it is a timing), kpcn beside OIDN
# on a 1920x1080 frame made of SPEED_SOURCE: models/$(MODEL)/speed.json and the card's speed section
SPEED_SOURCE ?= tests/fixtures/fixture-00008spp.exr
model-speed: $(KPCN)
	$(BIN)/pip install --quiet --disable-pip-version-check -c constraints.txt -e '.[oidn]'
	$(BIN)/python -m kpcn_keras.studies.card_speed --model models/$(MODEL) --frame $(SPEED_SOURCE)
