"""RendezvousWatch (model/rendezvous.py) on its own: its notices, and which errors it replaces. A whole job whose
node never comes: tests/model/test_ddp_resume.py."""

from __future__ import annotations

import re
import time
from datetime import timedelta

import pytest
import torch.distributed as dist

from model import rendezvous
from model.config import ConfigError
from model.rendezvous import RendezvousWatch


def init_process_group() -> None:
    """Named as torch's: the watch tells a rendezvous error by the frame it was raised in."""
    raise dist.DistStoreError("Timed out after 5 seconds waiting for clients. 1/2 clients joined.")


def test_a_rank_that_waited_says_so_and_then_that_the_ranks_met(monkeypatch, capsys):
    monkeypatch.setattr(rendezvous, "NOTICE_AFTER_S", 0.2)
    monkeypatch.setattr(rendezvous, "POLL_S", 0.05)
    met = []
    monkeypatch.setattr(dist, "is_initialized", lambda: bool(met))
    with RendezvousWatch("hauwm pretrain fit", 1, 4, 1, timedelta(minutes=5)):
        time.sleep(0.5)
        met.append(True)
        time.sleep(0.3)
    err = capsys.readouterr().err
    assert "hauwm pretrain fit: rank 1 has waited 0:00:00 for the job's 4 ranks to meet at " in err
    assert "(DDP gives up after 0:05:00): if a rank is not running yet, start all 4 ranks" in err
    assert re.search(r"hauwm pretrain fit: rank 1: the job's 4 ranks met after 0:00:0[01]\n", err)


def test_ranks_that_meet_at_once_are_not_mentioned(monkeypatch, capsys):
    monkeypatch.setattr(dist, "is_initialized", lambda: True)
    with RendezvousWatch("hauwm pretrain fit", 0, 2, 2, None):
        time.sleep(0.1)
    assert capsys.readouterr().err == ""


def test_only_an_error_of_the_rendezvous_is_replaced(monkeypatch):
    monkeypatch.setenv("MASTER_ADDR", "10.0.0.1")
    monkeypatch.setenv("MASTER_PORT", "29500")
    with pytest.raises(ConfigError, match=r"rank 0: the job's 2 ranks did not all meet at 10\.0\.0\.1:29500 within "
                                          r"DDP's timeout \(0:30:00; torch: Timed out after 5 seconds waiting for "
                                          r"clients\. 1/2 clients joined\.\): start the same `hauwm pretrain fit` on "
                                          r"each of the 2 nodes \(NODE_RANK 0 to 1"):
        with RendezvousWatch("hauwm pretrain fit", 0, 2, 2, None):
            init_process_group()
    lost = dist.DistNetworkError("Connection closed by peer")  # in training: hauwm pretrain says a rank was lost
    with pytest.raises(dist.DistNetworkError) as raised:
        with RendezvousWatch("hauwm pretrain fit", 0, 2, 2, None):
            raise lost
    assert raised.value is lost
