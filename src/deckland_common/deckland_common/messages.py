"""The contract's value types ↔ ``deckland_interfaces`` messages, field for field (no rclpy).

The functions fill or read message *objects* passed in, by attribute name only, so the same
code serves rclpy's generated classes (the nodes) and rosbags' decoded messages (plot, golden
replay, the Foxglove view). Renames and encodings: ``src/deckland_interfaces/README.md``.
Decoders never raise on bad input: they return ``None`` plus a counter name and a detail.
"""

from __future__ import annotations

import math
import re
from typing import Any

from deckland_common.contract import (
    DECK_SOURCE_BEACON,
    DECK_SOURCE_NONE,
    DECK_SOURCE_PREDICTION,
    DECK_SOURCE_TELEMETRY,
    VERTICAL_FRAMES,
    ApronState,
    Mode,
    PlannerOutput,
    VerticalState,
)
from deckland_common.frames import euler_to_quaternion, quaternion_to_euler

#: ``ApronState.source`` values (the constants of ApronState.msg)
SOURCE_NONE, SOURCE_BEACON, SOURCE_TELEMETRY, SOURCE_PREDICTION = 0, 1, 2, 3
SOURCE_CODES = {DECK_SOURCE_NONE: SOURCE_NONE, DECK_SOURCE_BEACON: SOURCE_BEACON,
                DECK_SOURCE_TELEMETRY: SOURCE_TELEMETRY,
                DECK_SOURCE_PREDICTION: SOURCE_PREDICTION}
SOURCE_NAMES = {code: name for name, code in SOURCE_CODES.items()}
#: ``AltitudeState.controller`` values
CONTROLLER_CODES = {'dob': 0, 'pid': 1}
_STEP = re.compile(r'Step (\d+)')


def s_to_time(t_s: float, stamp: Any) -> Any:
    """Fill a builtin_interfaces/Time in place from seconds (zero for -inf); returns it."""
    if not math.isfinite(t_s):
        stamp.sec, stamp.nanosec = 0, 0
        return stamp
    sec = math.floor(t_s)
    stamp.sec = int(sec)
    stamp.nanosec = min(round((t_s - sec) * 1e9), 999_999_999)
    return stamp


def time_to_s(stamp: Any) -> float:
    """builtin_interfaces/Time → seconds."""
    return stamp.sec + stamp.nanosec * 1e-9


def vertical_frame_code(name: str) -> int:
    """A contract vertical frame name → its ``VERTICAL_*`` constant."""
    return VERTICAL_FRAMES.index(name)


def vertical_frame_name(code: int) -> str:
    """A ``VERTICAL_*`` constant → the frame name; an unknown code gives a name the
    consumers' :func:`~deckland_common.contract.parse_vertical_frame` refuses."""
    return VERTICAL_FRAMES[code] if 0 <= code < len(VERTICAL_FRAMES) else f'#{code}'


def paper_step(reason: str) -> int:
    """The last "Step N" of a transition reason (0 when it names none)."""
    steps = _STEP.findall(reason)
    return int(steps[-1]) if steps else 0


# --- ApronState ------------------------------------------------------------------------------

def fill_apron_state(msg: Any, st: ApronState, frame_id: str = '') -> Any:
    """Fill an ``ApronState`` message from the estimator's state; returns it."""
    s_to_time(st.t_s, msg.header.stamp)
    msg.header.frame_id = frame_id
    s_to_time(st.camera_stamp_s, msg.camera_stamp)
    msg.source = SOURCE_CODES.get(st.source, SOURCE_NONE)
    msg.tracked = st.tracked
    msg.visible = st.visible
    msg.time_since_seen_s = st.time_since_seen_s
    msg.rel_position_m = st.rel_position_m
    msg.rel_velocity_mps = st.rel_velocity_mps
    vx, vy = st.rel_position_var_m2
    msg.rel_position_cov_m2 = (vx, 0.0, 0.0, vy)
    msg.rel_position_body_m = st.rel_position_body_m
    msg.rel_velocity_body_mps = st.rel_velocity_body_mps
    msg.apron_position_m = st.apron_position_m
    msg.apron_velocity_mps = st.apron_velocity_mps
    msg.apron_accel_mps2 = st.apron_accel_mps2
    msg.deck_attitude_valid = st.deck_attitude_valid
    roll, pitch, yaw = st.deck_rpy_rad if st.deck_attitude_valid else (0.0, 0.0, 0.0)
    q, w = msg.deck_orientation, msg.deck_angular_velocity_radps
    q.w, q.x, q.y, q.z = euler_to_quaternion(roll, pitch, yaw)
    # only the yaw rate is carried: the deck-frame rate of a pure heading change
    # (Z-Y-X kinematics with φ̇ = θ̇ = 0): ψ̇ · (−sin θ, cos θ sin φ, cos θ cos φ)
    r = st.deck_yaw_rate_radps if st.deck_attitude_valid else 0.0
    cp = math.cos(pitch)
    w.x, w.y, w.z = -r * math.sin(pitch), r * cp * math.sin(roll), r * cp * math.cos(roll)
    v, mv = st.vertical, msg.vertical
    mv.valid = v.valid
    mv.height_m = v.height_m
    mv.closing_speed_mps = v.closing_speed_mps
    mv.vehicle_altitude_m = v.vehicle_altitude_m
    mv.vehicle_vz_mps = v.vehicle_vz_mps
    mv.surface_height_m = v.surface_height_m
    mv.surface_vz_mps = v.surface_vz_mps
    mv.surface_accel_mps2 = v.surface_accel_mps2
    mv.surface_epoch = v.surface_epoch
    mv.last_rebase_m = v.last_rebase_m
    return msg


def fill_rivals(msg: Any, rivals: Any, t_s: float, confirm_hits: int, make: Any) -> Any:
    """``msg.rivals`` (``ApronState``) from the tracker's rival hypotheses at ``t_s``
    (``apron_estimator.horizontal.HorizontalTracker.rivals``: offset from the track, net hits,
    the surface level sampled under it, rejected, last seen); ``make()`` builds one ``Rival``
    message. A rival is confirmed at ``confirm_hits``. Returns ``msg``."""
    out = []
    for rv in rivals:
        m = make()
        m.offset_m = (float(rv.dx), float(rv.dy))
        m.hits = max(0, min(65535, int(rv.hits)))
        m.confirmed = rv.hits >= confirm_hits
        m.sampled = rv.surface is not None
        m.surface_level_m = float(rv.surface) if rv.surface is not None else 0.0
        m.rejected = bool(rv.rejected)
        m.time_since_seen_s = max(0.0, t_s - rv.t_seen)
        out.append(m)
    msg.rivals = out
    return msg


def _pair(a: Any) -> tuple[float, float]:
    return (float(a[0]), float(a[1]))


def _deck_fields(m: Any) -> dict[str, Any]:
    """The moving-deck fields of an ``ApronState`` message, as contract keyword arguments."""
    source = SOURCE_NAMES.get(int(m.source))
    if source is None:
        raise ValueError(f'unknown source {m.source}')
    valid = bool(m.deck_attitude_valid)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw_rate = 0.0
    if valid:
        q, w = m.deck_orientation, m.deck_angular_velocity_radps
        norm = math.sqrt(q.w * q.w + q.x * q.x + q.y * q.y + q.z * q.z)
        if not norm > 0.0:
            raise ValueError('deck_orientation is not a rotation')
        rpy = quaternion_to_euler(q.w / norm, q.x / norm, q.y / norm, q.z / norm)
        cp = math.cos(rpy[1])
        # ψ̇ = (ω_y sin φ + ω_z cos φ) / cos θ (Z-Y-X Euler kinematics)
        yaw_rate = ((float(w.y) * math.sin(rpy[0]) + float(w.z) * math.cos(rpy[0])) / cp
                    if abs(cp) > 1e-6 else 0.0)
    return {'source': source, 'apron_accel_mps2': _pair(m.apron_accel_mps2),
            'deck_attitude_valid': valid, 'deck_rpy_rad': rpy, 'deck_yaw_rate_radps': yaw_rate}


def apron_state_from_msg(m: Any) -> tuple[ApronState | None, str, str]:
    """An ``ApronState`` message → ``(state, reason, detail)``; ``state`` None = reject it
    (``reason`` ``'bad_size'`` or ``'non_finite'``: the consumers' counter names)."""
    try:
        if len(m.rel_position_cov_m2) != 4:
            return None, 'bad_size', 'apron/state (rel_position_cov_m2 is not 2x2)'
        mv = m.vertical
        cov = m.rel_position_cov_m2
        cam = m.camera_stamp
        vertical = VerticalState(bool(mv.valid), float(mv.height_m),
                                 float(mv.closing_speed_mps), float(mv.vehicle_altitude_m),
                                 float(mv.vehicle_vz_mps), float(mv.surface_height_m),
                                 float(mv.surface_vz_mps), float(mv.surface_accel_mps2),
                                 int(mv.surface_epoch), float(mv.last_rebase_m))
        st = ApronState(
            t_s=time_to_s(m.header.stamp), tracked=bool(m.tracked), visible=bool(m.visible),
            time_since_seen_s=float(m.time_since_seen_s),
            rel_position_m=_pair(m.rel_position_m), rel_velocity_mps=_pair(m.rel_velocity_mps),
            rel_position_var_m2=(float(cov[0]), float(cov[3])),
            rel_position_body_m=_pair(m.rel_position_body_m),
            rel_velocity_body_mps=_pair(m.rel_velocity_body_mps),
            apron_position_m=_pair(m.apron_position_m),
            apron_velocity_mps=_pair(m.apron_velocity_mps), vertical=vertical,
            camera_stamp_s=(time_to_s(cam) if cam.sec or cam.nanosec else -math.inf),
            **_deck_fields(m))
    except (IndexError, TypeError, ValueError, AttributeError) as exc:
        return None, 'bad_size', f'apron/state: {exc}'
    if st.has_nan() or cov[1] != cov[1] or cov[2] != cov[2]:
        return None, 'non_finite', 'apron/state: NaN in a field'
    return st, '', ''


# --- planner -------------------------------------------------------------------------------

def fill_planner_reference(msg: Any, out: PlannerOutput, stamp_s: float,
                           frame_id: str = '') -> Any:
    """Fill a ``PlannerReference`` message from one planner output; returns it."""
    s_to_time(stamp_s, msg.header.stamp)
    msg.header.frame_id = frame_id
    msg.vertical_frame = vertical_frame_code(out.vertical_mode)
    msg.setpoint_m = out.setpoint_m
    msg.velocity_ff_mps = out.velocity_ff_mps
    msg.accel_ff_mps2 = out.accel_ff_mps2
    msg.yaw_rad = out.yaw_rad
    msg.z_d_m = out.z_d_m
    msg.z_d_dot_mps = out.z_d_dot_mps
    msg.z_d_ddot_mps2 = out.z_d_ddot_mps2
    msg.precise_xy = out.precise_xy
    msg.thrust_enabled = out.thrust_enabled
    return msg


def fill_planner_status(msg: Any, mode: Mode, previous: Mode, transition_s: float,
                        reason: str, searches: int) -> Any:
    """Fill the mode part of a ``PlannerStatus`` (``reference`` is filled by the caller with
    :func:`fill_planner_reference`); returns it."""
    msg.mode = mode.value
    msg.previous_mode = previous.value
    s_to_time(transition_s, msg.transition_stamp)
    msg.reason = reason
    msg.paper_step = min(paper_step(reason), 255)
    msg.searches = min(max(searches, 0), 255)
    return msg


def mode_name(code: int) -> str:
    """A ``MODE_*`` constant → the mode's name (``'?N'`` when unknown)."""
    try:
        return Mode(code).name
    except ValueError:
        return f'?{code}'


# --- altitude ------------------------------------------------------------------------------

def fill_altitude_state(msg: Any, t_s: float, controller: str, frame: str, inp: Any,
                        out: Any, frame_id: str = '') -> Any:
    """Fill an ``AltitudeState`` from one controller step (``inp``: the
    :class:`~dob_altitude.types.AltitudeInput`, ``out``: its ``AltitudeOutput``)."""
    s_to_time(t_s, msg.header.stamp)
    msg.header.frame_id = frame_id
    msg.controller = CONTROLLER_CODES[controller]
    msg.vertical_frame = vertical_frame_code(frame)
    msg.z_m = inp.z_m
    msg.z_dot_mps = inp.z_dot_mps
    msg.z_d_m = inp.z_d_m
    msg.z_d_dot_mps = inp.z_d_dot_mps
    msg.e_z_m = out.e_z_m
    msg.sigma = out.sigma
    msg.d_hat_mps2 = out.d_hat_mps2
    msg.thrust_n = out.thrust_n
    # an absurd (finite) input can overflow the unsaturated law to ±inf: the message never
    # carries a non-finite number, so it then says the saturated value, flagged saturated
    unsat_ok = math.isfinite(out.thrust_unsat_n)
    msg.thrust_unsat_n = out.thrust_unsat_n if unsat_ok else out.thrust_n
    msg.saturated = out.saturated or not unsat_ok
    msg.gamma_bar = out.gamma_bar
    return msg
