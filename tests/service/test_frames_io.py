"""The REST frame format: strict parsing, round trips, JSON-lines files."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from graph.errors import InvalidFrame
from graph.types import BearingObservation, FrameInput, Odometry, Pose2D
from service.errors import ServiceError
from service.frame_model import FrameLimits, parse_frame
from service.frames_io import admit_frame, canonical_frame, frame_from_dict, frame_to_dict
from service.offline.frame_files import FrameFileError, read_frames, write_frames
from service.settings import Settings

DESIGN_EXAMPLE: dict[str, Any] = {
    "robot": "r1",
    "seq": 17,
    "stamp": 1248444189.599,
    "odometry": {"dx": 0.12, "dy": 0.0, "dtheta": 0.01},
    "initial_pose": {"x": 0.0, "y": 0.0, "theta": 0.0},
    "observations": [{"bearing": -0.257, "sigma": 0.02, "label": "14"}],
}


def _with(path: str, value: object) -> dict[str, Any]:
    """DESIGN_EXAMPLE with one field (dotted path, [i] indexes) set; deleted if value is `...`."""
    d = copy.deepcopy(DESIGN_EXAMPLE)
    node: Any = d
    keys: list[str | int] = []
    for part in path.split("."):
        if "[" in part:
            name, idx = part[:-1].split("[")
            keys += [name, int(idx)]
        else:
            keys.append(part)
    for k in keys[:-1]:
        node = node[k]
    if value is ...:
        del node[keys[-1]]
    else:
        node[keys[-1]] = value
    return d


def test_design_example_parses() -> None:
    frame = frame_from_dict(DESIGN_EXAMPLE)
    assert frame == FrameInput(
        robot="r1",
        seq=17,
        stamp=1248444189.599,
        odometry=Odometry(0.12, 0.0, 0.01),
        initial_pose=Pose2D(0.0, 0.0, 0.0),
        observations=(BearingObservation(bearing_rad=-0.257, label="14", sigma_rad=0.02),),
    )
    assert frame_to_dict(frame) == DESIGN_EXAMPLE


def test_optional_fields_absent_or_null() -> None:
    frame = frame_from_dict({"robot": "a", "seq": 0, "stamp": 3})
    assert frame == FrameInput(robot="a", seq=0, stamp=3.0)
    assert isinstance(frame.stamp, float)
    nulls = {"robot": "a", "seq": 0, "stamp": 3, "odometry": None, "initial_pose": None}
    assert frame_from_dict({**nulls, "observations": None}) == frame
    assert frame_to_dict(frame) == {"robot": "a", "seq": 0, "stamp": 3.0, "observations": []}


def test_odometry_sigmas_and_observation_sigma_optional() -> None:
    d = _with("observations", [{"bearing": 0.5, "label": "a"}])
    d["odometry"] = {"dx": 1, "dy": 2, "dtheta": 3, "sigma_x": 0.1, "sigma_theta": None}
    frame = frame_from_dict(d)
    assert frame.odometry == Odometry(1.0, 2.0, 3.0, sigma_x=0.1)
    assert frame.observations == (BearingObservation(0.5, "a"),)
    out = frame_to_dict(frame)
    assert out["odometry"] == {"dx": 1.0, "dy": 2.0, "dtheta": 3.0, "sigma_x": 0.1}
    assert out["observations"] == [{"bearing": 0.5, "label": "a"}]


def test_integer_label_is_stored_as_string() -> None:
    frame = frame_from_dict(_with("observations[0].label", 14))
    assert frame.observations[0].label == "14"


def test_descriptor_is_allowed_and_not_kept() -> None:
    d = copy.deepcopy(DESIGN_EXAMPLE)
    d["observations"][0]["descriptor"] = "AAECAw=="
    assert frame_from_dict(d) == frame_from_dict(DESIGN_EXAMPLE)


@pytest.mark.parametrize(
    ("path", "hint"),
    [
        ("observation", "did you mean observations?"),
        ("extra", "its fields: robot, seq, stamp, odometry, initial_pose, observations"),
        ("odometry.covariance", "is not a field of odometry"),
        ("initial_pose.z", "is not a field of initial_pose"),
        ("observations[0].patch_id", "is not a field of an observation"),
    ],
)
def test_unknown_field_is_refused_and_named(path: str, hint: str) -> None:
    """A typo is not silently ignored (the frame would be processed without its data)."""
    with pytest.raises(InvalidFrame) as info:
        frame_from_dict(_with(path, [{"bearing": 0.1, "label": "a"}]))
    assert info.value.field == path
    assert hint in info.value.detail


def test_image_member_of_a_frame_document_is_set_aside() -> None:
    """Frame files, the log and exports name the frame's image beside the frame."""
    assert frame_from_dict(_with("image", "images/000001.png")) == frame_from_dict(DESIGN_EXAMPLE)
    with pytest.raises(InvalidFrame) as info:
        parse_frame(_with("image", "images/000001.png"))
    assert info.value.field == "image"


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_nan_and_infinity_are_refused(value: float) -> None:
    with pytest.raises(InvalidFrame) as info:
        frame_from_dict(_with("observations[0].bearing", value))
    assert info.value.field == "observations[0].bearing"
    assert info.value.detail == f"must be finite, got {value!r}"


def test_out_of_range_bearing_is_left_to_the_graph() -> None:
    assert frame_from_dict(_with("observations[0].bearing", 7.0)).observations[0].bearing_rad == 7.0


@pytest.mark.parametrize(
    ("path", "value", "detail"),
    [
        ("robot", ..., "is required"),
        ("robot", 3, "must be a string, got number"),
        ("robot", "", "must not be empty"),
        ("seq", ..., "is required"),
        ("seq", 1.0, "must be an integer, got non-integer number"),
        ("seq", True, "must be an integer, got boolean"),
        ("seq", "3", "must be an integer, got string"),
        ("seq", -1, "must be >= 0, got -1"),
        ("stamp", ..., "is required"),
        ("stamp", None, "must be a number, got null"),
        ("stamp", False, "must be a number, got boolean"),
        ("stamp", "1.5", "must be a number, got string"),
        ("odometry", [1, 2, 3], "must be an object, got array"),
        ("odometry.dx", ..., "is required"),
        ("odometry.dtheta", True, "must be a number, got boolean"),
        ("odometry.sigma_y", "0.1", "must be a number, got string"),
        ("initial_pose", 0, "must be an object, got number"),
        ("initial_pose.theta", ..., "is required"),
        ("initial_pose.y", [0], "must be a number, got array"),
        ("observations", {"bearing": 0}, "must be an array, got object"),
        ("observations[0]", "0.1", "must be an object, got string"),
        ("observations[0].bearing", ..., "is required"),
        ("observations[0].bearing", True, "must be a number, got boolean"),
        ("observations[0].sigma", "x", "must be a number, got string"),
        ("observations[0].label", ..., "is required"),
        ("observations[0].label", 1.5, "must be a string or an integer, got number"),
        ("observations[0].label", True, "must be a string or an integer, got boolean"),
        ("observations[0].label", "", "must not be empty"),
        ("observations[0].descriptor", 12, "must be a base64 string, got number"),
        ("seq", 2**63, f"must be < 2^63, got {2**63}"),
        ("stamp", 10**400, "must be finite, got an integer beyond a double's range"),
        ("robot", "r\ud800", "must be Unicode text: a lone surrogate \\ud800 at character 1"),
        (
            "observations[0].label",
            "\udfff",
            "must be Unicode text: a lone surrogate \\udfff at character 0",
        ),
    ],
)
def test_invalid_field_is_named(path: str, value: object, detail: str) -> None:
    with pytest.raises(InvalidFrame) as info:
        frame_from_dict(_with(path, value))
    assert info.value.field == path
    assert info.value.detail == detail


def test_error_names_the_right_observation() -> None:
    d = _with("observations", [{"bearing": 0.1, "label": "a"}] * 2 + [{"bearing": "x", "label": 1}])
    with pytest.raises(InvalidFrame) as info:
        frame_from_dict(d)
    assert info.value.field == "observations[2].bearing"


def test_descriptor_only_observation_is_refused_clearly() -> None:
    d = _with("observations", [{"bearing": 0.1, "descriptor": "AAEC"}])
    with pytest.raises(InvalidFrame, match="descriptor-only") as info:
        frame_from_dict(d)
    assert info.value.field == "observations[0].label"


def test_not_an_object() -> None:
    with pytest.raises(InvalidFrame) as info:
        frame_from_dict([1, 2])  # type: ignore[arg-type]
    assert info.value.field == "frame"


finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
observations = st.builds(
    BearingObservation,
    bearing_rad=finite,
    label=st.text(min_size=1, max_size=5),
    sigma_rad=st.none() | finite,
)
frames = st.builds(
    FrameInput,
    robot=st.text(min_size=1, max_size=5),
    seq=st.integers(min_value=0, max_value=2**53),
    stamp=finite,
    odometry=st.none()
    | st.builds(
        Odometry,
        dx=finite,
        dy=finite,
        dtheta=finite,
        sigma_x=st.none() | finite,
        sigma_y=st.none() | finite,
        sigma_theta=st.none() | finite,
    ),
    initial_pose=st.none() | st.builds(Pose2D, x=finite, y=finite, theta=finite),
    observations=st.lists(observations, max_size=4).map(tuple),
)


@given(frames)
def test_round_trip_through_json(frame: FrameInput) -> None:
    text = json.dumps(frame_to_dict(frame))
    assert frame_from_dict(json.loads(text)) == frame


def test_file_round_trip(tmp_path: Path) -> None:
    frames_in = [
        frame_from_dict(DESIGN_EXAMPLE),
        FrameInput(robot="r1", seq=18, stamp=1248444189.7, odometry=Odometry(0.1, 0.0, -0.02)),
    ]
    for name in ("f.jsonl", "f.jsonl.gz"):
        path = tmp_path / name
        assert write_frames(path, frames_in) == 2
        assert list(read_frames(path)) == frames_in
    assert len((tmp_path / "f.jsonl").read_text().splitlines()) == 2


def test_read_skips_blank_lines_and_names_bad_lines(tmp_path: Path) -> None:
    good = json.dumps(DESIGN_EXAMPLE)
    bad = json.dumps(_with("observations[0].bearing", "north"))
    path = tmp_path / "f.jsonl"
    path.write_text(f"\n{good}\n   \n{good}\n{bad}\n")
    reader = read_frames(path)
    assert next(reader).seq == 17
    assert next(reader).seq == 17
    with pytest.raises(FrameFileError) as info:
        next(reader)
    assert info.value.line == 5
    assert info.value.field == "observations[0].bearing"
    assert "f.jsonl:5: observations[0].bearing" in str(info.value)

    path.write_text(f"{good}\n{{not json\n")
    with pytest.raises(FrameFileError) as info:
        list(read_frames(path))
    assert (info.value.line, info.value.field) == (2, "line")


def test_write_refuses_nan(tmp_path: Path) -> None:
    frame = FrameInput(robot="r1", seq=0, stamp=float("nan"))
    with pytest.raises(ValueError, match="JSON"):
        write_frames(tmp_path / "f.jsonl", [frame])


LIMITS = FrameLimits()


@pytest.mark.parametrize(
    ("path", "value", "detail"),
    [
        ("robot", "r" * 129, "must be at most 128 characters, got 129"),
        ("observations[0].label", "l" * 65, "must be at most 64 characters, got 65"),
        ("observations[0].label", 10**64, "must be at most 64 characters, got 65"),
        (
            "observations",
            [{"bearing": 0.0, "label": str(i)} for i in range(1001)],
            "must hold at most 1000, got 1001",
        ),
        ("stamp", 1e308, "must lie within +-1e+10 s, got 1e+308"),
        ("stamp", -2e10, "must lie within +-1e+10 s, got -20000000000.0"),
        ("odometry.dx", 100.5, "must lie within +-100 m, got 100.5"),
        ("odometry.dy", -1e9, "must lie within +-100 m, got -1000000000.0"),
        ("initial_pose.x", 2e6, "must lie within +-1e+06 m, got 2000000.0"),
        ("initial_pose.y", -1e7, "must lie within +-1e+06 m, got -10000000.0"),
    ],
)
def test_frame_beyond_a_limit_is_named(path: str, value: object, detail: str) -> None:
    doc = _with(path, value)
    with pytest.raises(InvalidFrame) as info:
        parse_frame(doc, limits=LIMITS)
    assert (info.value.field, info.value.detail) == (path, detail)
    # Without limits (a frame already in a map's log) only the structure is checked.
    assert parse_frame(doc).robot == doc["robot"]


def test_frame_at_the_limits_is_taken_as_it_is() -> None:
    doc = _with("robot", "r" * 128)
    doc["stamp"] = -1e10
    doc["odometry"] = {"dx": 100.0, "dy": -100, "dtheta": 0.0}
    doc["initial_pose"] = {"x": 1e6, "y": -1e6, "theta": 0.0}
    doc["observations"] = [{"bearing": 0.0, "label": "l" * 64}] * 1000
    assert parse_frame(doc, limits=LIMITS) == frame_from_dict(doc)
    assert frame_to_dict(parse_frame(doc, limits=LIMITS)) == {**doc, "stamp": -1e10}


def test_limits_are_configurable() -> None:
    tight = FrameLimits(max_robot_chars=2, max_observations=0)
    with pytest.raises(InvalidFrame) as info:
        parse_frame(_with("robot", "abc"), limits=tight)
    assert info.value.detail == "must be at most 2 characters, got 3"
    with pytest.raises(InvalidFrame) as info:
        parse_frame(_with("robot", "ab"), limits=tight)
    assert (info.value.field, info.value.detail) == ("observations", "must hold at most 0, got 1")


def test_limits_are_settings(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("COVSLAM_FRAMES__MAX_OBSERVATIONS", "7")
    settings = Settings()
    assert settings.frames == FrameLimits(max_observations=7)
    monkeypatch.setenv("COVSLAM_FRAMES__MAX_LABEL_CHARS", "0")
    with pytest.raises(ValueError, match="max_label_chars"):
        Settings()


@pytest.mark.parametrize(
    "doc",
    [
        _with("robot", "r" * 129),
        _with("odometry.dx", 100.5),
        _with("observations[0].label", "l" * 65),
        {**DESIGN_EXAMPLE, "image": {"sha256": "0" * 64, "bytes": 1}},  # not in a JSON frame
        _with("seq", -1),
    ],
)
def test_a_posted_frame_is_refused_by_its_one_parse_as_by_admit_frame(doc: dict[str, Any]) -> None:
    """The worker parses a posted JSON frame once, with the limits: the same 422 as the
    API process's check gave (an image member included), and never a frame it refuses."""
    with pytest.raises(ServiceError) as admitted:
        admit_frame(doc, LIMITS)
    with pytest.raises(ServiceError) as parsed:
        canonical_frame(doc, limits=LIMITS)
    assert parsed.value.as_dict() == admitted.value.as_dict()
    assert parsed.value.status == 422


def test_an_image_frames_meta_is_checked_against_the_limits_too() -> None:
    meta = {k: v for k, v in _with("robot", "r" * 129).items() if k != "observations"}
    with pytest.raises(ServiceError, match="robot: must be at most 128"):
        canonical_frame(meta, b"\x89PNG", limits=LIMITS)
    frame, text = canonical_frame({**meta, "robot": "r1"}, b"\x89PNG", limits=LIMITS)
    assert frame.robot == "r1" and '"image":{"bytes":4' in text
