"""The ship's telemetry: the link model's statistics (deck_simulator.ship_link) and the
bridge's decode (mavlink_bridge.ship): system id, units, NED → ENU, clock, stale and
out-of-order messages, and a pymavlink wire round trip."""

from __future__ import annotations

import itertools
import math
import statistics

from deck_simulator.deck_motion import PadState
from deck_simulator.ship_link import (
    Attitude,
    GlobalPositionInt,
    ShipLink,
    ShipTelemetryParams,
    enu_to_geodetic,
)
from deckland_common.frames import rot_body_to_world
from mavlink_bridge.ship import (
    DeckOdomAssembler,
    ShipDecodeParams,
    ShipTelemetryDecoder,
    geodetic_to_enu,
    yaw_rate_from_body_rates,
)
import pytest

ORIGIN = (54.32, 10.15, 0.0)


def sailing_pad(t: float) -> PadState:
    """A pad sailing north-east at (2, 1) m/s, rolling 3° at 0.1 Hz, yaw rate 0.02 rad/s."""
    roll = 0.05 * math.sin(2 * math.pi * 0.1 * t)
    droll = 0.05 * 2 * math.pi * 0.1 * math.cos(2 * math.pi * 0.1 * t)
    yaw = 0.4 + 0.02 * t
    rpy = (roll, 0.0, yaw)
    r = rot_body_to_world(*rpy)
    # ω (world) of Z-Y-X angles with zero pitch: ψ̇ e_z + φ̇ (Rz(ψ) e_x)
    omega = (droll * math.cos(yaw), droll * math.sin(yaw), 0.02)
    return PadState((2.0 * t + 5.0, 1.0 * t - 3.0, 2.5), (2.0, 1.0, 0.0), (0.0, 0.0, 0.0), rpy,
                    omega, (0.0, 0.0, 0.0), r)


def collect(params: ShipTelemetryParams, duration_s: float = 600.0, seed: str = '1:ship_link'):
    link = ShipLink(params, sailing_pad, seed)
    out = []
    t = 0.0
    while t < duration_s:
        t += 0.01
        out.extend(link.poll(t))
    return link, out


def test_rates_loss_and_latency_follow_the_parameters():
    p = ShipTelemetryParams(loss_probability=0.1, latency_s=0.2, jitter_s=0.05)
    link, msgs = collect(p)
    n_pos_sent = 600.0 * p.position_rate_hz
    n_att_sent = 600.0 * p.attitude_rate_hz
    assert link.sent == pytest.approx(n_pos_sent + n_att_sent, abs=3)
    # loss: binomial, 9000 trials at 0.1 -> σ = 0.0032; 4σ bound
    assert link.lost / link.sent == pytest.approx(0.1, abs=0.013)
    assert len(msgs) == link.sent - link.lost - link.in_flight
    # latency = 0.2 + Exp(mean 0.05): the ship clock runs 20 ppm fast from 1234.5 s
    delays = []
    for t_rx, m in msgs:
        t_ship = m.time_boot_ms * 1e-3
        t_sent = (t_ship - p.clock_offset_s) / (1.0 + p.clock_drift_ppm * 1e-6)
        delays.append(t_rx - t_sent)
    assert min(delays) >= 0.2 - 0.002       # ms quantisation of the stamp
    assert statistics.fmean(delays) == pytest.approx(0.25, abs=0.004)   # σ/√n = 0.0006
    assert statistics.median(delays) == pytest.approx(0.2 + 0.05 * math.log(2), abs=0.004)
    kinds = {m.get_type() for _, m in msgs}
    assert kinds == {'GLOBAL_POSITION_INT', 'ATTITUDE'}


def test_position_error_has_the_stated_bias_and_noise():
    """Across seeds the bias is N(0, σ_b) per axis; within one run the white noise is σ_n."""
    p = ShipTelemetryParams(loss_probability=0.0, position_noise_m=0.05)
    first_errors = []
    for seed in range(200):
        link = ShipLink(p, sailing_pad, f'{seed}:ship_link')
        msgs = link.poll(0.6)
        m = next(m for _, m in msgs if isinstance(m, GlobalPositionInt))
        t_sent = (m.time_boot_ms * 1e-3 - p.clock_offset_s) / (1.0 + p.clock_drift_ppm * 1e-6)
        e, n, _ = geodetic_to_enu(p.origin, m.lat, m.lon, m.alt)
        truth = sailing_pad(t_sent).position_m
        first_errors.append(e - truth[0])
        first_errors.append(n - truth[1])
    # 400 samples of N(0, sqrt(0.8² + 0.05²)): sample σ within ±15 %
    assert statistics.pstdev(first_errors) == pytest.approx(math.hypot(0.8, 0.05), rel=0.15)
    assert abs(statistics.fmean(first_errors)) < 4 * 0.8 / math.sqrt(400)
    # within one run: consecutive differences are the white noise (the bias moves slowly)
    link, msgs = collect(p, duration_s=120.0)
    errs = []
    for _, m in msgs:
        if isinstance(m, GlobalPositionInt):
            t_sent = (m.time_boot_ms * 1e-3 - p.clock_offset_s) / (1.0 + p.clock_drift_ppm * 1e-6)
            e, _, _ = geodetic_to_enu(p.origin, m.lat, m.lon, m.alt)
            errs.append(e - sailing_pad(t_sent).position_m[0])
    diffs = [b - a for a, b in itertools.pairwise(errs)]
    assert statistics.pstdev(diffs) == pytest.approx(0.05 * math.sqrt(2), rel=0.2)


def test_outage_drops_everything_in_its_window():
    p = ShipTelemetryParams(loss_probability=0.0, outage_start_s=10.0, outage_duration_s=5.0)
    _, msgs = collect(p, duration_s=30.0)
    arrivals = [t for t, _ in msgs]
    assert not [t for t in arrivals if 10.0 <= t < 15.0]
    assert [t for t in arrivals if t < 10.0] and [t for t in arrivals if t >= 15.0]


def test_geodetic_round_trip_and_units():
    lat, lon, alt = enu_to_geodetic(ORIGIN, 100.0, -50.0, 2.5)
    assert alt == 2500
    e, n, u = geodetic_to_enu(ORIGIN, lat, lon, alt)
    # 1e-7 deg quantisation: 1.1 cm north, 0.65 cm east at 54°
    assert (e, n, u) == pytest.approx((100.0, -50.0, 2.5), abs=0.012)
    # one degE7 of latitude is LOCATION_SCALING metres, of longitude that times cos(lat)
    assert geodetic_to_enu(ORIGIN, round(54.32e7) + 1000, round(10.15e7), 0)[1] == \
        pytest.approx(11.13188, abs=1e-4)


def decoder(**kw) -> ShipTelemetryDecoder:
    return ShipTelemetryDecoder(ShipDecodeParams(min_latency_s=0.0, **kw))


def gpi(ms: int, east=0.0, north=0.0, up=0.0, vn=0.0, ve=0.0, vd=0.0) -> GlobalPositionInt:
    lat, lon, alt = enu_to_geodetic(ORIGIN, east, north, up)
    return GlobalPositionInt(ms, lat, lon, alt, alt, round(vn * 100), round(ve * 100),
                             round(vd * 100), 0)


def test_decode_filters_the_system_and_converts_ned_to_enu():
    d = decoder()
    assert d.on_message(1.0, 1, gpi(1000)) is None            # the vehicle's autopilot
    assert d.rejected['other_system'] == 1

    class Heartbeat:
        def get_type(self):
            return 'HEARTBEAT'
    assert d.on_message(1.0, 17, Heartbeat()) is None
    assert d.rejected['other_message'] == 1
    s = d.on_message(1.0, 17, gpi(1000, east=3.0, north=4.0, up=2.0, vn=1.5, ve=-0.5, vd=0.2))
    assert s is not None and s.kind == 'position'
    assert s.position_m == pytest.approx((3.0, 4.0, 2.0), abs=0.012)
    assert s.velocity_mps == pytest.approx((-0.5, 1.5, -0.2))          # ENU = (E, N, −D)
    # ATTITUDE: FRD in NED; heading 0 = north = ENU yaw π/2; pitch up (nose up) is the same
    # rotation, sign flipped between FRD and FLU
    a = d.on_message(1.1, 17, Attitude(1100, 0.1, 0.05, 0.0, 0.01, 0.02, 0.03))
    assert a is not None and a.kind == 'attitude'
    assert a.rpy_rad == pytest.approx((0.1, -0.05, math.pi / 2))
    assert a.rates_flu_radps == pytest.approx((0.01, -0.02, -0.03))
    # ψ̇_ENU = (q sin φ + r cos φ)/cos θ with FLU rates; NED heading rate is its negative
    assert a.yaw_rate_radps == pytest.approx(
        (-0.02 * math.sin(0.1) - 0.03 * math.cos(0.1)) / math.cos(-0.05))


def test_decode_rejects_out_of_order_repeats_stale_and_garbage():
    d = decoder(max_age_s=1.0)
    assert d.on_message(10.0, 17, gpi(5000)) is not None      # offset = 10 − 5 = 5 s
    assert d.on_message(10.2, 17, gpi(5200)) is not None
    assert d.on_message(10.3, 17, gpi(5100)) is None           # older than the last
    assert d.on_message(10.3, 17, gpi(5200)) is None           # repeated
    assert d.rejected['out_of_order'] == 2
    # arrives 1.5 s after it was measured (in the receiver's clock): stale
    assert d.on_message(11.8, 17, gpi(5300)) is None
    assert d.rejected['stale'] == 1
    assert d.on_message(12.0, 17, Attitude(7000, math.nan, 0.0, 0.0, 0.0, 0.0, 0.0)) is None
    assert d.rejected['non_finite'] == 1
    fast = gpi(5400, vn=40.0)                                  # 40 m/s: no deck sails that
    assert d.on_message(10.5, 17, fast) is None and d.rejected['implausible'] == 1


def test_clock_offset_is_the_fastest_arrival_and_time_boot_ms_wraps():
    d = decoder()
    # ship clock 2^32 − 300 ms at our t = 0; delays 0.3, 0.1, 0.2 s
    base = (1 << 32) - 300
    s1 = d.on_message(0.3, 17, gpi(base))
    s2 = d.on_message(0.2 + 0.1, 17, gpi((base + 200) % (1 << 32)))   # wrapped past 2^32
    s3 = d.on_message(0.4 + 0.2, 17, gpi((base + 400) % (1 << 32)))
    assert s1 is not None and s2 is not None and s3 is not None
    # after the 0.1 s message the offset carries that delay: stamps 0.1 s late at most
    # (the 100 ppm drift allowance lets the offset creep up by 1e-4 s/s between messages)
    assert s3.t_s == pytest.approx(0.4 + 0.1, abs=1e-4)
    assert s2.t_s == pytest.approx(0.2 + 0.1, abs=1e-4)
    assert s2.t_s > s1.t_s - 1.0    # no wrap-around jump back by 49.7 days


def test_a_pymavlink_round_trip_decodes_like_the_values():
    from pymavlink.dialects.v20 import common as mavlink2

    class Sink:
        def __init__(self):
            self.buf = b''

        def write(self, data):
            self.buf += data

    sink = Sink()
    tx = mavlink2.MAVLink(sink, srcSystem=17, srcComponent=1)
    m = gpi(1234, east=-7.0, north=12.0, up=2.0, vn=2.0, ve=0.5, vd=-0.1)
    tx.global_position_int_send(m.time_boot_ms, m.lat, m.lon, m.alt, m.relative_alt, m.vx, m.vy,
                                m.vz, m.hdg)
    tx.attitude_send(1300, 0.02, -0.01, 1.0, 0.0, 0.0, 0.05)
    rx = mavlink2.MAVLink(None)
    msgs = rx.parse_buffer(sink.buf)
    assert [x.get_type() for x in msgs] == ['GLOBAL_POSITION_INT', 'ATTITUDE']
    d1, d2 = decoder(), decoder()
    a = d1.on_message(5.0, msgs[0].get_srcSystem(), msgs[0])
    b = d2.on_message(5.0, 17, m)
    assert a == b and a is not None
    att = d1.on_message(5.1, msgs[1].get_srcSystem(), msgs[1])
    assert att is not None and att.rpy_rad[2] == pytest.approx(math.pi / 2 - 1.0, abs=1e-6)


def test_the_assembler_carries_position_and_attitude_to_the_newest_stamp():
    asm = DeckOdomAssembler(attitude_max_age_s=0.5)
    d = decoder()
    assert asm.on_sample(d.on_message(1.0, 17, Attitude(1000, 0.0, 0.0, 0.0, 0, 0, 0))) is None
    o = asm.on_sample(d.on_message(1.2, 17, gpi(1200, east=1.0, ve=2.0)))
    assert o is not None and o.attitude_valid
    assert o.t_s == pytest.approx(1.0 + 0.2)
    o2 = asm.on_sample(d.on_message(1.3, 17, Attitude(1300, 0.0, 0.0, 0.0, 0.0, 0.0, -0.1)))
    assert o2 is not None and o2.t_s == pytest.approx(1.3)
    assert o2.position_m[0] == pytest.approx(1.0 + 2.0 * 0.1, abs=0.012)   # carried forward
    assert o2.yaw_rate_radps == pytest.approx(0.1)                        # FRD r = −0.1
    o3 = asm.on_sample(d.on_message(2.0, 17, gpi(2000, east=3.0)))
    assert o3 is not None and not o3.attitude_valid                     # attitude 0.7 s old


def test_link_and_decode_together_recover_the_deck_within_the_gnss_error():
    """The whole chain on the sailing pad: decoded positions within bias + noise, velocities
    within the velocity noise, attitude within its noise, stamps within the jitter."""
    p = ShipTelemetryParams(loss_probability=0.05, clock_drift_ppm=50.0)
    link = ShipLink(p, sailing_pad, '3:ship_link')
    d = ShipTelemetryDecoder(ShipDecodeParams(min_latency_s=p.latency_s))
    pos_err, vel_err, yaw_err, stamp_err = [], [], [], []
    t = 0.0
    while t < 300.0:
        t += 0.01
        for t_rx, m in link.poll(t):
            s = d.on_message(t_rx, p.sysid, m)
            if s is None:
                continue
            t_true = (m.time_boot_ms * 1e-3 - p.clock_offset_s) / (1.0 + p.clock_drift_ppm * 1e-6)
            if t > 10.0:   # after the first fast arrivals have set the offset
                stamp_err.append(s.t_s - t_true)
            truth = sailing_pad(t_true)
            if s.kind == 'position':
                bx, by, _ = link.position_bias_m
                pos_err.append(math.hypot(s.position_m[0] - truth.position_m[0] - bx,
                                          s.position_m[1] - truth.position_m[1] - by))
                vel_err.append(math.hypot(s.velocity_mps[0] - 2.0, s.velocity_mps[1] - 1.0))
            else:
                yaw_err.append(abs(math.remainder(s.rpy_rad[2] - truth.rpy_rad[2], 2 * math.pi)))
    assert d.rejected['out_of_order'] > 0          # the jitter reorders some messages
    assert max(pos_err) < 0.05 * 5 + 0.05          # noise (the bias moves ~cm over a fix)
    assert statistics.fmean(vel_err) < 0.03 * 2
    assert max(yaw_err) < 0.0035 * 4 + 0.0017 * 5  # heading bias (4σ) + noise
    # stamps: the fastest arrivals define the offset: late by the fastest jitter at most
    assert max(abs(e) for e in stamp_err) < 0.01
    assert yaw_rate_from_body_rates(0.0, 0.0, 0.0, 0.02) == pytest.approx(0.02)


def test_the_simulation_loop_sends_the_ship_stream_the_runner_decodes():
    """The graph's path: SimulationLoop (ship_ss3) sends the ship's MAVLink datagrams; decoded
    with the bridge's decoder they give the pad's position within the GNSS error."""
    from deck_simulator.loop import SimulationLoop
    from deck_simulator.px4_emulator import EmulatorParams, Px4Emulator
    from deck_simulator.scenario import load_scenario
    from deck_simulator.transport import MemoryLink
    from pymavlink.dialects.v20 import common as mavlink2

    sc = load_scenario('ship_ss3')
    assert sc.ship_telemetry is not None
    datagrams: list[bytes] = []
    emu = Px4Emulator(EmulatorParams(), transport=MemoryLink().a)
    sim = SimulationLoop(sc, 5, emu, lambda _b: None, ship_send=datagrams.append)
    rx = mavlink2.MAVLink(None)
    dec = ShipTelemetryDecoder(ShipDecodeParams(min_latency_s=sc.ship_telemetry.latency_s))
    errs = []
    for _ in range(300):                  # 6 s
        sim.advance(0.02)
        pad = sim.world.pad_state().position_m
        for d in datagrams:
            for m in rx.parse_buffer(d) or []:
                s = dec.on_message(sim.world.t_s, m.get_srcSystem(), m)
                if s is not None and s.kind == 'position':
                    errs.append(math.hypot(s.position_m[0] - pad[0], s.position_m[1] - pad[1]))
        datagrams.clear()
    ship = sim.world.ship_link
    assert ship is not None
    assert sim.counters['ship_messages'] == ship.sent - ship.lost - ship.in_flight
    assert sim.counters['ship_messages'] > 6 * 15 * 0.85
    bias = math.hypot(*ship.position_bias_m[:2])
    # bias + noise + the 2.5 m/s ship moving while the fix travels (≤ ~0.4 s old here)
    assert errs and max(errs) < bias + 0.3 + 2.6 * 0.45
    sim2 = SimulationLoop(load_scenario('paper'), 5, Px4Emulator(
        EmulatorParams(), transport=MemoryLink().a), lambda _b: None, ship_send=datagrams.append)
    sim2.advance(1.0)
    assert not datagrams and sim2.counters['ship_messages'] == 0   # a barge sends nothing
