"""The simulated spinning LiDARs' models: beam elevations, firings per revolution, range, noise
and dropouts, with the datasheets' figures of the HDL-64E, VLP-16, VLP-32C and OS1-128
(:data:`SENSORS`); :mod:`.lidar_sim` casts their rays."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

DEG = np.pi / 180.0

# HDL-64E S2 layout: the upper block's 32 lasers span +2° … −8.33° (≈1/3° apart), the lower
# block's 32 span −8.83° … −24.8° (≈1/2° apart).
HDL64E_UPPER_DEG = (2.0, -8.33)
HDL64E_LOWER_DEG = (-8.83, -24.8)
HDL64E_MIN_ELEVATION_DEG = HDL64E_LOWER_DEG[1]
HDL64E_MAX_ELEVATION_DEG = HDL64E_UPPER_DEG[0]
# The firing phase is not locked to the frame: each scan uses one of this many ray tables, each
# turned by a fraction of one azimuth step, so two scans from one pose sample different spots.
N_PHASES = 8


@dataclass(frozen=True, repr=False)
class LidarModel:
    """Parameters of the simulated sensor (the defaults: Velodyne HDL-64E S2)."""

    n_azimuth: int = 2000  # firings per revolution and laser (0.18° apart)
    max_range: float = 120.0  # m
    range_sigma: float = 0.02  # m, Gaussian range noise
    dropout: float = 0.02  # probability that any return is lost
    weak_dropout: float = 0.4  # extra loss probability of a zero-intensity return at max range
    intensity_noise: float = 0.05  # relative (multiplicative) intensity noise, standard deviation
    elevations_deg: tuple[float, ...] | None = None  # beam elevations, °; None = the HDL-64E's two blocks

    def __repr__(self) -> str:
        # The repr is part of the town's cache identity: the HDL-64E's (no elevations_deg) must
        # read as it always has, so the field is only shown when set.
        shown = [f for f in fields(self) if f.name != "elevations_deg" or self.elevations_deg is not None]
        return f"{type(self).__name__}({', '.join(f'{f.name}={getattr(self, f.name)!r}' for f in shown)})"

    @property
    def n_beams(self) -> int:
        return 64 if self.elevations_deg is None else len(self.elevations_deg)

    def elevations(self) -> np.ndarray:
        """(n_beams,) beam elevations in radians, top beam first."""
        if self.elevations_deg is not None:
            return np.sort(np.asarray(self.elevations_deg, np.float64))[::-1] * DEG
        upper = np.linspace(*HDL64E_UPPER_DEG, 32)
        lower = np.linspace(*HDL64E_LOWER_DEG, 32)
        return np.concatenate([upper, lower]) * DEG

    def ray_directions(self, phase: float = 0.0) -> np.ndarray:
        """(n_beams · n_azimuth, 3) float32 unit directions in the sensor frame, beam-major (ring
        order), the first firing of each beam ``phase`` azimuth steps after the x axis."""
        elevation = self.elevations()[:, None]
        azimuth = (np.arange(self.n_azimuth)[None, :] + phase) * (2.0 * np.pi / self.n_azimuth)
        dirs = np.stack(
            np.broadcast_arrays(
                np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)
            ),
            axis=-1,
        )
        return dirs.reshape(-1, 3).astype(np.float32)


# Datasheet sensors. Dropouts are not on any datasheet: every model keeps the HDL-64E's 2 % plus
# the weak-return loss, which scales with its own maximum range.
SENSORS: dict[str, LidarModel] = {
    # Velodyne HDL-64E S2 datasheet: 64 lasers, +2° … −24.8°, 0.09° azimuth resolution at 5 Hz,
    # 120 m range, < 2 cm accuracy (the model above; 2000 firings at 10 Hz, 0.18° apart).
    "hdl64e": LidarModel(),
    # Velodyne VLP-16 (Puck) datasheet 63-9229: 16 channels over ±15° every 2°, 0.2° azimuth
    # resolution at 10 Hz (1800 firings), range up to 100 m, accuracy ±3 cm (typical).
    "vlp16": LidarModel(
        n_azimuth=1800, max_range=100.0, range_sigma=0.03, elevations_deg=tuple(float(e) for e in range(-15, 16, 2))
    ),
    # Velodyne VLP-32C (Ultra Puck) datasheet 63-9378 and user manual 63-9325 (vertical angle per
    # laser ID): 32 channels, −25° … +15°, densest (0.33°) around the horizon; 0.2° azimuth
    # resolution at 10 Hz (1800 firings), range up to 200 m, accuracy ±3 cm.
    "vlp32c": LidarModel(
        n_azimuth=1800,
        max_range=200.0,
        range_sigma=0.03,
        elevations_deg=(
            -25.0,
            -15.639,
            -11.31,
            -8.843,
            -7.254,
            -6.148,
            -5.333,
            -4.667,
            -4.0,
            -3.667,
            -3.333,
            -3.0,
            -2.667,
            -2.333,
            -2.0,
            -1.667,
            -1.333,
            -1.0,
            -0.667,
            -0.333,
            0.0,
            0.333,
            0.667,
            1.0,
            1.333,
            1.667,
            2.333,
            3.333,
            4.667,
            7.0,
            10.333,
            15.0,
        ),
    ),
    # Ouster OS1-128 datasheet (rev. 6): 128 channels, uniform over 45° (±22.5°, 0.35° apart),
    # 1024 × 10 Hz mode (the sensor's default), 120 m range, accuracy ±3 cm (Lambertian targets).
    "os1-128": LidarModel(
        n_azimuth=1024,
        max_range=120.0,
        range_sigma=0.03,
        elevations_deg=tuple(float(e) for e in np.round(np.linspace(-22.5, 22.5, 128), 4)),
    ),
}
