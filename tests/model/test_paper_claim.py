"""The paper's RQ3 claim after a short CPU training on the built-in data (minutes: `make test-all`)."""

from __future__ import annotations

import importlib.util

import pytest

from conftest import REPO  # noqa: I001 (tests/model/conftest.py)


@pytest.mark.slow
def test_with_hcu_disagreement_rises_with_k_and_exceeds_no_hcu(tmp_path):
    spec = importlib.util.spec_from_file_location("bench_pretrain_claim", REPO / "bench" / "bench_pretrain_claim.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    result = bench.run_claim(tmp_path, steps=300)
    assert all(result["claims"].values()), result
