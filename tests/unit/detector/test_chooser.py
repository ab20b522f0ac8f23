"""A lone request runs the way that has been faster lately, and the other way is still tried."""

from __future__ import annotations

from service.detector.chooser import NARROW, WIDE, FasterWay


def test_both_ways_are_timed_first_then_the_faster_one_wins_but_the_other_is_retried():
    ways = FasterWay(explore=4)
    assert ways.pick(1) == WIDE
    ways.record(1, WIDE, 0.010)
    assert ways.pick(1) == NARROW
    ways.record(1, NARROW, 0.004)
    picks = [ways.pick(1) for _ in range(8)]
    assert picks.count(NARROW) == 6 and picks.count(WIDE) == 2, picks


def test_the_choice_follows_the_machine_when_the_faster_way_slows_down():
    ways = FasterWay(explore=100, window=5)
    for _ in range(3):
        ways.record(4, WIDE, 0.005)
    ways.record(4, NARROW, 0.010)
    assert ways.pick(4) == WIDE
    ways.record(4, WIDE, 0.030)  # one slow run does not flip the choice
    assert ways.pick(4) == WIDE
    for _ in range(3):  # the machine got busy: wide runs now wait for cores
        ways.record(4, WIDE, 0.030)
    assert ways.pick(4) == NARROW


def test_crop_counts_are_timed_apart():
    ways = FasterWay()
    ways.record(1, WIDE, 0.001)
    ways.record(1, NARROW, 0.002)
    ways.record(4, WIDE, 0.010)
    ways.record(4, NARROW, 0.005)
    assert ways.pick(1) == WIDE and ways.pick(4) == NARROW
