"""Fuzzing the readers of outside bytes (hypothesis): no input may make them raise anything
but their documented error (see :mod:`tests.fuzz.targets`).

The default suite tries :data:`FAST` inputs per target; ``pytest -m slow`` tries
:data:`SLOW`. ``bench/bench_fuzz.py`` runs any number and prints the inputs tried and the
crashes per target. The seeds are fixed (``derandomize``) so a run is reproducible.
"""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, given, settings

from tests.fuzz.targets import TARGETS, Target, run_one, seed_descriptors, with_checksum

FAST = 50
SLOW = 3000


def _fuzz(target: Target, examples: int) -> int:
    tried = 0

    @settings(max_examples=examples, deadline=None, database=None, derandomize=True,
              suppress_health_check=list(HealthCheck))
    @given(target.strategy)
    def run(example):
        nonlocal tried
        tried += 1
        crash = run_one(target, example)
        if crash is not None:
            raise AssertionError(f"{target.name} crashed: {type(crash).__name__}: {crash}") from crash

    run()
    return tried


@pytest.mark.parametrize("target", TARGETS, ids=[t.name for t in TARGETS])
def test_fuzz_fast(target: Target) -> None:
    assert _fuzz(target, FAST) >= FAST // 2  # hypothesis may stop early on a small space


@pytest.mark.slow
@pytest.mark.parametrize("target", TARGETS, ids=[t.name for t in TARGETS])
def test_fuzz_slow(target: Target) -> None:
    assert _fuzz(target, SLOW) >= SLOW // 2


def test_the_harness_reports_a_crash_and_accepts_the_documented_error() -> None:
    """A target that raises something undocumented is a crash; its documented error is
    not; and the descriptor mutator's checksum repair really gets past the checksum."""
    from robotd.base.errors import DescriptorError
    from robotd.floor.descriptor import decode

    def boom(_):
        raise KeyError("x")

    assert isinstance(run_one(Target("t", TARGETS[0].strategy, boom, ()), b""), KeyError)
    assert run_one(Target("t", TARGETS[0].strategy, boom, (KeyError,)), b"") is None
    seed = seed_descriptors()[3]
    assert decode(seed).mode == 4
    broken = seed[:40] + bytes([seed[40] ^ 0xFF]) + seed[41:]
    with pytest.raises(DescriptorError, match="checksum"):
        decode(broken)
    try:
        decode(with_checksum(broken))
    except DescriptorError as exc:
        assert "checksum" not in str(exc)
