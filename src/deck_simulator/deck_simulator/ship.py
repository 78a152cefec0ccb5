"""Ship deck motion: a small vessel underway in a directional sea (pure, seeded).

The sea is a sum of random-phase wave components (JONSWAP / Pierson–Moskowitz frequencies,
cos^2s-spread directions); each of the six ship motions is their sum through a response function
of wave number, relative heading and encounter frequency (:func:`response_functions`). The ship
follows a straight or constant-rate turning track and the pad rides on the rigid hull at a lever
arm from the centre of motion. :class:`ShipMotion` (a ``deck_motion.DeckMotion``) tabulates the
pad state with numpy, lazily in chunks, and interpolates it per call in plain floats.
Parameters: ``ship_params``. Model, equations, sources and YAML schema: ``docs/world/ship.md``.
"""

from __future__ import annotations

import math
import random
from typing import Any

from deckland_common.frames import rot_body_to_world, wrap_pi
from deckland_common.validate import require
import numpy as np

from deck_simulator.deck import jonswap, pierson_moskowitz
from deck_simulator.deck_motion import PadState
from deck_simulator.ship_params import ShipParams

G_MPS2 = 9.81                      # as deck_simulator.vehicle
TWO_PI = 2.0 * math.pi
#: Order of the six motions in every (6, ...) array: surge, sway, heave [m]; roll, pitch,
#: wave yaw [rad]. Surge/sway are along/across the mean heading; roll/pitch/yaw are the Z-Y-X
#: Euler angles of the hull (yaw about the mean heading).
DOF = ('surge', 'sway', 'heave', 'roll', 'pitch', 'yaw')
_ROW = 21                          # floats per table node (layout in ShipMotion)
_CHUNK_NODES = 200                 # nodes tabulated per numpy call (20 s at 0.1 s)
_DBETA = 1e-3                      # rad, central difference of the response in heading
_GOLDEN = 0.5 * (math.sqrt(5.0) - 1.0)
_TURN_STEP_RAD = 0.02              # rad of turn between coefficient evaluations (table)


# --- response functions (numpy) ---------------------------------------------------------------

def _sinc(u: np.ndarray) -> np.ndarray:
    """sin(u)/u: the mean of e^{-i 2u s} over s in [-1/2, 1/2] (hull averaging)."""
    return np.sinc(u / math.pi)


def _slope(u: np.ndarray) -> np.ndarray:
    """3 (sin u − u cos u)/u³: the least-squares slope of e^{-i 2u s} per unit −i 2u (→ 1)."""
    u = np.asarray(u, dtype=float)
    small = np.abs(u) < 1e-3
    us = np.where(small, 1.0, u)
    exact = 3.0 * (np.sin(us) - us * np.cos(us)) / us ** 3
    return np.where(small, 1.0 - u * u / 10.0, exact)


def encounter_frequency(omega: Any, beta: Any, speed_mps: float) -> np.ndarray:
    """ω_e = ω − ω² U cos β / g (deep water; signed: negative when the waves overtake)."""
    w = np.asarray(omega, dtype=float)
    return w - w * w * speed_mps * np.cos(beta) / G_MPS2


def second_order(omega_e: Any, period_s: float, damping: float) -> np.ndarray:
    """1 / (1 − r² + 2iζr), r = ω_e/ω_n: unit static gain; H(−ω) = conj H(ω)."""
    r = np.asarray(omega_e, dtype=float) * (period_s / TWO_PI)
    return 1.0 / (1.0 - r * r + 2j * damping * r)


def response_functions(p: ShipParams, omega: Any, beta: Any) -> np.ndarray:
    """Complex response per unit wave amplitude, shape (6, *broadcast(omega, beta)).

    Motion j of one wave component ``η = a cos χ`` at the centre of motion is
    ``Re(a H_j e^{iχ})``: heave [m/m], roll and pitch [rad/m] are the hull-averaged
    excitation (elevation, transverse and longitudinal slope; Smith factor e^{-kd}) through a
    damped second-order system at ω_e; surge, sway [m/m] and yaw [rad/m] are the hull's rigid
    fit to the orbital displacement of the water (averaged over the draft).
    """
    w = np.asarray(omega, dtype=float)
    b = np.asarray(beta, dtype=float)
    w, b = np.broadcast_arrays(w, b)
    k = w * w / G_MPS2
    cb, sb = np.cos(b), np.sin(b)
    kx, ky = k * cb, k * sb                   # wave vector in the hull frame (x fwd, y port)
    length, beam, draft = p.length_m, p.beam_m, p.draft_m
    ul, ub = 0.5 * kx * length, 0.5 * ky * beam
    ml, mb = _sinc(ul), _sinc(ub)
    sl, sbm = _slope(ul), _slope(ub)
    smith = np.exp(-k * draft)
    kd = k * draft
    orbit = np.where(kd < 1e-6, 1.0 - 0.5 * kd, -np.expm1(-kd) / np.where(kd < 1e-6, 1.0, kd))
    we = encounter_frequency(w, b, p.speed_mps)
    h = np.empty((6, *w.shape), dtype=complex)
    h[0] = -1j * cb * ml * mb * orbit
    h[1] = -1j * sb * ml * mb * orbit
    h[2] = ml * mb * smith * second_order(we, p.heave_period_s, p.heave_damping)
    h[3] = -1j * ky * ml * sbm * smith * second_order(we, p.roll_period_s, p.roll_damping)
    h[4] = 1j * kx * sl * mb * smith * second_order(we, p.pitch_period_s, p.pitch_damping)
    l2, b2 = length * length, beam * beam
    kk = np.where(k > 0.0, k, 1.0)
    h[5] = -(kx * ky / kk) * (sl * mb * l2 - sbm * ml * b2) / (l2 + b2) * orbit
    return h


def spreading_density(p: ShipParams, delta_rad: Any) -> np.ndarray:
    """D(δ) = Γ(s+1) / (√π Γ(s+½)) cos^2s δ for |δ| ≤ π/2 (∫ D dδ = 1); δ = θ − θ0."""
    d = np.asarray(delta_rad, dtype=float)
    s = 1.0 if p.spreading_s is None else float(p.spreading_s)
    c = math.exp(math.lgamma(s + 1.0) - math.lgamma(s + 0.5)) / math.sqrt(math.pi)
    return np.where(np.abs(d) <= 0.5 * math.pi, c * np.cos(d).clip(0.0) ** (2.0 * s), 0.0)


def wave_spectrum(p: ShipParams, omega: Any) -> np.ndarray:
    """S(ω) [m² s/rad] of the sea (deck_simulator.deck's spectra)."""
    w = np.asarray(omega, dtype=float)
    if p.spectrum == 'jonswap':
        return jonswap(w, p.significant_height_m, p.peak_period_s, p.jonswap_gamma)
    return pierson_moskowitz(w, p.significant_height_m, p.peak_period_s)


def motion_variances(p: ShipParams, n_omega: int = 2000, n_delta: int = 181) -> np.ndarray:
    """Expected variance of each motion, ∫∫ |H_j(ω, β0 + δ)|² S(ω) D(δ) dδ dω, straight.

    Over the frequency band the components cover, [0.4, 4] ω_p, normalised like them so that
    the elevation variance is exactly m0 = (Hs/4)² (trapezoid rule on a fine grid).
    """
    wp = TWO_PI / p.peak_period_s
    w = np.linspace(0.4 * wp, 4.0 * wp, n_omega)
    s = wave_spectrum(p, w)
    m0 = (p.significant_height_m / 4.0) ** 2
    band = float(np.trapezoid(s, w))
    s = s * (m0 / band) if band > 0.0 else s
    if p.spreading_s is None:
        h2 = np.abs(response_functions(p, w, p.wave_heading_rad)) ** 2       # (6, n_omega)
    else:
        d = np.linspace(-0.5 * math.pi, 0.5 * math.pi, n_delta)
        dens = spreading_density(p, d)
        dens = dens / float(np.trapezoid(dens, d))
        h = np.abs(response_functions(p, w[:, None], p.wave_heading_rad + d[None, :])) ** 2
        h2 = np.trapezoid(h * dens, d, axis=2)
    return np.trapezoid(h2 * s, w, axis=1)


# --- the ship ----------------------------------------------------------------------------------

class ShipMotion:
    """The ship's pad state over a run, seeded (``rng``) and tabulated up to ``duration_s``.

    Table node k (t = k·table_dt_s) holds 21 floats: pad position, velocity, acceleration,
    roll/pitch/yaw (yaw unwrapped), their rates, angular velocity, angular acceleration.
    :meth:`pad_state` interpolates position, velocity, angles and angular velocity by cubic
    Hermite (the next quantity is the derivative) and takes the accelerations as the
    derivatives of the velocity interpolants; nodes are computed in chunks of
    ``_CHUNK_NODES`` the first time a call needs them. Outside [0, duration_s] it evaluates
    the exact sum (:meth:`exact_pad_state`, numpy, slow).
    """

    __slots__ = ('_amp', '_c0', '_coef_ri', '_dt', '_inv_dt', '_kcos', '_ksin',
                 '_n_nodes', '_n_ready', '_omega', '_phase', '_tab', '_theta', '_we0',
                 'duration_s', 'params')

    def __init__(self, params: ShipParams, rng: random.Random, duration_s: float) -> None:
        p = params
        require(math.isfinite(duration_s) and duration_s >= 0.0, 'duration_s',
                'must be a finite number >= 0', duration_s)
        self.params = p
        self.duration_s = float(duration_s)
        n = p.components
        # frequencies: one per equal bin over [0.4, 4] ω_p, uniform inside its bin
        wp = TWO_PI / p.peak_period_s
        edges = np.linspace(0.4 * wp, 4.0 * wp, n + 1)
        u = np.array([rng.random() for _ in range(n)])
        omega = edges[:-1] + u * np.diff(edges)
        amp = np.sqrt(2.0 * wave_spectrum(p, omega) * np.diff(edges))
        m0 = (p.significant_height_m / 4.0) ** 2
        total = float(np.sum(amp ** 2) / 2.0)
        if total > 0.0:
            amp = amp * math.sqrt(m0 / total)       # Σ a²/2 = m0 exactly (Hs exact)
        # directions: stratified quantiles of D(δ); bin i takes stratum rank(frac(u0 + i/φ)), a
        # golden-ratio (Kronecker) order, so neighbouring frequencies get distant directions
        u0 = rng.random()
        stratum = np.argsort(np.argsort((u0 + np.arange(n) * _GOLDEN) % 1.0))
        q = (stratum + np.array([rng.random() for _ in range(n)])) / n
        if p.spreading_s is None:
            delta = np.zeros(n)
        else:
            grid = np.linspace(-0.5 * math.pi, 0.5 * math.pi, 4001)
            dens = spreading_density(p, grid)
            cdf = np.concatenate(([0.0], np.cumsum(0.5 * (dens[1:] + dens[:-1])
                                                   * np.diff(grid))))
            delta = np.interp(q, cdf / cdf[-1], grid)
        phase = np.array([rng.uniform(0.0, TWO_PI) for _ in range(n)])
        theta = p.heading_rad + p.wave_heading_rad + delta     # world travel direction
        k = omega * omega / G_MPS2
        self._omega = omega
        self._kcos = k * np.cos(theta)
        self._ksin = k * np.sin(theta)
        self._amp = amp
        self._phase = phase
        self._theta = theta
        beta0 = theta - p.heading_rad
        self._we0 = encounter_frequency(omega, beta0, p.speed_mps)
        self._c0 = amp * response_functions(p, omega, beta0)        # (6, n) at t = 0
        iwe = 1j * self._we0
        coef = np.concatenate((self._c0, self._c0 * iwe, self._c0 * iwe * iwe))   # (18, n)
        self._coef_ri = np.concatenate((coef.real, coef.imag), axis=1)           # (18, 2n)
        self._dt = p.table_dt_s
        self._inv_dt = 1.0 / p.table_dt_s
        self._n_nodes = math.ceil(self.duration_s / p.table_dt_s) + 1 if duration_s > 0 else 0
        self._n_ready = 0
        self._tab: list[float] = []

    # -- exact evaluation (numpy, vectorised over times) --

    def track(self, t_s: Any) -> tuple[np.ndarray, ...]:
        """Mean track of the centre of motion: x, y, ẋ, ẏ, ẍ, ÿ and heading ψ_t = ψ0 + r t."""
        p = self.params
        t = np.asarray(t_s, dtype=float)
        r, speed, psi0 = p.turn_rate_radps, p.speed_mps, p.heading_rad
        psi = psi0 + r * t
        half = 0.5 * r * t
        chord = speed * t * np.sinc(half / math.pi)       # |p(t) − p(0)| on the arc, stable r→0
        c, s = math.cos(psi0), math.sin(psi0)
        ox = p.pad_position_m[0] - (c * p.pad_offset_m[0] - s * p.pad_offset_m[1])
        oy = p.pad_position_m[1] - (s * p.pad_offset_m[0] + c * p.pad_offset_m[1])
        cp, sp = np.cos(psi), np.sin(psi)
        return (ox + chord * np.cos(psi0 + half), oy + chord * np.sin(psi0 + half),
                speed * cp, speed * sp, -speed * r * sp, speed * r * cp, psi)

    def _phases(self, x: np.ndarray, y: np.ndarray, t: np.ndarray) -> np.ndarray:
        """χ_i = ω_i t − k_i·p(t) + φ_i, shape (times, components)."""
        return (np.outer(t, self._omega) - np.outer(x, self._kcos) - np.outer(y, self._ksin)
                + self._phase)

    def _coefficients(self, beta: np.ndarray) -> np.ndarray:
        """a_i H_j(ω_i, β_i): (6, ..., components) for relative headings (..., components)."""
        return self._amp * response_functions(self.params, self._omega, beta)

    def _turning_coefficients(self, t: np.ndarray, dt: float) -> np.ndarray:
        """Coefficients of x, ẋ, ẍ at times t (uniform, step dt), turning: (n, 18, 2·comp).

        x = Re Σ c e^{iχ}, ẋ = Re Σ (ċ + iω_e c) e^{iχ},
        ẍ = Re Σ (c̈ + 2iω_e ċ + (iχ̈ − ω_e²) c) e^{iχ}; c depends on time through the heading
        only, ċ and c̈ are central differences over t (one extra time each side).
        """
        tt = np.concatenate(([t[0] - dt], t, [t[-1] + dt]))
        _, _, vx, vy, ax, ay, psi = self.track(tt)
        c = self._coefficients(self._theta - psi[:, None])          # (6, n + 2, comp)
        cd = (c[:, 2:] - c[:, :-2]) / (2.0 * dt)
        cdd = (c[:, 2:] - 2.0 * c[:, 1:-1] + c[:, :-2]) / (dt * dt)
        c = c[:, 1:-1]
        iwe = 1j * (self._omega - np.outer(vx[1:-1], self._kcos)
                    - np.outer(vy[1:-1], self._ksin))
        ichidd = -1j * (np.outer(ax[1:-1], self._kcos) + np.outer(ay[1:-1], self._ksin))
        coef = np.concatenate((c, cd + iwe * c, cdd + 2.0 * iwe * cd + (ichidd + iwe * iwe) * c))
        coef = coef.transpose(1, 0, 2)                               # (n, 18, comp)
        return np.ascontiguousarray(np.concatenate((coef.real, coef.imag), axis=2))

    def motions(self, t_s: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The six motions (:data:`DOF`) and their first and second derivatives, (6, n).

        The exact sum, the reference of the table. Component i has phase
        χ_i = ω_i t − k_i·p(t) + φ_i at the mean track point p(t), so χ̇_i = ω_e,i. Turning,
        the response follows the slowly changing heading quasi-steadily,
        x = Re Σ c_i(β_i(t)) e^{iχ_i}, differentiated exactly (ċ, c̈ by differences in β).
        """
        p = self.params
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        x, y = self.track(t)[:2]
        chi = self._phases(x, y, t)
        e = np.concatenate((np.cos(chi), -np.sin(chi)), axis=1)    # Re(c e^{iχ}) = [cr ci]·e
        if p.turn_rate_radps == 0.0:
            out = np.einsum('ji,ki->jk', self._coef_ri, e)
        else:
            # the β-difference step, taken in time: Δt = _DBETA / |r|, evaluated at each t
            step = _DBETA / abs(p.turn_rate_radps)
            coef = np.stack([self._turning_coefficients(np.array([tk]), step)[0] for tk in t])
            out = np.einsum('kji,ki->jk', coef, e)
        return out[0:6], out[6:12], out[12:18]

    def _chunk_motions(self, k0: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The motions at nodes k0 .. k0+n−1, fast; :meth:`motions` is the reference.

        Phases exact. Straight: constant coefficients, one product. Turning: the coefficients
        (functions of the heading only) are evaluated every ``_TURN_STEP_RAD`` of turn and
        interpolated linearly in time between, as one product per interval end.
        """
        p = self.params
        h = self._dt
        t = (k0 + np.arange(n)) * h
        x, y = self.track(t)[:2]
        chi = self._phases(x, y, t)
        e = np.concatenate((np.cos(chi), -np.sin(chi)), axis=1)    # (n, 2 comp)
        if p.turn_rate_radps == 0.0:
            out = np.einsum('ji,ki->jk', self._coef_ri, e)
            return out[0:6], out[6:12], out[12:18]
        m = max(1, min(n, int(_TURN_STEP_RAD / (abs(p.turn_rate_radps) * h))))  # per interval
        n_iv = -(-n // m)                                          # intervals, last one padded
        span = m * h
        coef = self._turning_coefficients(t[0] + np.arange(n_iv + 1) * span, span)
        eb = np.zeros((n_iv * m, e.shape[1]))
        eb[:n] = e
        eb = np.ascontiguousarray(eb.reshape(n_iv, m, -1).transpose(1, 0, 2))   # (m, n_iv, ·)
        left = np.einsum('vji,kvi->jvk', coef[:-1], eb).reshape(18, n_iv * m)
        right = np.einsum('vji,kvi->jvk', coef[1:], eb).reshape(18, n_iv * m)
        u = np.tile(np.arange(m) / m, n_iv)
        out = (left + u * (right - left))[:, :n]
        return out[0:6], out[6:12], out[12:18]

    def _rows(self, t: np.ndarray, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
        """Table rows (n, 21): the pad kinematics from the track and the six motions."""
        p = self.params
        x, y, vx, vy, ax, ay, psi_t = self.track(t)
        r = p.turn_rate_radps
        ct, st = np.cos(psi_t), np.sin(psi_t)
        # centre of motion: track + surge/sway in the mean-heading frame + heave
        s1, s2 = q[0], q[1]
        s1dd = qdd[0] - 2.0 * r * qd[1] - r * r * q[0]     # ξ̈ + 2r J ξ̇ − r² ξ
        s2dd = qdd[1] + 2.0 * r * qd[0] - r * r * q[1]
        v1, v2 = qd[0] - r * s2, qd[1] + r * s1           # ξ̇ + r J ξ
        o = (x + ct * s1 - st * s2, y + st * s1 + ct * s2, p.motion_centre_height_m + q[2])
        od = (vx + ct * v1 - st * v2, vy + st * v1 + ct * v2, qd[2])
        odd = (ax + ct * s1dd - st * s2dd, ay + st * s1dd + ct * s2dd, qdd[2])
        # attitude (Z-Y-X): roll, pitch, yaw = heading + wave yaw
        ph, th, ps = q[3], q[4], psi_t + q[5]
        phd, thd, psd = qd[3], qd[4], r + qd[5]
        phdd, thdd, psdd = qdd[3], qdd[4], qdd[5]
        cf, sf = np.cos(ph), np.sin(ph)
        ce, se = np.cos(th), np.sin(th)
        cy, sy = np.cos(ps), np.sin(ps)
        lx, ly, lz = p.pad_offset_m
        rl = (cy * ce * lx + (cy * se * sf - sy * cf) * ly + (cy * se * cf + sy * sf) * lz,
              sy * ce * lx + (sy * se * sf + cy * cf) * ly + (sy * se * cf - cy * sf) * lz,
              -se * lx + ce * sf * ly + ce * cf * lz)
        # ω = ψ̇ e_z + θ̇ Rz e_y + φ̇ Rz Ry e_x, and its derivative α
        w = (-thd * sy + phd * cy * ce, thd * cy + phd * sy * ce, psd - phd * se)
        al = (-thdd * sy - thd * psd * cy + phdd * cy * ce
              + phd * (-psd * sy * ce - thd * cy * se),
              thdd * cy - thd * psd * sy + phdd * sy * ce
              + phd * (psd * cy * ce - thd * sy * se),
              psdd - phdd * se - phd * thd * ce)
        wr = _cross3(w, rl)
        ar = _cross3(al, rl)
        wwr = _cross3(w, wr)
        cols = (o[0] + rl[0], o[1] + rl[1], o[2] + rl[2],
                od[0] + wr[0], od[1] + wr[1], od[2] + wr[2],
                odd[0] + ar[0] + wwr[0], odd[1] + ar[1] + wwr[1], odd[2] + ar[2] + wwr[2],
                ph, th, ps, phd, thd, psd, w[0], w[1], w[2], al[0], al[1], al[2])
        return np.stack([np.broadcast_to(c, t.shape) for c in cols], axis=1)

    def exact_rows(self, t_s: Any) -> np.ndarray:
        """Table rows (n, 21) at arbitrary times from the exact sum (:meth:`motions`)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        q, qd, qdd = self.motions(t)
        return self._rows(t, q, qd, qdd)

    def exact_pad_state(self, t_s: float) -> PadState:
        """The pad state from the exact sum (no table); raises ValueError for a bad time."""
        require(math.isfinite(t_s), 't_s', 'must be a finite number', t_s)
        row = [float(v) for v in self.exact_rows(np.array([t_s]))[0]]
        return _state_from(row[0], row[1], row[2], row[3], row[4], row[5], row[6], row[7],
                           row[8], row[9], row[10], row[11], row[15], row[16], row[17],
                           row[18], row[19], row[20])

    # -- table and hot path --

    def _fill_to(self, n_needed: int) -> None:
        """Tabulate the chunks up to node n_needed − 1; chunk k is always nodes [kC, (k+1)C)
        (whatever the order of the calls, the table is the same)."""
        while self._n_ready < n_needed:
            start = self._n_ready
            stop = min(self._n_nodes, start + _CHUNK_NODES)
            t = (start + np.arange(stop - start)) * self._dt
            q, qd, qdd = self._chunk_motions(start, stop - start)
            self._tab.extend(self._rows(t, q, qd, qdd).ravel().tolist())
            self._n_ready = stop

    def pad_state(self, t_s: float) -> PadState:
        """The pad state at ``t_s`` (interpolated; see the class docstring)."""
        f = t_s * self._inv_dt
        if not (f >= 0.0 and f < self._n_nodes - 1):
            return self.exact_pad_state(t_s)
        i = int(f)
        if i + 2 > self._n_ready:
            self._fill_to(i + 2)
        s = f - i
        s2 = s * s
        s3 = s2 * s
        dt = self._dt
        inv = self._inv_dt
        h00 = 2.0 * s3 - 3.0 * s2 + 1.0
        h01 = 1.0 - h00
        h10 = (s3 - 2.0 * s2 + s) * dt
        h11 = (s3 - s2) * dt
        d00 = (6.0 * s2 - 6.0 * s) * inv          # d/dt of the weights
        d01 = -d00
        d10 = 3.0 * s2 - 4.0 * s + 1.0
        d11 = 3.0 * s2 - 2.0 * s
        tb = self._tab
        a = i * _ROW
        b = a + _ROW
        # value at offset j, its derivative at offset j + 3
        p0, p1, p2 = tb[a], tb[a + 1], tb[a + 2]
        v0, v1, v2 = tb[a + 3], tb[a + 4], tb[a + 5]
        a0, a1, a2 = tb[a + 6], tb[a + 7], tb[a + 8]
        q0, q1, q2 = tb[b], tb[b + 1], tb[b + 2]
        u0, u1, u2 = tb[b + 3], tb[b + 4], tb[b + 5]
        c0, c1, c2 = tb[b + 6], tb[b + 7], tb[b + 8]
        w0, w1, w2 = tb[a + 15], tb[a + 16], tb[a + 17]
        e0, e1, e2 = tb[a + 18], tb[a + 19], tb[a + 20]
        x0, x1, x2 = tb[b + 15], tb[b + 16], tb[b + 17]
        f0, f1, f2 = tb[b + 18], tb[b + 19], tb[b + 20]
        return _state_from(
            h00 * p0 + h10 * v0 + h01 * q0 + h11 * u0,
            h00 * p1 + h10 * v1 + h01 * q1 + h11 * u1,
            h00 * p2 + h10 * v2 + h01 * q2 + h11 * u2,
            h00 * v0 + h10 * a0 + h01 * u0 + h11 * c0,
            h00 * v1 + h10 * a1 + h01 * u1 + h11 * c1,
            h00 * v2 + h10 * a2 + h01 * u2 + h11 * c2,
            d00 * v0 + d10 * a0 + d01 * u0 + d11 * c0,
            d00 * v1 + d10 * a1 + d01 * u1 + d11 * c1,
            d00 * v2 + d10 * a2 + d01 * u2 + d11 * c2,
            h00 * tb[a + 9] + h10 * tb[a + 12] + h01 * tb[b + 9] + h11 * tb[b + 12],
            h00 * tb[a + 10] + h10 * tb[a + 13] + h01 * tb[b + 10] + h11 * tb[b + 13],
            h00 * tb[a + 11] + h10 * tb[a + 14] + h01 * tb[b + 11] + h11 * tb[b + 14],
            h00 * w0 + h10 * e0 + h01 * x0 + h11 * f0,
            h00 * w1 + h10 * e1 + h01 * x1 + h11 * f1,
            h00 * w2 + h10 * e2 + h01 * x2 + h11 * f2,
            d00 * w0 + d10 * e0 + d01 * x0 + d11 * f0,
            d00 * w1 + d10 * e1 + d01 * x1 + d11 * f1,
            d00 * w2 + d10 * e2 + d01 * x2 + d11 * f2)

    # -- this realisation --

    def component_variances(self) -> np.ndarray:
        """Σ_i |c_ij|²/2 per motion at t = 0: the variance this realisation has (straight)."""
        return np.sum(np.abs(self._c0) ** 2, axis=1) / 2.0

    def wave_components(self) -> dict[str, np.ndarray]:
        """The drawn components: ω, world direction θ, amplitude a, phase φ, ω_e at t = 0."""
        return {'omega': self._omega.copy(), 'theta': self._theta.copy(),
                'amplitude': self._amp.copy(), 'phase': self._phase.copy(),
                'omega_e': self._we0.copy()}


def _cross3(a: tuple[Any, Any, Any], b: tuple[Any, Any, Any]) -> tuple[Any, Any, Any]:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _state_from(px: float, py: float, pz: float, vx: float, vy: float, vz: float, ax: float,
                ay: float, az: float, roll: float, pitch: float, yaw: float, wx: float,
                wy: float, wz: float, lx: float, ly: float, lz: float) -> PadState:
    return PadState((px, py, pz), (vx, vy, vz), (ax, ay, az), (roll, pitch, wrap_pi(yaw)),
                    (wx, wy, wz), (lx, ly, lz), rot_body_to_world(roll, pitch, yaw))
