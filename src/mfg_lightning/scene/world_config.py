"""The layout and densities of a persistent world (:class:`WorldConfig`): lanes, parking
strips, sidewalks, facades, parked and moving boxes, exposure and sensor noise."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["Range", "WorldConfig"]

#: A range ``(lo, hi)`` from which a quantity is drawn uniformly.
Range = tuple[float, float]


@dataclass(frozen=True)
class WorldConfig:
    """Layout and densities of a persistent world.

    Lengths in metres; densities per 100 m of path (per side where stated); speeds in metres per
    frame (KITTI's 10 Hz: 1 m/frame = 36 km/h).

    Attributes:
        lane_width: width of one lane. The camera drives in the middle of its lane.
        lanes_per_side: lanes beside the camera's on each side (oncoming on the left, same
            direction on the right). The road spans ``±lane_width · (lanes_per_side + 0.5)``.
        parking_width: parking strip between the outer lane and the kerb on each side.
        sidewalk_width: sidewalk between the kerb and the building line.
        facade_coverage: fraction of the path's length lined with facades on each side.
        facade_setback: range of the distance of a facade behind the sidewalk.
        facade_length, facade_depth, facade_height: ranges of a facade box's size.
        parked_per_100m: parked boxes per 100 m per side (at most one per 5.5 m).
        crate_fraction: fraction of parked boxes that are textured boxes (containers, vans)
            rather than cars.
        cars_per_100m: moving cars per 100 m of path (all lanes beside the camera's).
        car_speed: range of a moving car's speed.
        pedestrians_per_100m: pedestrians per 100 m of path (both sidewalks).
        pedestrian_speed: range of a pedestrian's walking speed.
        exposure_std: stationary standard deviation of the log exposure gain.
        exposure_corr: frame-to-frame correlation of the log exposure gain (AR(1)).
        sensor_noise: standard deviation of the per-pixel sensor noise, grey levels.
        grid_cell: ground-grid cell size (grown automatically beyond ``MAX_GRID_CELLS``).
        margin: ground grid beyond the path's bounding box.
    """

    lane_width: float = 3.3
    lanes_per_side: int = 1
    parking_width: float = 2.2
    sidewalk_width: float = 3.0
    facade_coverage: float = 0.8
    facade_setback: Range = (0.3, 6.0)
    facade_length: Range = (8.0, 30.0)
    facade_depth: Range = (8.0, 16.0)
    facade_height: Range = (6.0, 20.0)
    parked_per_100m: float = 6.0
    crate_fraction: float = 0.2
    cars_per_100m: float = 2.5
    car_speed: Range = (0.4, 1.3)
    pedestrians_per_100m: float = 3.0
    pedestrian_speed: Range = (0.08, 0.16)
    exposure_std: float = 0.04
    exposure_corr: float = 0.9
    sensor_noise: float = 1.0
    grid_cell: float = 1.0
    margin: float = 80.0

    def __post_init__(self) -> None:
        for name in ("lane_width", "parking_width", "sidewalk_width", "grid_cell", "margin"):
            if not getattr(self, name) > 0:
                raise ValueError(f"WorldConfig.{name} must be > 0, got {getattr(self, name)}")
        for name in (
            "facade_setback",
            "facade_length",
            "facade_depth",
            "facade_height",
            "car_speed",
            "pedestrian_speed",
        ):
            lo, hi = getattr(self, name)
            if not 0 <= lo <= hi:
                raise ValueError(f"WorldConfig.{name} must be a range 0 <= lo <= hi, got {lo, hi}")
        for name in ("parked_per_100m", "cars_per_100m", "pedestrians_per_100m", "sensor_noise"):
            if getattr(self, name) < 0:
                raise ValueError(f"WorldConfig.{name} must be >= 0, got {getattr(self, name)}")
        if not 0 <= self.facade_coverage <= 1 or not 0 <= self.crate_fraction <= 1:
            raise ValueError("WorldConfig.facade_coverage and crate_fraction must be in [0, 1]")
        if self.lanes_per_side < 0:
            raise ValueError(f"WorldConfig.lanes_per_side must be >= 0, got {self.lanes_per_side}")
        if not 0 <= self.exposure_corr < 1 or self.exposure_std < 0:
            raise ValueError("WorldConfig.exposure_corr must be in [0, 1), exposure_std >= 0")

    @property
    def road_half_width(self) -> float:
        """Distance from the path to the outer edge of the outer lane (metres)."""
        return self.lane_width * (self.lanes_per_side + 0.5)

    @property
    def kerb(self) -> float:
        """Distance from the path to the kerb (outer edge of the parking strip, metres)."""
        return self.road_half_width + self.parking_width

    @property
    def building_line(self) -> float:
        """Distance from the path to the back of the sidewalk (metres)."""
        return self.kerb + self.sidewalk_width
