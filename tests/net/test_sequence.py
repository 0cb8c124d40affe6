"""Sequence and age sanity of received samples (``asyncdonkey.parts.zenoh.sequence``): no sample, however
numbered or aged, can lock the genuine sender out, and none with an implausible age is ever taken."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from asyncdonkey.parts.zenoh.sequence import (
    IMPLAUSIBLE,
    MAX_AGE_S,
    MAX_JUMP,
    OUT_OF_ORDER,
    SEQ_MAX,
    UNCONFIRMED,
    SampleOrder,
    plausible_age,
)

PILOT = 0x1234_5678_9ABC


def _feed(order: SampleOrder, seqs, source=PILOT, age=0.02):
    return [order.check(age, s, source) for s in seqs]


def test_the_sample_numbered_2_64_minus_1_under_the_pilots_source_does_not_lock_it_out():
    order = SampleOrder()
    assert all(v.taken for v in _feed(order, range(1, 11)))
    hostile = order.check(0.0, SEQ_MAX, PILOT)
    assert not hostile.taken and hostile.reason == IMPLAUSIBLE and "jump" in hostile.detail
    after = _feed(order, range(11, 31))
    assert all(v.taken for v in after)  # the pilot's own stream was never moved
    assert sum(v.lost for v in after) == 0


def test_a_hostile_stream_and_a_hostile_jump_cost_the_pilot_at_most_one_sample():
    order = SampleOrder()
    _feed(order, range(1, 11))
    # two hostile samples continuing each other: a stream of their own, taken (a peer that may put can command)
    assert [v.reason for v in _feed(order, [SEQ_MAX - 1, SEQ_MAX], age=0.0)] == [IMPLAUSIBLE, ""]
    after = _feed(order, range(11, 31))
    assert all(v.taken for v in after)  # the pilot's own stream still takes its samples
    # a hostile sample *inside* the pilot's stream (a jump forward within MAX_JUMP) takes that stream ahead ...
    hostile = order.check(0.0, 30 + MAX_JUMP, PILOT)
    assert hostile.taken and hostile.lost == MAX_JUMP - 1  # a gap, bounded by MAX_JUMP
    verdicts = _feed(order, range(31, 31 + MAX_JUMP + 20))
    # ... which costs the pilot one sample: its next one starts a stream that the one after confirms
    assert [v.reason for v in verdicts[:2]] == [OUT_OF_ORDER, ""] and verdicts[1].restart
    assert all(v.taken for v in verdicts[1:])  # reaching the hostile number later is no duplicate
    assert sum(v.lost for v in verdicts) == 0


@pytest.mark.parametrize("age", [1e300, math.inf, -math.inf, math.nan, -1.0, -1e-9, MAX_AGE_S * 1.01, 3600.0], ids=repr)
def test_an_implausible_age_is_refused_and_changes_nothing(age):
    order = SampleOrder()
    _feed(order, range(1, 4))
    before = order.streams()
    v = order.check(age, 4, PILOT)
    assert not v.taken and v.reason == IMPLAUSIBLE and "age" in v.detail
    assert order.streams() == before
    assert order.check(0.01, 4, PILOT).taken  # the genuine sample with that number is still taken


def test_plausible_ages_are_finite_and_between_zero_and_the_bound():
    assert plausible_age(0.0) and plausible_age(MAX_AGE_S) and plausible_age(0.25)
    assert not plausible_age(-0.001) and not plausible_age(math.nan) and not plausible_age(MAX_AGE_S + 1)
    assert plausible_age(20.0, max_age_s=30.0)


def test_sequence_zero_is_refused():
    order = SampleOrder()
    assert order.check(0.0, 0, PILOT).reason == IMPLAUSIBLE
    assert order.streams() == []


def test_a_restarted_sender_is_resynchronised_after_one_sample():
    order = SampleOrder()
    _feed(order, range(1, 501))
    # a new process: a new source, numbering from 1
    v = _feed(order, range(1, 5), source=99)
    assert [x.reason for x in v] == [UNCONFIRMED, "", "", ""] and v[1].restart
    # the same source numbering from 1 again (a sender that keeps its source across restarts)
    order = SampleOrder()
    _feed(order, range(1, 501))
    v = _feed(order, range(1, 5))
    assert [x.reason for x in v] == [OUT_OF_ORDER, "", "", ""] and v[1].restart
    # a long outage: a gap beyond MAX_JUMP is confirmed by the next sample
    v = _feed(order, [5 + 5 * MAX_JUMP, 6 + 5 * MAX_JUMP])
    assert [x.reason for x in v] == [IMPLAUSIBLE, ""] and v[1].lost == 0


def test_late_and_duplicated_samples_are_refused():
    order = SampleOrder()
    v = _feed(order, [1, 2, 3, 3, 4, 7, 5, 8])
    assert [x.reason for x in v] == ["", "", "", OUT_OF_ORDER, "", "", OUT_OF_ORDER, ""]
    assert [x.lost for x in v] == [0, 0, 0, 0, 0, 2, 0, 0]


def test_bad_arguments():
    with pytest.raises(ValueError, match="max_age_s"):
        SampleOrder(max_age_s=math.inf)
    with pytest.raises(ValueError, match="max_jump"):
        SampleOrder(max_jump=0)


_ages = st.one_of(
    st.sampled_from([0.0, 1e300, math.inf, -math.inf, math.nan, -1.0, MAX_AGE_S, MAX_AGE_S + 0.5, 5e-324]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(0.0, 2 * MAX_AGE_S),
)


_hostile = st.tuples(
    _ages,
    st.one_of(
        st.sampled_from([0, 1, 2, SEQ_MAX - 1, SEQ_MAX]),
        st.integers(0, SEQ_MAX),
        st.integers(0, 2 * MAX_JUMP),
        st.integers(0, 50),  # among the sender's own numbers
    ),
    st.one_of(st.just(PILOT), st.integers(0, 3), st.integers(0, 2**64 - 1)),  # the pilot's own source, or another
)


@st.composite
def _traffic(draw) -> list[tuple[bool, tuple[float, int, int]]]:
    """A genuine sender numbering 1..n (plausible ages) with hostile samples (any age, number and source, near
    the sender's numbers too) interleaved anywhere, then five more genuine samples."""
    n = draw(st.integers(1, 40))
    hostile = draw(st.lists(st.tuples(st.integers(0, n), _hostile), max_size=16))
    age = draw(st.floats(0.0, 1.0))
    out: list[tuple[bool, tuple[float, int, int]]] = []
    for seq in range(1, n + 6):
        out.extend((False, sample) for at, sample in hostile if at == seq - 1)
        out.append((True, (age, seq, PILOT)))
    return out


@settings(max_examples=300, deadline=None)
@given(traffic=_traffic(), size=st.integers(1, 5), max_jump=st.sampled_from([1, 3, MAX_JUMP]))
def test_no_interleaving_of_hostile_samples_locks_out_the_genuine_sender(traffic, size, max_jump):
    """A genuine sample is refused only when some other sample arrived since the genuine one before it (or
    before its first), so after the last hostile sample at most one is refused; nothing with an implausible
    age is ever taken; the loss counts stay bounded."""
    order = SampleOrder(max_jump=max_jump, size=size)
    other_since_last_genuine = False
    refused_after_last_hostile = 0
    taken = 0
    lost = 0
    for genuine, (age, seq, source) in traffic:
        v = order.check(age, seq, source)
        assert v.lost >= 0 and v.lost <= max_jump - 1
        lost += v.lost
        if v.taken:
            taken += 1
            assert plausible_age(age) and seq >= 1
        if genuine:
            if not v.taken:
                assert other_since_last_genuine, (seq, v)
                refused_after_last_hostile += 1
            other_since_last_genuine = False
        else:
            other_since_last_genuine = True
            refused_after_last_hostile = 0
    assert refused_after_last_hostile <= 1
    assert lost <= taken * (max_jump - 1)
    assert len(order.streams()) <= size
