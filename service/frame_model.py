"""The REST frame (docs/api.md, "A frame") as one pydantic model: the single
validation of a frame's structure and the OpenAPI schema of a frame.

`parse_frame` validates a decoded JSON object and returns the estimator's `FrameInput`,
or raises `InvalidFrame` naming the first offending field with a dotted path
(``observations[2].bearing``) and saying why (``must be a number, got string``).

Always refused: unknown fields (a typo such as ``observation`` is not silently
ignored), wrong JSON types (booleans are not numbers), NaN and infinities, an empty
robot name or label, a negative ``seq`` or one of 2^63 or more (SQLite's integers are
64-bit), text with lone UTF-16 surrogates (not Unicode, so it cannot be stored).

Refused when `FrameLimits` are given (the service gives its `frames` settings): names,
labels, observation counts, odometry steps, initial-pose coordinates and stamps
beyond the configured bounds.

Left to the estimator's own checks (`graph.validation`), so that every entry point
refuses the same frames with the same words: bearings outside (-pi, pi], sigmas that
are not > 0, an odometry turn beyond [-pi, pi], a label twice in one frame, the order
of seq and stamp, a new robot without ``initial_pose``.

Units: metres, radians, seconds (stamps are seconds, any epoch).
"""

from __future__ import annotations

import difflib
from collections.abc import Callable, Mapping
from typing import Annotated, Any, TypeVar

from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from graph.errors import InvalidFrame
from graph.types import BearingObservation, FrameInput, Odometry, Pose2D

T = TypeVar("T")

SEQ_END = 2**63
"""seq must be below this: the store keeps it in a signed 64-bit integer."""


class FrameLimits(BaseModel):
    """Bounds on what one posted frame may hold (settings ``COVSLAM_FRAMES__*``).

    A frame beyond one is refused with 422 naming the field; the map is unchanged.
    """

    model_config = ConfigDict(extra="forbid")

    max_robot_chars: int = Field(128, ge=1, description="longest robot name, characters")
    max_label_chars: int = Field(64, ge=1, description="longest observation label, characters")
    max_observations: int = Field(1000, ge=0, description="most bearing observations in one frame")
    max_odometry_step_m: float = Field(
        100.0, gt=0, description="largest |dx| and |dy| of one frame's odometry, metres"
    )
    max_coordinate_m: float = Field(
        1e6, gt=0, description="largest |x| and |y| of an initial_pose, metres (map frame)"
    )
    max_abs_stamp_s: float = Field(
        1e10,
        gt=0,
        description="largest |stamp|, seconds (1e10 s after the Unix epoch is the year 2286); "
        "a stamp far in the future would make every later frame of its robot out of order",
    )


# --------------------------------------------------------------------------- checks


def _json_type(value: object) -> str:
    """The JSON name of a Python value's type, for error details."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "boolean"
    if isinstance(value, int | float):
        return "number"
    if isinstance(value, str):
        return "string"
    if isinstance(value, list | tuple):
        return "array"
    if isinstance(value, Mapping):
        return "object"
    return type(value).__name__


def _refuse(detail: str) -> PydanticCustomError:
    """A validation error whose message is `detail`, as the API states it."""
    return PydanticCustomError("invalid_frame", "{detail}", {"detail": detail})


def _limited(value: T, info: ValidationInfo, check: Callable[[T, FrameLimits], None]) -> T:
    """`value`, once `check` passed with the limits of the validation's context (none
    given: no check)."""
    context = info.context
    limits = context.get("limits") if isinstance(context, Mapping) else None
    if isinstance(limits, FrameLimits):
        check(value, limits)
    return value


def _number(value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise _refuse(f"must be a number, got {_json_type(value)}")
    try:
        return float(value)
    except OverflowError:
        raise _refuse("must be finite, got an integer beyond a double's range") from None


def _optional_number(value: object) -> float | None:
    return None if value is None else _number(value)


def _object(value: object) -> object:
    if type(value) is dict:  # decoded JSON: no ABC check needed
        return value
    if not isinstance(value, Mapping):
        raise _refuse(f"must be an object, got {_json_type(value)}")
    return value


def _optional_object(value: object) -> object:
    return None if value is None else _object(value)


def _unicode(text: str) -> str:
    if text.isascii():  # nearly every name and label: no surrogate to look for
        return text
    for i, ch in enumerate(text):
        if "\ud800" <= ch <= "\udfff":
            raise _refuse(
                f"must be Unicode text: a lone surrogate \\u{ord(ch):04x} at character {i}"
            )
    return text


def _robot(value: object) -> str:
    if not isinstance(value, str):
        raise _refuse(f"must be a string, got {_json_type(value)}")
    if not value:
        raise _refuse("must not be empty")
    return _unicode(value)


def _seq(value: object) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        kind = "non-integer number" if isinstance(value, float) else _json_type(value)
        raise _refuse(f"must be an integer, got {kind}")
    if value < 0:
        raise _refuse(f"must be >= 0, got {value}")
    if value >= SEQ_END:
        raise _refuse(f"must be < 2^63, got {value}")
    return value


class _Marker:
    """Stands for a missing label (see `ObservationIn._label_or_marker`)."""


_MISSING_LABEL = _Marker()
_DESCRIPTOR_ONLY_LABEL = _Marker()


def _label(value: object) -> str:
    """A label as str; JSON integers are accepted and converted (17 -> "17")."""
    if value is _MISSING_LABEL:
        raise _refuse("is required")
    if value is _DESCRIPTOR_ONLY_LABEL:
        raise _refuse("is required (descriptor-only observations are not supported yet)")
    if isinstance(value, bool) or not isinstance(value, int | str):
        raise _refuse(f"must be a string or an integer, got {_json_type(value)}")
    label = str(value)
    if not label:
        raise _refuse("must not be empty")
    return _unicode(label)


def _descriptor(value: object) -> object:
    if value is not None and not isinstance(value, str):
        raise _refuse(f"must be a base64 string, got {_json_type(value)}")
    return value


def _observations(value: object) -> object:
    if value is None:
        return []
    if not isinstance(value, list | tuple):
        raise _refuse(f"must be an array, got {_json_type(value)}")
    return value


def _within(value: float, bound: float, unit: str) -> None:
    if abs(value) > bound:
        raise _refuse(f"must lie within +-{bound:g} {unit}, got {value!r}")


def _at_most_items(items: list[Any], bound: int) -> None:
    if len(items) > bound:
        raise _refuse(f"must hold at most {bound}, got {len(items)}")


def _at_most_chars(text: str, bound: int) -> None:
    if len(text) > bound:
        raise _refuse(f"must be at most {bound} characters, got {len(text)}")


Number = Annotated[float, BeforeValidator(_number)]
OptionalNumber = Annotated[float | None, BeforeValidator(_optional_number)]


def _bounded(bound: str, unit: str) -> AfterValidator:
    """|value| <= the `FrameLimits` field `bound` (in `unit`), when limits are given."""

    def check(value: float, info: ValidationInfo) -> float:
        return _limited(value, info, lambda v, lim: _within(v, getattr(lim, bound), unit))

    return AfterValidator(check)


StepM = Annotated[float, BeforeValidator(_number), _bounded("max_odometry_step_m", "m")]
CoordinateM = Annotated[float, BeforeValidator(_number), _bounded("max_coordinate_m", "m")]
StampS = Annotated[float, BeforeValidator(_number), _bounded("max_abs_stamp_s", "s")]
_STRICT = ConfigDict(extra="forbid", allow_inf_nan=False)


# --------------------------------------------------------------------------- the model


class OdometryIn(BaseModel):
    """Motion since the robot's previous frame, expressed in the previous robot frame."""

    model_config = _STRICT

    dx: StepM = Field(description="forward motion, metres (|dx| <= frames.max_odometry_step_m)")
    dy: StepM = Field(description="leftward motion, metres (|dy| <= frames.max_odometry_step_m)")
    dtheta: Number = Field(description="heading change, radians, counter-clockwise, in [-pi, pi]")
    sigma_x: OptionalNumber = Field(None, description="one-sigma noise of dx, metres, > 0")
    sigma_y: OptionalNumber = Field(None, description="one-sigma noise of dy, metres, > 0")
    sigma_theta: OptionalNumber = Field(None, description="one-sigma noise of dtheta, radians, > 0")


class InitialPoseIn(BaseModel):
    """A robot's first pose in the map frame."""

    model_config = _STRICT

    x: CoordinateM = Field(description="metres, map frame (|x| <= frames.max_coordinate_m)")
    y: CoordinateM = Field(description="metres, map frame (|y| <= frames.max_coordinate_m)")
    theta: Number = Field(
        description="yaw, radians, counter-clockwise from the map's +x axis, in (-pi, pi]"
    )


class ObservationIn(BaseModel):
    """One bearing to a landmark, with its known data association."""

    model_config = _STRICT

    bearing: Number = Field(
        description="radians in the robot frame, counter-clockwise from the robot's forward "
        "axis (+x), in (-pi, pi]"
    )
    sigma: OptionalNumber = Field(None, description="one-sigma bearing noise, radians, > 0")
    label: Annotated[str | int, BeforeValidator(_label)] = Field(
        description="known data association (e.g. a fiducial id): a non-empty string, or an "
        "integer stored as its decimal string; at most frames.max_label_chars characters"
    )
    descriptor: Annotated[str | None, BeforeValidator(_descriptor)] = Field(
        None, description="base64 appearance descriptor (not used yet: label is required)"
    )

    @model_validator(mode="before")
    @classmethod
    def _label_or_marker(cls, data: Any) -> Any:
        """A missing (or null) label gets a marker, so that its error names the label
        and says whether a descriptor stood in for it."""
        if (type(data) is dict or isinstance(data, Mapping)) and data.get("label") is None:
            marker = _DESCRIPTOR_ONLY_LABEL if "descriptor" in data else _MISSING_LABEL
            return {**data, "label": marker}
        return data

    @field_validator("label")
    @classmethod
    def _label_length(cls, value: str, info: ValidationInfo) -> str:
        return _limited(value, info, lambda v, lim: _at_most_chars(v, lim.max_label_chars))


class FrameIn(BaseModel):
    """One frame of one robot (JSON form). Unknown fields, NaN and infinities are refused."""

    model_config = _STRICT

    robot: Annotated[str, BeforeValidator(_robot)] = Field(
        min_length=1,
        description="robot name; one pose chain per robot; at most frames.max_robot_chars "
        "characters",
    )
    seq: Annotated[int, BeforeValidator(_seq)] = Field(
        ge=0, lt=SEQ_END, description="per-robot sequence number, strictly increasing"
    )
    stamp: StampS = Field(
        description="seconds (any epoch), non-decreasing per robot; |stamp| <= "
        "frames.max_abs_stamp_s"
    )
    odometry: Annotated[OdometryIn | None, BeforeValidator(_optional_object)] = Field(
        None, description="required on every frame after the robot's first"
    )
    initial_pose: Annotated[InitialPoseIn | None, BeforeValidator(_optional_object)] = Field(
        None,
        description="optional, only read on a robot's first frame; without it the robot is "
        "'initialising' until the place localiser finds it",
    )
    observations: Annotated[
        list[Annotated[ObservationIn, BeforeValidator(_object)]],
        BeforeValidator(_observations),
    ] = Field(
        default_factory=list,
        description="bearings seen in this frame (absent or null = none); at most "
        "frames.max_observations",
    )

    @field_validator("robot")
    @classmethod
    def _robot_length(cls, value: str, info: ValidationInfo) -> str:
        return _limited(value, info, lambda v, lim: _at_most_chars(v, lim.max_robot_chars))

    @field_validator("observations")
    @classmethod
    def _observation_count(cls, value: list[ObservationIn], info: ValidationInfo) -> Any:
        return _limited(value, info, lambda v, lim: _at_most_items(v, lim.max_observations))

    def to_frame(self) -> FrameInput:
        """The estimator's frame (labels as strings; the descriptor is not kept)."""
        odo = self.odometry
        pose = self.initial_pose
        return FrameInput(
            robot=self.robot,
            seq=self.seq,
            stamp=self.stamp,
            odometry=None
            if odo is None
            else Odometry(odo.dx, odo.dy, odo.dtheta, odo.sigma_x, odo.sigma_y, odo.sigma_theta),
            initial_pose=None if pose is None else Pose2D(pose.x, pose.y, pose.theta),
            observations=tuple(
                BearingObservation(bearing_rad=o.bearing, label=str(o.label), sigma_rad=o.sigma)
                for o in self.observations
            ),
        )


# --------------------------------------------------------------------------- errors


def _field_path(loc: tuple[int | str, ...]) -> str:
    """('observations', 2, 'bearing') -> 'observations[2].bearing'."""
    path = ""
    for part in loc:
        path += f"[{part}]" if isinstance(part, int) else (f".{part}" if path else str(part))
    return path


def _unknown_field(name: str, known: list[str], what: str) -> str:
    close = difflib.get_close_matches(name, known, n=1)
    hint = f"; did you mean {close[0]}?" if close else ""
    return f"is not a field of {what} (its fields: {', '.join(known)}){hint}"


_OWNERS: dict[str, tuple[type[BaseModel], str]] = {
    "": (FrameIn, "a frame"),
    "odometry": (OdometryIn, "odometry"),
    "initial_pose": (InitialPoseIn, "initial_pose"),
    "observations": (ObservationIn, "an observation"),
}


def _detail(error: Mapping[str, Any]) -> str:
    """The API's words for one pydantic error."""
    kind = error["type"]
    if kind == "invalid_frame":
        return str(error["ctx"]["detail"])
    if kind == "missing":
        return "is required"
    if kind == "finite_number":
        return f"must be finite, got {error['input']!r}"
    if kind == "extra_forbidden":
        loc = error["loc"]
        owner, what = _OWNERS[str(loc[0]) if len(loc) > 1 else ""]
        return _unknown_field(str(loc[-1]), list(owner.model_fields), what)
    return str(error["msg"])


def parse_frame(doc: object, *, limits: FrameLimits | None = None) -> FrameInput:
    """Validate one frame's decoded JSON object; the estimator's `FrameInput`.

    `limits`: the bounds of `FrameLimits` to apply as well (None: structure only, as
    for frames already in a map's log).

    Raises:
        InvalidFrame: with the dotted path of the first offending field.
    """
    if not isinstance(doc, Mapping):
        raise InvalidFrame("frame", f"must be an object, got {_json_type(doc)}")
    try:
        model = FrameIn.model_validate(doc, context={"limits": limits})
    except ValidationError as exc:
        first = exc.errors(include_url=False)[0]
        raise InvalidFrame(_field_path(first["loc"]), _detail(first)) from None
    return model.to_frame()
