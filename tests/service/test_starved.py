"""When a tracked image frame is starved (its pose-gated landmark matches far below the
robot's running average): the filter then weighs pose-free matches instead."""

from __future__ import annotations

from service.pipeline.map_pipeline import (
    STARVED_MIN_AVERAGE,
    STARVED_SHARE,
    _starved,
)
from service.pipeline.robots import RobotState


def test_a_robot_carried_elsewhere_stays_starved_until_it_sees_its_landmarks_again() -> None:
    # A capped camera map: a little above the floor, as many matches as the cap allows.
    usual = STARVED_MIN_AVERAGE + 2.0
    robot = RobotState()
    assert not any(_starved(robot, round(usual)) for _ in range(30))
    before = robot.landmark_matches
    assert before is not None and before >= STARVED_MIN_AVERAGE
    # Carried elsewhere: no landmark matches, frame after frame; the average stays put.
    assert all(_starved(robot, 0) for _ in range(50))
    assert robot.landmark_matches == before
    # Found again (or seeing enough of them): not starved, and the average moves on.
    enough = int(STARVED_SHARE * before) + 1
    assert not _starved(robot, enough)
    assert robot.landmark_matches is not None and robot.landmark_matches < before


def test_a_robot_that_usually_sees_few_landmarks_is_never_starved() -> None:
    robot = RobotState()
    few = int(STARVED_MIN_AVERAGE) - 2
    assert not any(_starved(robot, few) for _ in range(20))
    assert not any(_starved(robot, 0) for _ in range(20))
