"""Meeting the other ranks of a DDP job, said aloud: `RendezvousWatch`.

Each rank of a DDP job waits in `torch.distributed.init_process_group` until every rank has come to node 0's
MASTER_ADDR:MASTER_PORT, up to DDP's timeout (30 minutes unless `--trainer.strategy DDPStrategy
--trainer.strategy.timeout H:MM:SS` says otherwise). A node that was never started, or that cannot reach node 0,
kept the others there without a word for the whole timeout, and the job then ended with torch's DistStoreError
("1/2 clients joined") or DistNetworkError from inside its TCP store, read by `hauwm pretrain` as a rank lost in
training. While a rank waits, the watch says so (after NOTICE_AFTER_S, then every NOTICE_EVERY_S); when the ranks
never all came, it says that, and what to do, as a ConfigError in place of torch's error.
"""

from __future__ import annotations

import os
import sys
import threading
import time
import traceback
from datetime import timedelta
from types import TracebackType

import torch.distributed as dist

from hauwm.messages import first_line
from model.config import ConfigError

NOTICE_AFTER_S = 60.0  # the first notice that a rank is still waiting for the others
NOTICE_EVERY_S = 300.0  # the notices after it
POLL_S = 1.0  # how often the watch looks whether the ranks have met
DEFAULT_TIMEOUT = timedelta(minutes=30)  # DDP's, where the strategy does not say (torch's default_pg_timeout)


def duration(seconds: float) -> str:
    """H:MM:SS, as --trainer.strategy.timeout takes it."""
    return str(timedelta(seconds=round(seconds)))


class RendezvousWatch:
    """A context around a DDP fit or validation: a thread that, until the process group is up, says every so often on
    stderr that this rank still waits for the others; on leaving, a DistError raised inside `init_process_group`
    becomes a ConfigError that says the ranks did not all come and what to check."""

    def __init__(self, command: str, rank: int, world_size: int, nodes: int, timeout: timedelta | None) -> None:
        self.command, self.rank, self.world_size, self.nodes = command, rank, world_size, nodes
        self.timeout = DEFAULT_TIMEOUT if timeout is None else timeout
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="rendezvous-watch", daemon=True)

    def where(self) -> str:
        """Node 0's address and port, as Lightning sets them for torch right before the rendezvous."""
        return f"{os.environ.get('MASTER_ADDR', '?')}:{os.environ.get('MASTER_PORT', '?')}"

    def fix(self) -> str:
        if self.nodes > 1:
            start = (f"start the same `{self.command}` on each of the {self.nodes} nodes (NODE_RANK 0 to "
                     f"{self.nodes - 1}, or one srun for the whole job), with MASTER_ADDR and MASTER_PORT naming node 0 "
                     "and that port reachable from every node")
        else:
            start = (f"start all {self.world_size} ranks (a rank that never comes ended first, and its own error says "
                     "why, or was not started)")
        return f"{start}; `--trainer.strategy DDPStrategy --trainer.strategy.timeout H:MM:SS` sets how long they wait"

    def _watch(self) -> None:
        started, notice_at, noticed = time.monotonic(), NOTICE_AFTER_S, False
        while not self._done.wait(POLL_S):
            waited = time.monotonic() - started
            if dist.is_initialized():
                if noticed:
                    print(f"{self.command}: rank {self.rank}: the job's {self.world_size} ranks met after "
                          f"{duration(waited)}", file=sys.stderr, flush=True)
                return
            if waited >= notice_at:
                print(f"{self.command}: rank {self.rank} has waited {duration(waited)} for the job's {self.world_size} "
                      f"ranks to meet at {self.where()} (DDP gives up after {duration(self.timeout.total_seconds())}): "
                      f"if a {'node' if self.nodes > 1 else 'rank'} is not running yet, {self.fix()}", file=sys.stderr,
                      flush=True)
                noticed, notice_at = True, notice_at + NOTICE_EVERY_S

    def __enter__(self) -> RendezvousWatch:
        self._thread.start()
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 trace: TracebackType | None) -> None:
        self._done.set()
        self._thread.join()
        in_rendezvous = any(frame.f_code.co_name == "init_process_group" for frame, _ in traceback.walk_tb(trace))
        if isinstance(error, dist.DistError) and in_rendezvous:
            raise ConfigError(
                f"rank {self.rank}: the job's {self.world_size} ranks did not all meet at {self.where()} within DDP's "
                f"timeout ({duration(self.timeout.total_seconds())}; torch: {first_line(error)}): {self.fix()}"
            ) from None
