"""Data-parallel training: the launcher's environment read into a World, and gradients averaged
over processes so that two processes on halves of a batch train what one process trains on all of it."""

import json
import os
import socket
import subprocess
from pathlib import Path

import numpy as np
import pytest
from helpers.commands import WarmProcess, launcher_free_env, torchrun
from helpers.paths import REPO

from kpcn_keras import distributed


# One process of a data-parallel run of a small branch network (``steps`` Adam steps on its slice of a fixed
# global batch of 4), or, with WORLD_SIZE unset, the one-process run on the whole batch. Each rank initialises
# from its own seed: broadcast_weights must make them start equal.
def train_steps(out: str, steps: int = 3) -> None:
    import keras
    import torch

    from kpcn_keras.config import ModelConfig
    from kpcn_keras.losses import SMAPE
    from kpcn_keras.models import build_branch_model

    world = distributed.from_environment()
    distributed.start(world)
    torch.set_num_threads(1)
    keras.utils.set_random_seed(7 + world.rank)
    cfg = ModelConfig(width=6, depth=2, kernel_size=3)
    model = build_branch_model(cfg)
    distributed.broadcast_weights(model, world)
    distributed.average_gradients(model, world)
    model.compile(optimizer=keras.optimizers.Adam(1e-2), loss=SMAPE())
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 2, (4, 12, 12, cfg.input_channels)).astype("float32")
    y = rng.uniform(0, 2, (4, 12, 12, 3)).astype("float32")
    per = 4 // world.size
    mine = slice(world.rank * per, (world.rank + 1) * per)
    for _ in range(steps):
        model.train_on_batch(x[mine], y[mine])
    np.savez(out, *[np.asarray(w.numpy()) for w in model.weights])
    distributed.stop(world)


def _processes(target, args_of_rank, env) -> None:
    """``target(*args_of_rank[r])`` as rank r of a gloo world of ``len(args_of_rank)`` processes (one process
    outside any world if it is 1), each a process of its own; fails with the output of one that fails."""
    size = len(args_of_rank)
    rendezvous = {} if size == 1 else {"MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(_free_port()),
                                        "WORLD_SIZE": str(size)}
    ranks = [{"RANK": str(r), "LOCAL_RANK": str(r)} if size > 1 else {} for r in range(size)]
    procs = [WarmProcess(target, args, cwd=REPO, env={**env, **rendezvous, **rank})
             for args, rank in zip(args_of_rank, ranks)]
    for p in procs:
        out, _ = p.communicate(timeout=300)
        assert p.returncode == 0, out[-3000:]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _weights(path) -> list[np.ndarray]:
    with np.load(path) as z:
        return [z[k] for k in sorted(z.files, key=lambda k: int(k.split("_")[1]))]


@pytest.mark.slow
def test_two_gloo_processes_on_halves_of_a_batch_train_what_one_process_trains_on_all_of_it(tmp_path):
    env = launcher_free_env(KERAS_BACKEND="torch")
    _processes(train_steps, [(str(tmp_path / "one.npz"),)], env)
    _processes(train_steps, [(str(tmp_path / f"rank{r}.npz"),) for r in range(2)], env)
    single, rank0, rank1 = (_weights(tmp_path / f"{n}.npz") for n in ("one", "rank0", "rank1"))
    assert len(single) == len(rank0) > 2
    for a, b in zip(rank0, rank1):
        np.testing.assert_array_equal(a, b)  # one all-reduced gradient, the same update in both
    for a, b in zip(rank0, single):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)  # sums in another order: float rounding only
    _processes(train_steps, [(str(tmp_path / "init.npz"), 0)], env)  # seed 7, untrained
    initial = _weights(tmp_path / "init.npz")
    assert any(not np.allclose(a, b) for a, b in zip(initial, single))  # it trained


def test_collectives_of_our_own_tensors_use_the_device_the_backend_reduces_on():
    """nccl has no CPU backend: the logs' mean must be reduced on this process's CUDA device (that of its
    local_rank, which start() selects), gloo's on the CPU."""
    import torch

    world = distributed.World(rank=1, size=2, local_rank=1)
    assert distributed.collective_device("nccl", world) == torch.device("cuda", 1)
    assert distributed.collective_device("gloo", world) == torch.device("cpu")


# Each of two gloo processes passes its own logs; both must get their mean.
def log_mean(out: str) -> None:
    world = distributed.from_environment()
    distributed.start(world)
    mine = {"loss": [1.0, 3.0][world.rank], "lr": [0.25, 0.75][world.rank]}
    Path(out).write_text(json.dumps(distributed.mean_over_processes(mine, world)))
    distributed.stop(world)


@pytest.mark.slow
def test_two_gloo_processes_log_the_mean_of_their_losses(tmp_path):
    outs = [tmp_path / f"rank{r}.json" for r in range(2)]
    _processes(log_mean, [(str(out),) for out in outs], launcher_free_env(KERAS_BACKEND="torch"))
    for out in outs:
        assert json.loads(out.read_text()) == {"loss": (1.0 + 3.0) / 2, "lr": (0.25 + 0.75) / 2}


def test_the_world_is_read_from_the_launchers_variables():
    assert distributed.from_environment({}) == distributed.World(0, 1, 0)
    got = distributed.from_environment({"RANK": "3", "WORLD_SIZE": "4", "LOCAL_RANK": "1"})
    assert (got.rank, got.size, got.local_rank, got.distributed, got.writer) == (3, 4, 1, True, False)
    assert distributed.World().writer and not distributed.World().distributed


@pytest.mark.parametrize("environ,needle", [
    ({"RANK": "0"}, "WORLD_SIZE, LOCAL_RANK not set"),
    ({"RANK": "one", "WORLD_SIZE": "2", "LOCAL_RANK": "0"}, "RANK must be an integer, got 'one'"),
    ({"RANK": "2", "WORLD_SIZE": "2", "LOCAL_RANK": "0"}, "rank must be below size (2), got 2"),
    ({"RANK": "0", "WORLD_SIZE": "0", "LOCAL_RANK": "0"}, "size must be an integer >= 1, got 0"),
])
def test_a_malformed_launcher_environment_is_refused_naming_what_it_held(environ, needle):
    with pytest.raises(ValueError) as err:
        distributed.from_environment(environ)
    assert needle in str(err.value)


def test_one_process_installs_nothing():
    assert distributed.average_gradients(object(), distributed.World()) == []
    distributed.broadcast_weights(object(), distributed.World())
    distributed.start(distributed.World())


TRAIN = ("train", "--set", "s", "--shards", "shards", "--width", "4", "--depth", "2", "--kernel-size", "3",
         "--steps", "3", "--batch-size", "4", "--threads", "1")


EVERY_PHASE = ("--joint-steps", "2", "--compositor", "alpha", "--compositor-steps", "2")


@pytest.mark.slow
def test_torchrun_with_two_processes_trains_the_run_that_one_process_trains(tmp_path):
    """The documented launch line, on 2 gloo processes, against `kpcn train` alone, through every phase
    (branches, joint fine-tuning, compositor): the same networks (float rounding apart), the same logged
    losses, and one set of files, written by rank 0."""
    from helpers.commands import run_main
    from helpers.tiny import build_tiny_shards

    from kpcn_keras.run import Run, load_model

    build_tiny_shards(tmp_path)
    alone = run_main(*TRAIN, *EVERY_PHASE, "--run-dir", "runs/one", cwd=tmp_path)
    assert alone.returncode == 0, alone.stderr[-3000:]
    res = subprocess.run(torchrun(*TRAIN, *EVERY_PHASE, "--run-dir", "runs/two"), cwd=tmp_path,
                         env=launcher_free_env(PYTHONPATH=str(REPO)), capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "data-parallel: 2 processes (gloo), 2 patches each of every batch of 4" in res.stdout
    one, two = Run(tmp_path / "runs" / "one"), Run(tmp_path / "runs" / "two")
    assert sorted(p.name for p in two.dir.iterdir()) == sorted(p.name for p in one.dir.iterdir())
    assert not [p for p in two.dir.rglob("*") if ".tmp-" in p.name]
    for name in ("diffuse", "specular", "joint", "compositor"):
        a, b = load_model(one.model_path(name)), load_model(two.model_path(name))
        for wa, wb in zip(a.weights, b.weights, strict=True):
            np.testing.assert_allclose(np.asarray(wb.numpy()), np.asarray(wa.numpy()), rtol=1e-4, atol=1e-6)
    log_one, log_two = (np.genfromtxt(r.log_path, delimiter=",", names=True) for r in (one, two))
    for column in ("loss", "val_loss"):
        np.testing.assert_allclose(log_two[column], log_one[column], rtol=1e-4)


# 60 steps of 50 per epoch: a checkpoint to be killed after, then a shorter epoch (as in tests/test_cli_resume.py)
RESUMABLE = ("train", "--set", "s", "--shards", "shards", "--width", "4", "--depth", "2", "--kernel-size", "3",
             "--steps", "60", "--batch-size", "4", "--threads", "1", "--run-dir", "runs/r")


@pytest.mark.slow
def test_a_killed_two_process_run_resumes_with_the_same_command_to_the_same_files(tmp_path):
    """Every process of the run killed at once (as a cancelled job is) after its first checkpoint; the same
    launch line again finishes it, and every file equals an uninterrupted two-process run's byte for byte."""
    import signal
    import time

    from helpers.files import checksums
    from helpers.tiny import build_tiny_shards

    env = launcher_free_env(PYTHONPATH=str(REPO))
    trees = {}
    for name in ("whole", "killed"):
        root = tmp_path / name
        build_tiny_shards(root)
        if name == "killed":
            proc = subprocess.Popen(torchrun(*RESUMABLE), cwd=root, env=env, start_new_session=True,
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            first = root / "runs" / "r" / "checkpoints" / "diffuse.keras"
            deadline = time.monotonic() + 300
            while not first.is_file() and proc.poll() is None and time.monotonic() < deadline:
                time.sleep(0.05)
            assert proc.poll() is None, "the run ended before its first checkpoint: nothing was killed"
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=60)
            assert not (root / "runs" / "r" / "diffuse.keras").exists()
        res = subprocess.run(torchrun(*RESUMABLE), cwd=root, env=env, capture_output=True, text=True,
                             timeout=600)
        assert res.returncode == 0, res.stderr[-3000:]
        if name == "killed":
            assert "[diffuse] resuming from" in res.stdout
        trees[name] = {k: v for k, v in checksums(root / "runs").items() if not k.endswith("timings.json")}
    assert trees["killed"] == trees["whole"]
