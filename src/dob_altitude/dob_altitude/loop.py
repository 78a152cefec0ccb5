"""The altitude node's loop core (pure): apron state, reference, attitude in; thrust out.

Everything between the node's subscriptions and ``control/thrust``, on plain numbers: inputs
gated (finite, stamps in order and not stale or future against ``now``, known vertical
frame, unit orientation), the command withheld — and the controller reset, so that it
restarts bumpless — while control is disabled, an input is stale or the vertical estimate is
invalid, a reset on a switch of the vertical frame, and ``dt`` from the apron stamps. The
node, the in-process runner and the golden replay call it; the laws are
:mod:`dob_altitude.dob` / :mod:`dob_altitude.pid`, wired by :mod:`dob_altitude.adapter`.
"""

from __future__ import annotations

import math

from deckland_common.checks import InputGuard, finite
from deckland_common.contract import (
    VERTICAL_RELATIVE,
    ApronState,
    VerticalReference,
    parse_vertical_frame,
)
from deckland_common.frames import quaternion_to_euler

from deckland_common import validate as chk
from dob_altitude import adapter
from dob_altitude.adapter import ROTOR_HEIGHT_OFFSET_M, AltitudeController
from dob_altitude.types import AltitudeOutput

REJECTED = ('non_finite', 'bad_size', 'bad_layout', 'out_of_order', 'stale_stamp',
            'future_stamp', 'bad_frame', 'bad_quaternion')
WITHHELD = ('disabled', 'stale', 'invalid_vertical', 'non_finite_output')



class AltitudeLoop(InputGuard):
    """The altitude node between its inputs and ``control/thrust``.

    Each accepted apron state steps the controller once (:meth:`on_apron`) with the latest
    accepted reference and attitude; dt is the difference of the apron stamps (the first step
    after a reset uses ``period_s``, which the cores ignore).

    Args:
        controller: the altitude law (``adapter.make_controller``).
        period_s: nominal control period (s).
        input_timeout_s: max age of the apron state, reference and attitude stamps.
        rotor_height_offset_m: rotor plane above the body origin (z_p of (4)).
        surface_accel_ff: feed the estimated surface acceleration forward (relative frame).
        require_valid_vertical: withhold while the vertical estimate is invalid (the node);
            False flies through it on the filter's prediction (the in-process runner, as it
            always has).
    """

    def __init__(self, controller: AltitudeController, period_s: float = 0.01,
                 input_timeout_s: float = 0.2,
                 rotor_height_offset_m: float = ROTOR_HEIGHT_OFFSET_M,
                 surface_accel_ff: bool = False, require_valid_vertical: bool = True) -> None:
        chk.positive('AltitudeLoop.period_s', period_s)
        chk.positive('AltitudeLoop.input_timeout_s', input_timeout_s)
        chk.in_range('AltitudeLoop.rotor_height_offset_m', rotor_height_offset_m, 0.0, 1.0)
        super().__init__(REJECTED, WITHHELD)
        self.controller = controller
        self.period_s = float(period_s)
        self.timeout_s = float(input_timeout_s)
        self.offset_m = float(rotor_height_offset_m)
        self.surface_accel_ff = bool(surface_accel_ff)
        self.require_valid_vertical = bool(require_valid_vertical)
        self.apron: ApronState | None = None
        # the latest reference and attitude with their stamps (-inf: none yet); plain
        # attributes, set every tick (see reference / attitude)
        self._t_ref = self._t_att = -math.inf
        self._z_d = self._z_d_dot = self._z_d_ddot = 0.0
        self._frame = VERTICAL_RELATIVE
        self._roll = self._pitch = 0.0
        self._frame_name = VERTICAL_RELATIVE   # the last frame name accepted, and its frame
        self._frame_parsed = VERTICAL_RELATIVE
        self.enabled = True
        self.need_reset = True
        self.last_t_s = 0.0          # t_s of the apron state of the last step
        self.frame_used = ''
        self.last_output: AltitudeOutput | None = None
        #: controller steps, resets, frame switches
        self.counts: dict[str, int] = {'steps': 0, 'resets': 0, 'frame_switches': 0}

    # --- inputs ------------------------------------------------------------------------------

    def on_apron(self, now_s: float, state: ApronState,
                 reference: VerticalReference | None = None,
                 dt_s: float | None = None) -> AltitudeOutput | None:
        """Accept ``state`` and step on it: the command to publish, or None (withheld).

        ``reference`` replaces the latest received one for this step (a replay that knows
        which one the node had); ``dt_s`` replaces the stamp difference (a caller stepping
        on a fixed schedule, the in-process runner).
        """
        v = state.vertical
        if not (finite(state.t_s) and finite(v.height_m)
                and finite(v.closing_speed_mps) and finite(v.vehicle_altitude_m)
                and finite(v.vehicle_vz_mps) and finite(v.surface_accel_mps2)):
            self.reject('non_finite', 'apron/state')
            return None
        last = self.apron.t_s if self.apron is not None else -math.inf
        if state.t_s == last:
            self.reject('out_of_order', 'apron/state (repeated t_s)')
            return None
        if not self.check_stamp(state.t_s, last, now_s, self.timeout_s, 'apron/state'):
            return None
        self.apron = state
        return self._step(now_s, reference, dt_s)

    def on_reference(self, now_s: float, stamp_s: float, frame_name: str, z_d_m: float,
                     z_d_dot_mps: float, z_d_ddot_mps2: float) -> bool:
        """The vertical part of ``planner/reference`` (``frame_name``: its joint name)."""
        if not (finite(z_d_m) and finite(z_d_dot_mps) and finite(z_d_ddot_mps2)):
            self.reject('non_finite', 'planner/reference')
            return False
        # parsed once per change of the name (the planner changes it once per mode switch)
        frame = (self._frame_parsed if frame_name == self._frame_name
                 else parse_vertical_frame(frame_name))
        if frame is None:
            self.reject('bad_frame', f'planner/reference (joint name {frame_name!r})')
            return False
        if not self.check_stamp(stamp_s, self._t_ref, now_s, self.timeout_s,
                                'planner/reference'):
            return False
        self._frame_name, self._frame_parsed = frame_name, frame
        self._z_d, self._z_d_dot, self._z_d_ddot = z_d_m, z_d_dot_mps, z_d_ddot_mps2
        self._frame, self._t_ref = frame, stamp_s
        return True

    @property
    def reference(self) -> VerticalReference | None:
        """The latest accepted reference (None before the first)."""
        if self._t_ref == -math.inf:
            return None
        return VerticalReference(self._z_d, self._z_d_dot, self._z_d_ddot, self._frame,
                                 self._t_ref)

    @property
    def attitude(self) -> tuple[float, float, float] | None:
        """The latest accepted (roll, pitch, stamp), None before the first."""
        return None if self._t_att == -math.inf else (self._roll, self._pitch, self._t_att)

    def on_imu(self, now_s: float, stamp_s: float, q: tuple[float, float, float, float],
               has_orientation: bool = True) -> bool:
        """``vehicle/imu`` orientation (w, x, y, z) → roll and pitch."""
        if not has_orientation:   # REP-145: no orientation estimate
            self.reject('bad_quaternion', 'vehicle/imu (no orientation)')
            return False
        qn = self.unit_quaternion(q, 'vehicle/imu orientation')
        if qn is None:
            return False
        roll, pitch, _ = quaternion_to_euler(qn[0], qn[1], qn[2], qn[3])
        return self.on_attitude(now_s, stamp_s, roll, pitch)

    def on_attitude(self, now_s: float, stamp_s: float, roll_rad: float,
                    pitch_rad: float) -> bool:
        """Roll and pitch already as angles (the in-process runner)."""
        if not (finite(roll_rad) and finite(pitch_rad)):
            self.reject('non_finite', 'attitude')
            return False
        if not self.check_stamp(stamp_s, self._t_att, now_s, self.timeout_s, 'vehicle/imu'):
            return False
        self._roll, self._pitch, self._t_att = roll_rad, pitch_rad, stamp_s
        return True

    def on_enabled(self, enabled: bool) -> None:
        """``control/enabled``: False withholds every command and resets the controller."""
        self.enabled = enabled
        if not enabled:
            self._reset()

    def watchdog(self, now_s: float) -> None:
        """Staleness without any apron state arriving: count it and reset the controller."""
        reason = self.withhold_reason(now_s)
        if reason:
            self._withhold(reason)

    # --- the step ----------------------------------------------------------------------------

    def withhold_reason(self, now_s: float) -> str:
        """Why no command may be computed at ``now_s`` ('' = it may)."""
        if not self.enabled:
            return 'disabled'
        apron = self.apron
        if apron is None or now_s - apron.t_s > self.timeout_s:
            return 'stale'
        # never received: the stamp is -inf, now - stamp = inf
        if now_s - self._t_ref > self.timeout_s or now_s - self._t_att > self.timeout_s:
            return 'stale'
        if self.require_valid_vertical and not apron.vertical.valid:
            return 'invalid_vertical'
        return ''

    def _reset(self) -> None:
        if not self.need_reset:
            self.counts['resets'] += 1
        self.controller.reset()
        self.need_reset = True

    def _withhold(self, reason: str) -> None:
        self.withhold(reason)
        self._reset()

    def _step(self, now_s: float, reference: VerticalReference | None,
              dt_s: float | None) -> AltitudeOutput | None:
        reason = self.withhold_reason(now_s)
        st = self.apron
        if reason or st is None:
            self._withhold(reason or 'stale')
            return None
        if reference is not None:
            z_d, z_d_dot = reference.z_d_m, reference.z_d_dot_mps
            z_d_ddot, frame = reference.z_d_ddot_mps2, reference.frame
        else:
            z_d, z_d_dot, z_d_ddot, frame = self._z_d, self._z_d_dot, self._z_d_ddot, self._frame
        dt = dt_s if dt_s is not None else st.t_s - self.last_t_s
        if frame != self.frame_used and not self.need_reset:
            self.counts['frame_switches'] += 1
            self._reset()
        if self.need_reset or not 0.0 < dt <= self.timeout_s:
            self.controller.reset()  # bumpless (re)start: the cores initialise on this sample
            dt = self.period_s
        inp = adapter.altitude_input(st.vertical, z_d, z_d_dot, z_d_ddot, frame, self._roll,
                                     self._pitch, self.offset_m, self.surface_accel_ff)
        out = self.controller.step(inp, dt)
        self.counts['steps'] += 1
        if not (finite(out.thrust_n) and finite(out.sigma) and finite(out.d_hat_mps2)
                and finite(out.e_z_m)):
            self.withheld['non_finite_output'] += 1  # defensive: the cores never do this
            self._reset()
            return None
        self.need_reset = False
        self.withheld_reason = ''
        self.last_t_s = st.t_s
        self.frame_used = frame
        self.last_output = out
        return out
