"""Every honest sensor model of one seed with its timing: what the World will hold (pure).

``SensorSuite(params, seed)`` builds the IMU, attitude estimate, EKF local
position, LIDAR-Lite and camera models from the streams ``f'{seed}:<name>:draw|noise|timing'``
(names: :data:`SENSOR_NAMES`) and one :class:`~deck_simulator.sensor_models.SensorTiming` per
sensor. The World samples a model on its timing's clock and reads what has been delivered;
the wiring (which truth, which stamps, which YAML keys) is docs/world/sensors.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from deckland_common.frames import Vec3

from deck_simulator.sensor_camera import CameraModel, CameraModelParams
from deck_simulator.sensor_ekf import LocalPositionModel, LocalPositionParams
from deck_simulator.sensor_imu import AttitudeModel, AttitudeModelParams, ImuModel, ImuModelParams
from deck_simulator.sensor_lidar import LidarLiteModel, LidarLiteParams
from deck_simulator.sensor_models import SensorTiming, TimingParams, model_streams
from deck_simulator.sensors import Block, CameraParams
from deckland_common import validate as chk

#: Stream names of the models, one per sensor (``f'{seed}:{name}:draw'`` etc.).
SENSOR_NAMES = ('imu', 'attitude', 'local_position', 'lidar', 'camera')


@dataclass(frozen=True, slots=True)
class SensorSuiteParams:
    """The YAML-facing bundle, one section per sensor (``sensors.<name>.*``): ``camera`` is
    the nominal camera (what the estimator is configured with), ``true_camera`` how the
    simulated one differs from it."""

    camera: CameraParams = field(default_factory=CameraParams)
    true_camera: CameraModelParams = field(default_factory=CameraModelParams)
    imu: ImuModelParams = field(default_factory=ImuModelParams)
    attitude: AttitudeModelParams = field(default_factory=AttitudeModelParams)
    local_position: LocalPositionParams = field(default_factory=LocalPositionParams)
    lidar: LidarLiteParams = field(default_factory=LidarLiteParams)

    def __post_init__(self) -> None:
        for name, cls in (('camera', CameraParams), ('true_camera', CameraModelParams),
                          ('imu', ImuModelParams), ('attitude', AttitudeModelParams),
                          ('local_position', LocalPositionParams), ('lidar', LidarLiteParams)):
            chk.require(isinstance(getattr(self, name), cls), name,
                        f'must be {cls.__name__}', getattr(self, name))


class SensorSuite:
    """Models and timings of one seed. Payloads: IMU (specific force FLU, rate FLU);
    attitude (roll, pitch, yaw); local position (position ENU, velocity ENU); lidar range
    (m or None); camera blocks."""

    __slots__ = ('attitude', 'attitude_timing', 'camera', 'camera_timing', 'imu', 'imu_timing',
                 'lidar', 'lidar_timing', 'local_position', 'local_position_timing', 'params',
                 'seed')

    def __init__(self, params: SensorSuiteParams, seed: int, gravity_mps2: float = 9.81,
                 start_s: float = 0.0) -> None:
        self.params = params
        self.seed = seed
        p = params
        s = model_streams(seed, 'imu')
        self.imu_timing: SensorTiming[tuple[Vec3, Vec3]] = SensorTiming(
            p.imu.timing, s.timing, s.timing_normal, start_s)
        self.imu = ImuModel(p.imu, s, self.imu_timing.period_s, gravity_mps2)
        s = model_streams(seed, 'attitude')
        self.attitude_timing: SensorTiming[Vec3] = SensorTiming(
            p.attitude.timing, s.timing, s.timing_normal, start_s)
        self.attitude = AttitudeModel(p.attitude, s, self.attitude_timing.period_s)
        s = model_streams(seed, 'local_position')
        self.local_position_timing: SensorTiming[tuple[Vec3, Vec3]] = SensorTiming(
            p.local_position.timing, s.timing, s.timing_normal, start_s)
        self.local_position = LocalPositionModel(p.local_position, s,
                                                 self.local_position_timing.period_s)
        s = model_streams(seed, 'lidar')
        self.lidar_timing: SensorTiming[float | None] = SensorTiming(
            p.lidar.timing, s.timing, s.timing_normal, start_s)
        self.lidar = LidarLiteModel(p.lidar, s)
        s = model_streams(seed, 'camera')
        self.camera_timing: SensorTiming[list[Block]] = SensorTiming(
            p.true_camera.timing, s.timing, s.timing_normal, start_s)
        self.camera = CameraModel(p.true_camera, p.camera, s)


def _ideal_timing(tp: TimingParams) -> TimingParams:
    return TimingParams(rate_hz=tp.rate_hz, random_phase=False)


def ideal_sensors(params: SensorSuiteParams) -> SensorSuiteParams:
    """``params`` with every error and delay of the honest models set to zero (rates kept):
    truth at the sensors' rates, stamped exactly, through a camera equal to the nominal one
    (no distortion) — for analytic tests of the world, never for judging the stack. The
    nominal camera's own pixel noise, dropouts and glints are left as given."""
    p = params
    imu = replace(p.imu, accel_noise_density=0.0, accel_vibration_density=0.0,
                  accel_bias_instability=0.0, accel_turn_on_bias_std=0.0,
                  gyro_noise_density=0.0, gyro_vibration_density=0.0,
                  gyro_bias_instability=0.0, gyro_turn_on_bias_std=0.0,
                  timing=_ideal_timing(p.imu.timing))
    att = replace(p.attitude, tilt_bias_std_rad=0.0, tilt_drift_std_rad=0.0,
                  tilt_noise_rad=0.0, yaw_bias_std_rad=0.0, yaw_drift_std_rad=0.0,
                  yaw_noise_rad=0.0, timing=_ideal_timing(p.attitude.timing))
    lp = p.local_position
    axis0 = {'bias_std_m': 0.0, 'bias_random_walk_m_rts': 0.0, 'velocity_std_mps': 0.0}
    pos = replace(lp, horizontal=replace(lp.horizontal, **axis0),
                  vertical=replace(lp.vertical, **axis0), timing=_ideal_timing(lp.timing))
    li = replace(p.lidar, offset_std_m=0.0, scale_std=0.0, noise_std_m=0.0,
                 noise_std_far_m=0.0, near_bias_m=0.0, near_noise_gain=0.0,
                 resolution_m=1e-9, timing=_ideal_timing(p.lidar.timing))
    cam = replace(p.true_camera, k1=0.0, k2=0.0, p1=0.0, p2=0.0, k_rel_std=0.0, p_std=0.0,
                  focal_rel_std=0.0, principal_point_std_px=0.0,
                  mount_std_rad=(0.0, 0.0, 0.0), exposure_jitter_s=0.0,
                  rolling_readout_s=0.0, timing=_ideal_timing(p.true_camera.timing))
    return replace(p, imu=imu, attitude=att, local_position=pos, lidar=li, true_camera=cam)
