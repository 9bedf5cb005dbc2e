"""Distributed and resumed training: DDP over gloo with 2 CPU processes (equal steps, SIGTERM to every rank), and
exact resume from a checkpoint."""

from __future__ import annotations

import contextlib
import json
import os
import re
import socket
import subprocess
import sys
from pathlib import Path

import lightning as L
import pytest
import torch
from lightning.pytorch.callbacks import ModelCheckpoint

from hauwm.pid_lock import pid_lock
from model.config import WorldModelConfig
from model.module import PretrainModule

import rank_report  # noqa: I001 (tests/model/rank_report.py)
from conftest import REPO, TINY_CONFIG  # noqa: I001 (tests/model/conftest.py)


def ddp_fit(shards: Path, root: Path, callbacks: list[str], args: tuple[str, ...] = (),
            timeout: float = 300) -> subprocess.CompletedProcess:
    """`hauwm pretrain fit` of tiny.yaml for 5 steps with 2 gloo ranks on the CPU, with these callbacks (YAML items)
    and `args` after the others."""
    command, env = ddp_fit_command(shards, root, callbacks, args)
    return subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout)


def ddp_fit_command(shards: Path, root: Path, callbacks: list[str],
                    args: tuple[str, ...] = ()) -> tuple[list[str], dict[str, str]]:
    """The command of `ddp_fit` and its environment."""
    extra = root / "callbacks.yaml"
    extra.parent.mkdir(parents=True, exist_ok=True)
    extra.write_text("trainer:\n  callbacks:\n    - class_path: data_pipeline.SetEpoch\n" + "".join(callbacks))
    command = [sys.executable, "-m", "model.cli", "fit", "--config", str(TINY_CONFIG), "--config", str(extra),
               "--data.shards", str(shards), "--data.val_split", "train", "--data.batch_size", "2",
               "--data.seq_len", "6", "--data.num_workers", "0", "--trainer.limit_val_batches", "0",
               "--trainer.devices", "2", "--trainer.strategy", "ddp", "--trainer.max_steps", "5",
               "--trainer.enable_progress_bar", "false", "--trainer.default_root_dir", str(root / "run"), *args]
    python_path = [str(Path(__file__).parent), str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(python_path), "OMP_NUM_THREADS": "1", "PL_DISABLE_FORK": "1"}
    return command, env


def free_port() -> int:
    """A TCP port free on this machine now, for a job's rendezvous."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


# a callbacks item that writes last.ckpt (ddp_fit's callbacks replace tiny.yaml's list)
SAVE_LAST = "    - class_path: lightning.pytorch.callbacks.ModelCheckpoint\n      init_args:\n        save_last: true\n"


def assert_terminated_at(done: subprocess.CompletedProcess, run: Path, step: int) -> None:
    """The fit exited with 143 after `step`, said so, and last.ckpt holds that step."""
    assert done.returncode == 143, done.stderr[-3000:]
    last = run / "checkpoints" / "last.ckpt"
    assert f"terminated (SIGTERM) at step {step}; resume with --ckpt_path {last} (step {step}, " in done.stderr
    assert torch.load(last, weights_only=False)["global_step"] == step


def test_ddp_two_cpu_processes_take_the_same_steps_and_end_identical(built_shards, tmp_path):
    reports = tmp_path / "reports"
    done = ddp_fit(built_shards, tmp_path,
                   [f"    - class_path: rank_report.RankReport\n      init_args:\n        out_dir: {reports}\n"])
    assert done.returncode == 0, done.stderr[-3000:]
    rank0, rank1 = (json.loads((reports / f"rank{r}.json").read_text()) for r in (0, 1))
    assert rank0["world_size"] == rank1["world_size"] == 2
    assert rank0["global_step"] == rank1["global_step"] == 5
    assert rank0["batches"] == rank1["batches"] == 5
    # no per-step broadcast read on the host (Lightning's SIGTERM check, which model/sigterm.py replaces): on a GPU
    # each would make the host wait for the step's GPU work
    assert rank0["broadcasts"] == rank1["broadcasts"] == 0
    assert rank0["weights_sha256"] == rank1["weights_sha256"]
    assert rank0["lambda"] == rank1["lambda"] != 1.0  # λ moved, identically on both ranks


def test_ddp_with_the_compiled_step_takes_the_same_steps_and_ends_identical(built_shards, tmp_path):
    """ssv2.yaml's combination, DDP and `model.compile`, on the CPU: gloo ranks and inductor (its CUDA graphs need a
    GPU). The compiled losses run inside DDP's forward, and its gradient hooks fire from the compiled backward."""
    reports = tmp_path / "reports"
    done = ddp_fit(built_shards, tmp_path,
                   [f"    - class_path: rank_report.RankReport\n      init_args:\n        out_dir: {reports}\n"],
                   ("--model.compile", "default"), timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    rank0, rank1 = (json.loads((reports / f"rank{r}.json").read_text()) for r in (0, 1))
    assert rank0["global_step"] == rank1["global_step"] == 5
    assert rank0["scaler_skips"] == rank1["scaler_skips"] == rank0["nonfinite_steps"] == rank1["nonfinite_steps"] == 0
    assert rank0["weights_sha256"] == rank1["weights_sha256"]
    assert rank0["lambda"] == rank1["lambda"] != 1.0


def test_a_nan_loss_on_one_rank_under_16_mixed_is_a_non_finite_step_on_every_rank(tmp_path):
    """Each rank told a GradScaler skip from a non-finite step by its own loss: a NaN loss on rank 1 alone was counted
    as the scaler's calibration on rank 0, whose counters the logs and the checkpoint hold (found by a review)."""
    torch.multiprocessing.spawn(rank_report.fp16_fit_with_a_nan_on_rank_one, args=(free_port(), tmp_path), nprocs=2)
    rank0, rank1 = (json.loads((tmp_path / f"rank{rank}.json").read_text()) for rank in (0, 1))
    assert rank0["nonfinite_steps"] == rank1["nonfinite_steps"] == 1
    assert rank0["scaler_skips"] == rank1["scaler_skips"]
    assert rank0["weights_sha256"] == rank1["weights_sha256"]


def test_a_rank_that_fails_stops_the_job_with_one_line_from_each_rank(built_shards, tmp_path):
    """Rank 1's loader error left rank 0 in a collective: it printed gloo's 100-line traceback of a "Connection
    closed by peer" under "stopped by the error below", and the job exited with 1."""
    done = ddp_fit(built_shards, tmp_path, ["    - class_path: rank_report.LoaderFailsOnRankOne\n"])
    assert done.returncode == 2, done.stderr[-3000:]
    assert "hauwm pretrain fit: error: shard train-000001.tar of rank 1 is damaged (a test's)" in done.stderr
    assert "hauwm pretrain fit: error: rank 0 lost the other ranks of the job (" in done.stderr
    assert "Traceback" not in done.stderr, done.stderr[-3000:]


def test_lambdas_constraint_is_the_mean_over_ranks_not_their_sum(tmp_path):
    """The 2-rank fits above end with the same λ on both ranks, which the constraint's sum over ranks gives too."""
    torch.multiprocessing.spawn(rank_report.mean_of_two_ranks, args=(free_port(), tmp_path), nprocs=2)
    assert [float((tmp_path / f"rank{rank}").read_text()) for rank in (0, 1)] == [1.5, 1.5]


def test_a_job_whose_ranks_a_launcher_started_is_refused_by_every_rank_when_its_directory_is_in_use(built_shards,
                                                                                                 tmp_path):
    """srun, or torchrun over several nodes, starts every rank itself: the refused rank 0 exited before DDP's set-up,
    and the other ranks waited there for it until DDP's 30-minute timeout. Two ranks started as torchrun starts them,
    with no agent to end the second when the first fails (as under srun)."""
    checkpoints = tmp_path / "run" / "checkpoints"
    checkpoints.mkdir(parents=True)
    command, env = ddp_fit_command(built_shards, tmp_path, [])
    launched = {"TORCHELASTIC_RUN_ID": "test", "WORLD_SIZE": "2", "LOCAL_WORLD_SIZE": "2", "GROUP_RANK": "0",
                "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(free_port())}
    with pid_lock(checkpoints / ".fit.lock"), contextlib.ExitStack() as ranks:
        processes = [ranks.enter_context(subprocess.Popen(
            command, cwd=REPO, env={**env, **launched, "RANK": str(rank), "LOCAL_RANK": str(rank)},
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)) for rank in (0, 1)]
        ranks.callback(lambda: [process.kill() for process in processes if process.poll() is None])
        outputs = [process.communicate(timeout=240)[1] for process in processes]
    for process, stderr in zip(processes, outputs):
        assert process.returncode == 2, stderr[-3000:]
        assert f"{checkpoints} is in use by another fit (pid {os.getpid()}): wait for it to end" in stderr, stderr[-3000:]
        assert "Traceback" not in stderr
    assert [path.name for path in (tmp_path / "run").rglob("*")] == ["checkpoints", ".fit.lock"]  # nothing of its own


@pytest.mark.parametrize("node_rank", [0, 1])
def test_a_node_that_never_comes_is_said_while_the_ranks_wait_and_ends_the_job_with_what_to_do(built_shards, tmp_path,
                                                                                            node_rank):
    """Node 0 waited for a node 1 that was never started (node 1 for a node 0 never started) without a word until
    DDP's timeout (30 minutes by default), then ended with torch's DistStoreError (DistNetworkError), read as a rank
    lost in training. Here the first notice comes after 1 s and DDP's timeout is 4 s."""
    command, env = ddp_fit_command(built_shards, tmp_path, [], ("--trainer.devices", "1", "--trainer.num_nodes", "2",
                                                                "--trainer.strategy", "DDPStrategy",
                                                                "--trainer.strategy.timeout", "0:00:04"))
    notice_soon = "import sys; from model import rendezvous; rendezvous.NOTICE_AFTER_S = 1; from model.cli import main; "
    command[1:3] = ["-c", notice_soon + "sys.exit(main())"]  # for `-m model.cli`
    port = free_port()
    env = {**env, "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port), "NODE_RANK": str(node_rank)}
    done = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr[-3000:]
    assert re.search(rf"hauwm pretrain fit: rank {node_rank} has waited 0:00:0[1-3] for the job's 2 ranks to meet at "
                     rf"127.0.0.1:{port} \(DDP gives up after 0:00:04\): if a node is not running yet, start the same "
                     r"`hauwm pretrain fit` on each of the 2 nodes \(NODE_RANK 0 to 1", done.stderr), done.stderr[-3000:]
    assert (f"hauwm pretrain fit: error: rank {node_rank}: the job's 2 ranks did not all meet at 127.0.0.1:{port} "
            "within DDP's timeout (0:00:04; torch: ") in done.stderr
    assert "lost the other ranks" not in done.stderr and "Traceback" not in done.stderr
    assert not [path for path in (tmp_path / "run").rglob("*") if path.is_file()]  # no lock, log or config left


def test_sigterm_to_every_rank_at_different_points_stops_them_after_the_same_step(built_shards, tmp_path):
    """As SLURM sends it: each rank gets SIGTERM, rank 0 before step 3's batch and rank 1 inside its backward pass
    (rank_report.SigtermEveryRank). Lightning's own handler hung here; the ranks agree on step 3's flags after step 4
    (one step late: reading them costs no wait for the GPU), every rank stops after step 4, last.ckpt holds step 4,
    and the fit exits with 143."""
    done = ddp_fit(built_shards, tmp_path, [SAVE_LAST, "    - class_path: rank_report.SigtermEveryRank\n"])
    assert_terminated_at(done, tmp_path / "run", step=4)


def test_sigterm_to_every_rank_before_a_step_that_validates_writes_last_ckpt_after_it(built_shards, tmp_path):
    """The step the ranks agree to stop after (4) validates (every 4 steps, 2 batches): its validation runs to its
    end and last.ckpt holds step 4 (Lightning raised inside the validation, where no checkpoint is written)."""
    done = ddp_fit(built_shards, tmp_path, [SAVE_LAST, "    - class_path: rank_report.SigtermEveryRank\n"],
                   ("--trainer.limit_val_batches", "2", "--trainer.val_check_interval", "4"))
    assert_terminated_at(done, tmp_path / "run", step=4)


def test_sigterm_to_every_rank_in_the_sanity_check_stops_them_after_the_second_step(built_shards, tmp_path):
    """A SIGTERM before the fit trains (here in its sanity check) reached Lightning's own handler, which hung. The
    ranks agree on step 1's flags after step 2."""
    done = ddp_fit(built_shards, tmp_path, [SAVE_LAST, "    - class_path: rank_report.SigtermInSanityCheck\n"],
                   ("--trainer.limit_val_batches", "2", "--trainer.num_sanity_val_steps", "1"), timeout=120)
    assert_terminated_at(done, tmp_path / "run", step=2)


class ResumableBatches:
    """Fixed batches as a resumable loader (`state_dict` / `load_state_dict`): Lightning saves its position in
    the checkpoint and restores it, so this test isolates what the module must restore itself."""

    def __init__(self, batches: list[dict]):
        self.batches, self.position, self.skip = batches, 0, 0

    def __len__(self) -> int:
        return len(self.batches)

    def __iter__(self):
        start, self.skip = self.skip, 0
        for index in range(start, len(self.batches)):
            self.position = index + 1  # batches handed out this epoch
            yield self.batches[index]

    def state_dict(self) -> dict:
        return {"position": self.position}

    def load_state_dict(self, state: dict) -> None:
        self.skip = state["position"]


class LossRecorder(L.Callback):
    def __init__(self):
        self.losses: dict[int, float] = {}

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.losses[trainer.global_step] = float(trainer.callback_metrics["train/loss"])


def train(batches: list[dict], root: Path, sizes: WorldModelConfig, max_steps: int, ckpt_path: str | None = None):
    L.seed_everything(0)
    module = PretrainModule(sizes, k_max=5, lambda_lr=0.01)
    recorder = LossRecorder()
    checkpoint = ModelCheckpoint(dirpath=root, save_last=True, every_n_train_steps=4)
    trainer = L.Trainer(max_steps=max_steps, accelerator="cpu", logger=False, enable_progress_bar=False,
                        enable_model_summary=False, callbacks=[recorder, checkpoint], log_every_n_steps=1)
    trainer.fit(module, train_dataloaders=ResumableBatches(batches), ckpt_path=ckpt_path)
    return module, recorder.losses


def test_resuming_gives_the_same_next_losses_as_an_uninterrupted_run(tmp_path, small_sizes, batch_factory):
    batches = [batch_factory(batch_size=2, length=6, seed=i) for i in range(6)]  # 6 steps an epoch
    full_module, full = train(batches, tmp_path / "full", small_sizes, max_steps=10)
    train(batches, tmp_path / "first", small_sizes, max_steps=4)  # stops mid-epoch, checkpoint at step 4
    resumed_module, resumed = train(batches, tmp_path / "resumed", small_sizes, max_steps=10,
                                    ckpt_path=str(tmp_path / "first" / "last.ckpt"))
    assert sorted(resumed) == list(range(5, 11))  # the rest of epoch 0 and 4 steps of epoch 1
    assert [resumed[step] for step in range(5, 11)] == [full[step] for step in range(5, 11)]
    full_state, resumed_state = full_module.state_dict(), resumed_module.state_dict()
    assert all(torch.equal(full_state[name], resumed_state[name]) for name in full_state)  # weights, λ, counters
    assert full_module.hcu_weight() != 1.0


def test_a_checkpoint_of_the_unfused_step_resumes(tmp_path, small_sizes, batch_factory):
    """Checkpoints written before the synchronisation-free step (one skipped_steps counter, unfused Adams) resume."""
    batches = [batch_factory(batch_size=2, length=3, seed=i) for i in range(3)]
    _, full = train(batches, tmp_path / "full", small_sizes, max_steps=6)
    train(batches, tmp_path / "first", small_sizes, max_steps=4)
    checkpoint = torch.load(tmp_path / "first" / "last.ckpt", weights_only=False)
    state = checkpoint["state_dict"]
    state["skipped_steps"] = state.pop("nonfinite_steps") + state.pop("scaler_skips")
    for optimizer in checkpoint["optimizer_states"]:
        for group in optimizer["param_groups"]:
            group["fused"] = None
    torch.save(checkpoint, tmp_path / "old.ckpt")
    _, resumed = train(batches, tmp_path / "resumed", small_sizes, max_steps=6, ckpt_path=str(tmp_path / "old.ckpt"))
    assert [resumed[step] for step in (5, 6)] == [full[step] for step in (5, 6)]
