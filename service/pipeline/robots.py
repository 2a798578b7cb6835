"""What the pipeline keeps of each robot between its frames (besides the estimator's
pose chain, which graph.slam keeps).

Poses are ``(x m, y m, theta rad)`` in the map frame (DESIGN.md, Conventions).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from service.pipeline.offgraph import OffGraphTrack

FloatArray = NDArray[np.float64]


@dataclass
class RobotState:
    """One robot of the map, as the pipeline knows it."""

    last: tuple[int, float] | None = None
    """(seq, stamp) of the robot's last frame the pipeline took (graph or filter only)."""
    reported: tuple[int | None, float | None] = (None, None)
    """(place, confidence) that the robot's last frame result reported."""
    pose: tuple[FloatArray, FloatArray] | None = None
    """The robot's last graph pose (3,) and its (3, 3) covariance, x, y in the map frame:
    where the front end predicts its next image frame from."""
    signature: NDArray[np.float32] | None = None
    """Appearance signature of the robot's last panorama (the visual compass)."""
    landmark_matches: float | None = None
    """Running average of the pose-gated landmark matches of its image frames (a frame
    far below it is starved)."""
    off_graph: OffGraphTrack = field(default_factory=OffGraphTrack)
    """Frames acknowledged while the graph did not take them."""
