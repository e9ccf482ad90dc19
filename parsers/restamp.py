"""The slave on the master's clock, written in its own format: the shared types of the native writers.

A native writer copies every record of a slave log and rewrites only its time fields with a
:class:`ClockShift`. Each format's writer lives beside its reader (it knows the format's time fields,
units and clocks); this module holds what they share.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class ClockShift:
    """``t_master = t_slave - latency(t)``, ``latency(t) = latency_s + drift_ppm 1e-6 (t - t_ref_ns)``.

    Instants are int64 nanoseconds on the slave's analysis clock (``meta.t0_ns + t_s 1e9`` of the slave's
    InsLog: UNIX or boot, whichever the parser put it on). ``t_ref_ns`` is where ``latency_s`` holds (the
    middle of the analysed window, on the slave's clock)."""

    latency_s: float
    drift_ppm: float
    t_ref_ns: int

    def shift_ns(self, t_ns: np.ndarray) -> np.ndarray:
        """The nanoseconds to subtract from each slave instant (int64, rounded to the nearest ns)."""
        t = np.asarray(t_ns, dtype=np.int64)
        dt_s = (t - np.int64(self.t_ref_ns)).astype(np.float64) * 1e-9
        return np.rint((self.latency_s + self.drift_ppm * 1e-6 * dt_s) * 1e9).astype(np.int64)

    def to_master_ns(self, t_ns: np.ndarray) -> np.ndarray:
        t = np.asarray(t_ns, dtype=np.int64)
        return t - self.shift_ns(t)


@dataclass(frozen=True)
class RestampStats:
    """What a native writer did: for the report's ``outputs`` entry and the summary."""

    path: str
    format: str
    how: str  # e.g. "byte-level rewrite of the time fields" or "rewritten through pymavlink"
    records: int  # records written (== records read that were intact)
    records_by_type: dict[str, int] = field(default_factory=dict)
    time_fields: tuple[str, ...] = ()  # which fields were rewritten
    damage: tuple[str, ...] = ()  # what could not be read and is therefore not in the output
