"""One map in process: `MapPipeline.step(frame, *, image=None) -> FrameStep` over the
front end, the estimator and the place localiser, with each robot's `RobotState` and
one snapshot of the whole (service.pipeline.snapshot). No store, HTTP, processes or
settings: the runtime (service.session) and the offline replay both drive it."""

from service.pipeline.map_pipeline import FrameStep, ImageFeatures, MapPipeline
from service.pipeline.robots import RobotState

__all__ = ["FrameStep", "ImageFeatures", "MapPipeline", "RobotState"]
