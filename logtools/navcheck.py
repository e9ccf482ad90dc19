"""Validity of a unit's navigation output (attitude, velocity): what an INS or EKF logs while it is not
running or when it resets. Shared by the latency (rates derived from attitude) and the alignment (the
master's measurements).

* frozen: 3 or more bit-identical samples in a row (an EKF not yet initialised logs the identity, or holds
  its last output); no sensor-driven solution repeats itself exactly while it runs;
* jump (reset): an attitude increment between two samples that differs in size from what the angular
  rate allows (``rate_at_mid``, where the unit has a gyro) or from its neighbours' increments, by more than
  max(2 deg, 10 x the median difference); without a rate, also by more than an angular acceleration of 20
  deg/s^2 could change it over the step (slow outputs). With a rate, two jumps around one sample whose
  neighbours agree with the rate over the two steps are that one sample's corruption: it is invalid, and no
  reset.
"""
from __future__ import annotations

import numpy as np

from logtools.conventions import DEG, angle_between_quats, typical_step_s
from logtools.rows import by_rows

JUMP_MIN_DEG = 2.0
JUMP_MIN_RAD = JUMP_MIN_DEG * DEG
JUMP_MEDIAN_FACTOR = 10.0
#: without a rate, consecutive increments of a unit sampled every dt differ by up to about its angular
#: acceleration x dt^2 by motion alone: above 20 deg/s^2 x dt^2 a change is a jump, where that exceeds
#: JUMP_MIN_RAD (steps beyond 0.32 s: an aircraft's S-turns at 1 Hz were 6 resets in 60 s)
JUMP_ACCEL_RAD_S2 = 20.0 * DEG
#: a step of a unit's navigation stamps beyond this many of its typical steps is a gap (samples missing): the
#: output across it is no measurement and its increment no rate (AlignmentConfig.nav_gap_steps)
NAV_GAP_STEPS = 3.0


def nav_gaps(t: np.ndarray, steps: float = NAV_GAP_STEPS) -> np.ndarray:
    """(n-1,) True at the steps of sorted navigation stamps ``t`` longer than ``steps`` of their typical
    step (``conventions.typical_step_s``: the length-weighted median step, so that telemetry's bursts are
    no gaps)."""
    return np.diff(t) > steps * typical_step_s(t)


def output_validity(t: np.ndarray, quat: np.ndarray | None, vel: np.ndarray | None = None,
                    rate_at_mid: np.ndarray | None = None, gap: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """(valid mask over the samples, reset times). ``quat`` (n, 4) wxyz, ``vel`` (n, 3), either may be None;
    ``rate_at_mid`` (n-1,): |angular rate| (rad/s) at the intervals' middles, when known. ``gap`` (n-1,):
    the intervals over which samples are missing: the increment over one is not judged (it spans more time
    than its neighbours, and the rate at its middle says nothing of the motion over it: a 5 s gap read as
    two resets, a 15 s gap in a turning car as one); the caller may judge it by the unit's gyro."""
    n = len(t)
    valid = np.ones(n, bool)
    rows = [a for a in (quat, vel) if a is not None]
    if not rows or n < 2:
        return valid, np.zeros(0)
    same = np.all(np.concatenate([np.diff(a, axis=0) == 0 for a in rows], axis=1), axis=1)  # k+1 == k
    run3 = np.zeros(n, bool)
    if n >= 3:
        s2 = same[1:] & same[:-1]  # samples k, k+1, k+2 identical
        for off in range(3):
            run3[off:n - 2 + off] |= s2
    valid &= ~run3
    resets = np.zeros(0)
    if quat is not None and n > 3:
        dq = by_rows(angle_between_quats, quat[:-1], quat[1:])
        if rate_at_mid is not None:
            d = np.abs(dq - rate_at_mid * np.diff(t))
            if gap is not None:
                d[gap] = 0.0
            floor = JUMP_MIN_RAD
        else:
            d = np.abs(np.diff(np.concatenate([[0.0], dq])))  # jump in the increment size
            d = d[1:] if len(d) > len(dq) else d
            if gap is not None and gap.any():  # (an increment over a gap, and the next one back to normal)
                d[gap | np.concatenate([[False], gap[:-1]])] = 0.0
            floor = np.maximum(JUMP_MIN_RAD, JUMP_ACCEL_RAD_S2 * np.diff(t) ** 2)
        moving = valid[:-1] & valid[1:]
        med = float(np.median(d[moving])) if moving.any() else 0.0
        thr = np.maximum(floor, JUMP_MEDIAN_FACTOR * med)
        jump = moving & (d > thr)
        if rate_at_mid is not None and n > 2 and (jump[:-1] & jump[1:]).any():
            # a sample off both ways whose neighbours agree with the rate over the two steps: one corrupt
            # sample (a flipped bit of a quaternion), not two resets (which restarted the slave's attitude
            # twice: a simulated pair's mounting sigma 3.9' against 0.028')
            k = np.flatnonzero(jump[:-1] & jump[1:])
            a02 = by_rows(angle_between_quats, quat[k], quat[k + 2])
            turned = (rate_at_mid[k] * (t[k + 1] - t[k]) + rate_at_mid[k + 1] * (t[k + 2] - t[k + 1]))
            back = k[np.abs(a02 - turned) <= thr]  # (a scalar with a rate)
            valid[back + 1] = False
            jump[back] = jump[back + 1] = False
        elif rate_at_mid is None and n > 4 and (jump[:-2] & jump[2:]).any():
            # without a rate, the same sample shows as a change of the increments' size into it and out of it:
            # jumps on the intervals before and after it (two resets, the sample itself kept). Where its
            # neighbours' rotation over the two steps is what their own increments make it, it is that one
            # sample's corruption
            k = np.flatnonzero(jump[:-2] & jump[2:])
            k = k[(k >= 1) & (k + 3 <= n - 1)]  # (the neighbours' own increments, k-1 and k+2, exist)
            a02 = by_rows(angle_between_quats, quat[k], quat[k + 2])
            turned = dq[k - 1] + dq[k + 2]
            tol = np.maximum(thr[k], thr[k + 2])
            off = np.minimum(dq[k], dq[k + 1]) > a02 + tol  # (out and back)
            back = k[off & (np.abs(a02 - turned) <= tol)]
            valid[back + 1] = False
            jump[back] = jump[back + 1] = jump[back + 2] = False
        if jump.any():
            k = np.nonzero(jump)[0]
            resets = 0.5 * (t[k] + t[k + 1])
            valid[k] = False
    return valid, resets
