"""When a tracked image frame is starved (its pose-gated landmark matches far below the
robot's running average): the filter then weighs pose-free matches instead."""

from __future__ import annotations

import math

from service.pipeline.map_pipeline import (
    STARVED_FLOOR,
    STARVED_LIVE_SHARE,
    STARVED_MIN_AVERAGE,
    STARVED_SHARE,
    _starved,
    starved_floor,
)
from service.pipeline.robots import RobotState

UNCAPPED = 200
"""Live landmarks of an uncapped camera map (167-188 in the rendered rooms)."""


def test_a_robot_carried_elsewhere_stays_starved_until_it_sees_its_landmarks_again() -> None:
    # A capped camera map: a little above the floor, as many matches as the cap allows.
    usual = STARVED_MIN_AVERAGE + 2.0
    robot = RobotState()
    assert not any(_starved(robot, round(usual), UNCAPPED) for _ in range(30))
    before = robot.landmark_matches
    assert before is not None and before >= STARVED_MIN_AVERAGE
    # Carried elsewhere: no landmark matches, frame after frame; the average stays put.
    assert all(_starved(robot, 0, UNCAPPED) for _ in range(50))
    assert robot.landmark_matches == before
    # Found again (or seeing enough of them): not starved, and the average moves on.
    enough = int(STARVED_SHARE * before) + 1
    assert not _starved(robot, enough, UNCAPPED)
    assert robot.landmark_matches is not None and robot.landmark_matches < before


def test_a_robot_that_usually_sees_few_of_many_landmarks_is_never_starved() -> None:
    robot = RobotState()
    few = int(STARVED_MIN_AVERAGE) - 2
    assert not any(_starved(robot, few, UNCAPPED) for _ in range(20))
    assert not any(_starved(robot, 0, UNCAPPED) for _ in range(20))


def test_under_a_small_cap_the_same_few_matches_are_much_of_the_map() -> None:
    # Cap 30: a robot matches ~12 of the 30 live landmarks a frame (the rendered rooms);
    # carried elsewhere it matches none. In a map of many live landmarks the same 12
    # say nothing (previous test); here they are 40 % of what the map holds.
    cap, usual = 30, 12
    assert usual < STARVED_MIN_AVERAGE
    assert starved_floor(cap) <= usual
    robot = RobotState()
    assert not any(_starved(robot, usual, cap) for _ in range(30))
    assert all(_starved(robot, 0, cap) for _ in range(30))
    assert not _starved(robot, usual, cap)
    # The same robot in an uncapped map is never starved.
    other = RobotState()
    assert not any(_starved(other, usual, UNCAPPED) for _ in range(30))
    assert not any(_starved(other, 0, UNCAPPED) for _ in range(30))


def test_the_floor_follows_the_live_landmarks_between_its_bounds() -> None:
    assert starved_floor(UNCAPPED) == STARVED_MIN_AVERAGE
    assert starved_floor(40) == min(STARVED_MIN_AVERAGE, STARVED_LIVE_SHARE * 40)
    assert starved_floor(30) == STARVED_LIVE_SHARE * 30
    assert starved_floor(0) == STARVED_FLOOR
    # However few landmarks are live, a robot that usually matches a handful is not
    # starved by a frame with none.
    handful = math.floor(STARVED_FLOOR) - 1
    robot = RobotState()
    assert not any(_starved(robot, handful, 10) for _ in range(20))
    assert not any(_starved(robot, 0, 10) for _ in range(20))
