"""The fixtures shared by the test files; the helpers they use are in the ``helpers`` package, one module per job."""

import os
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

os.environ.setdefault("KERAS_BACKEND", "torch")
# one all-effects kernel compiled for every scene rather than one per effect set, in this process and in the
# commands it starts (docs/scenes.md §2); the tests of specialisation name their kernel's effects
os.environ.setdefault("KPCN_KERNELS", "all")
# make test and make test-all run a worker per core: OpenMP threads (torch's) that spin while they wait would
# take the cores from the other workers (it does not change a result)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from helpers.commands import process_state_kept  # noqa: E402
from helpers.files import SmallDisk  # noqa: E402
from helpers.malformed import SCALE as FUZZ_SCALE  # noqa: E402
from helpers.paths import FIXTURES  # noqa: E402
from helpers.tiny import TINY_MODEL, build_tiny_shards  # noqa: E402

# The property tests' budgets (tests/test_fuzz_properties.py; helpers.malformed.PROFILE picks one): ci, a fixed
# set of examples the same on every run; deep, ten times as many drawn afresh (KPCN_FUZZ_SCALE multiplies them)
_FUZZ_COMMON = dict(deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("ci", max_examples=30, derandomize=True, **_FUZZ_COMMON)
settings.register_profile("deep", max_examples=300 * FUZZ_SCALE, **_FUZZ_COMMON)

# the files that take longest from a fresh clone, longest first; the rest follow in collection order. The
# workers (pytest-xdist, --dist loadfile --no-loadscope-reorder) take whole files in this order, so that none is
# left alone at the end on a long one
LONGEST_FIRST = ("test_resample_resume.py", "test_cli_resume.py", "test_distributed.py", "test_render.py",
                 "test_resample.py", "test_shard_set.py", "test_kernels.py", "test_parts.py", "test_train.py",
                 "test_run.py", "test_train_phases.py", "test_bench.py")


def pytest_sessionstart(session):
    """The library's numba functions compiled into numba's disk cache once, here, before the workers start
    (helpers.compiled): from a fresh clone every worker and every kpcn process started before the cache is
    written would compile each again, the albedo prefilter over a minute on two loaded cores. The all-effects
    render kernel (half a minute) only where the slow tests run, which render."""
    if hasattr(session.config, "workerinput"):
        return
    from helpers.compiled import compile_all

    compile_all(render="not slow" not in (session.config.option.markexpr or ""))


def pytest_collection_modifyitems(items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: a file keeps its order


@pytest.fixture
def fixture_noisy() -> Path:
    return FIXTURES / "fixture-00008spp.exr"


@pytest.fixture
def fixture_reference() -> Path:
    return FIXTURES / "fixture-01024spp.exr"


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """A run folder with both branches of a tiny KPCN trained for a few steps on random renders."""
    from kpcn_keras.train import TrainConfig, train

    tmp = tmp_path_factory.mktemp("run")
    shard_cfg = build_tiny_shards(tmp)
    cfg = TrainConfig.from_preset(
        "cpu", set_name="s", shards_root=shard_cfg.out_root,
        model=TINY_MODEL, steps=8, steps_per_epoch=4, batch_size=2, val_batches=1,
    )
    return train(cfg, tmp / "runs" / "r", verbose=0)


@pytest.fixture(scope="session")
def tiny_slope_module_run(tmp_path_factory):
    """A run folder of a tiny KPCN with λ maps joined after the trunk (``--slope-module 1``), trained for a few
    steps on random renders."""
    from kpcn_keras.train import TrainConfig, train

    tmp = tmp_path_factory.mktemp("slope-module")
    shard_cfg = build_tiny_shards(tmp)
    cfg = TrainConfig.from_preset(
        "cpu", set_name="s", shards_root=shard_cfg.out_root, model={**TINY_MODEL, "slope_module": 1},
        loss="asymmetric", slope_input=True, steps=4, steps_per_epoch=4, batch_size=2, val_batches=1,
    )
    return train(cfg, tmp / "runs" / "r", verbose=0)


@pytest.fixture(scope="session")
def tiny_slope_mixture_run(tmp_path_factory):
    """A run folder of a tiny KPCN whose module mixes two kernels by λ (``--slope-module 1 --slope-mixture 2``),
    trained for a few steps on random renders."""
    from kpcn_keras.train import TrainConfig, train

    tmp = tmp_path_factory.mktemp("slope-mixture")
    shard_cfg = build_tiny_shards(tmp)
    cfg = TrainConfig.from_preset(
        "cpu", set_name="s", shards_root=shard_cfg.out_root,
        model={**TINY_MODEL, "slope_module": 1, "slope_mixture": 2}, loss="asymmetric", slope_input=True, steps=4,
        steps_per_epoch=4, batch_size=2, val_batches=1,
    )
    return train(cfg, tmp / "runs" / "r", verbose=0)


@pytest.fixture(scope="session")
def tiny_run_of_every_input_set(tmp_path_factory):
    """A tiny run with a variant for every other input set in its ``inputs/`` folder: what ``make train`` and
    ``make train-inputs`` make, at toy size, so that a frame of any layout finds its model."""
    from kpcn_keras.train import TrainConfig, train
    from prep import shards
    from prep.inputs import INPUT_SETS

    tmp = tmp_path_factory.mktemp("variants")
    full = build_tiny_shards(tmp)
    run = tmp / "runs" / "r"
    for name in INPUT_SETS:
        if name != "full":
            shards.build_shards(shards.ShardConfig(**{**full.to_dict(), "inputs": name}), progress=False)
        cfg = TrainConfig.from_preset("cpu", set_name="s", shards_root=full.out_root, model=TINY_MODEL, steps=4,
                                      steps_per_epoch=4, batch_size=2, val_batches=1, inputs=name)
        train(cfg, run, verbose=0)
    return run


@pytest.fixture
def small_disk(tmp_path):
    """A full disk: :class:`SmallDisk` at ``tmp_path/disk`` (root only; the test is skipped, saying why,
    where mounting is not permitted)."""
    disk = SmallDisk(tmp_path / "disk")
    yield disk
    disk.unmount()


@pytest.fixture(autouse=True)
def _process_state_put_back():
    """Every test leaves the process as it found it, ``cli.main`` called directly included: a thread request
    left behind would make every later in-process shard build of the worker start that many processes, each
    importing the stack again. A request already set here was left by a fixture of a wider scope."""
    from prep import threads

    assert threads.requested() is None, f"a fixture left prep.threads.requested() = {threads.requested()!r}"
    with process_state_kept():
        yield
