"""The bench scripts start, and the GPU session's first commands run end to end on the CPU.

A GPU is lent to few sessions and for 15 minutes: `bench/bench_gpu.py` and `bench/bench_agent.py --device cuda`
are what such a session runs first (bench/README.md), so a script that no longer imports must be caught here,
not there. The figures themselves are bench output, never asserted (they depend on the machine).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SCRIPTS = sorted((REPO / "bench").glob("*.py"))
LIBRARIES = ("machine.py", "args.py")  # what the scripts import, not scripts
sys.path.insert(0, str(REPO))

from bench.machine import describe_machine  # noqa: E402


def run_script(script: Path, *args: str, timeout: float) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(script), *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)


@pytest.mark.parametrize("script", [s for s in SCRIPTS if s.name not in LIBRARIES], ids=lambda s: s.name)
def test_every_bench_script_starts(script):
    done = run_script(script, "--help", timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "usage:" in done.stdout


def test_the_machine_line_names_the_usable_cpus_and_the_accelerator():
    line = describe_machine("cpu")
    assert f"{len(os.sched_getaffinity(0))} of {os.cpu_count()} CPUs usable" in line
    assert "no GPU" in line and "torch " in line and "load average" in line


@pytest.mark.slow
def test_bench_gpu_runs_on_the_cpu(built_shards):
    done = run_script(REPO / "bench" / "bench_gpu.py", "--device", "cpu", "--shards", str(built_shards),
                      "--steps", "2", "--fit-steps", "8", "--rounds", "1", timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    shown = done.stdout
    assert shown.startswith("machine: ") and "no GPU" in shown.splitlines()[0]
    for row in ("eager ", "compiled (default)", "loader alone", "bare step fed by the loader", "(a) long epochs",
                "(b) short epochs", "the fits by the host",
                "where a fit step's time goes", "host, inside the step", "host operators by own time"):
        assert row in shown, shown
    assert "aim ≥ 0.9×" in shown and "failed (" not in shown


@pytest.mark.slow
def test_bench_agent_runs_on_the_cpu():
    done = run_script(REPO / "bench" / "bench_agent.py", "--compile", "off", "--updates", "1", "--seconds", "1",
                      "--envs", "1", "2", "--act-batches", "1", timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    shown = done.stdout
    assert shown.startswith("machine: ") and "MUJOCO_GL=" in shown and "MUJOCO_GL=unset" not in shown
    for row in ("hauwm    eager", "scratch  eager", "agent steps/s summed over the envs"):
        assert row in shown, shown


def test_bench_step_ops_counts_an_eager_step():
    done = run_script(REPO / "bench" / "bench_step_ops.py", "--sizes", "tiny", "--length", "4", "--no-compile",
                      timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.startswith("machine: ") and "tiny: eager step (forward + backward) " in done.stdout
    assert "agent: eager update (L 50, H 15) " in done.stdout


def test_bench_loader_runs_every_section(built_shards):
    done = run_script(REPO / "bench" / "bench_loader.py", "--shards", str(built_shards), "--batches", "4",
                      "--epochs", "2", "--epoch-batches", "2", "--batch-size", "4", "--seq-len", "8", timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    for row in ("main process:", "DataLoader, 2 workers:", "receiving a batch from a worker:", "workers started once:",
                "the loader before issue 12 (workers restarted every epoch, torch's hand-over):"):
        assert row in done.stdout, done.stdout


def test_bench_learning_starts_a_new_run_and_reports_it(tmp_path):
    """The GPU learning check (`--gpu`) is this script at Table 3 sizes: a fresh --logdir must train, not fail."""
    settings = ["threads=1", "prefill=50", "eval_every=100", "eval_episodes=1", "time_limit=25", "batch_size=4",
                "seq_len=8"]
    done = run_script(REPO / "bench" / "bench_learning.py", "--minutes", "0.01", "--chunk", "100", "--logdir",
                      str(tmp_path / "run"), *[arg for setting in settings for arg in ("--set", setting)], timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "random policy:" in done.stdout and (tmp_path / "run" / "learning_curve.png").is_file()


def stopped_by_sigterm(script: str, args: list[str], evaluations: Path, rows: int) -> tuple[str, str]:
    """Run bench/`script` with `args`, send it SIGTERM once its `evaluations` CSV holds `rows` rows (the header
    too), and return its stdout and stderr once it has ended with exit status 143 and no traceback."""
    command = [sys.executable, str(REPO / "bench" / script), *args]
    with subprocess.Popen(command, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as bench:
        deadline = time.monotonic() + 240
        while not evaluations.is_file() or len(evaluations.read_text().splitlines()) < rows:
            assert bench.poll() is None and time.monotonic() < deadline, bench.stderr.read()[-3000:]
            time.sleep(0.2)
        bench.send_signal(signal.SIGTERM)
        out, err = bench.communicate(timeout=240)
    assert bench.returncode == 143, err[-3000:]
    assert "Traceback" not in err, err[-3000:]
    return out, err


def test_bench_learning_stopped_by_sigterm_reports_the_evaluations_so_far(tmp_path):
    """A GPU call wraps the learning check in `timeout`: its SIGTERM must end the run with its checkpoint and still
    print the table and draw the curve of the evaluations made, exit status 143 (not a traceback, as on 2026-11-26)."""
    settings = ["threads=1", "prefill=50", "eval_every=100", "eval_episodes=1", "time_limit=25", "batch_size=4",
                "seq_len=8"]
    run = tmp_path / "run"
    out, _ = stopped_by_sigterm("bench_learning.py", ["--minutes", "10", "--chunk", "100000", "--logdir", str(run),
                                                      *[arg for setting in settings for arg in ("--set", setting)]],
                                run / "eval.csv", rows=3)
    assert "bench_learning: terminated (SIGTERM) at env step " in out and "random policy:" in out
    assert (run / "checkpoint.pt").is_file() and (run / "learning_curve.png").is_file()


def test_bench_downstream_stopped_by_sigterm_reports_the_runs_so_far(tmp_path):
    """The offline RL and imitation checks of a GPU call run under `timeout` too: its SIGTERM ends the run under
    way with its checkpoint, and the datasets' references and that run's evaluations are still reported (143)."""
    from model.config import WorldModelConfig
    from model.export import export_frozen
    from model.world_model import WorldModel

    export = export_frozen(WorldModel(WorldModelConfig(cnn_width=8, embed_dim=64, deter=24, stoch=8, hidden=24,
                                                       ensemble=3, temporal_dim=8)), tmp_path / "export", {})
    small = ["eval_every=5", "checkpoint_every=5", "batch_size=4", "seq_len=8", "units=32", "hidden=24"]
    run = tmp_path / "runs" / "offline_lam0"
    args = ["--pretrained", str(export), "--logdir", str(tmp_path / "runs"), "--only", "offline", "--updates", "100000",
            "--lams", "0", "--expert-episodes", "1", "--noisy-episodes", "1", "--demos", "1", "--eval-episodes", "1",
            "--no-progress", *[arg for setting in small for arg in ("--set", setting)]]
    out, _ = stopped_by_sigterm("bench_downstream.py", args, run / "eval.csv", rows=2)
    assert "bench_downstream: offline_lam0 terminated (SIGTERM) at update " in out
    assert "expert policy" in out and "offline_lam0: 5: " in out and (run / "checkpoint.pt").is_file()


def test_bench_downstream_shows_no_success_rate_where_the_suite_has_none():
    from bench.bench_downstream import percent

    assert percent(float("nan")) == "—" and percent(0.4) == "40%" and percent(1.0) == "100%"  # DMC has no success
