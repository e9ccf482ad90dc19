"""Result records passed from logtools to pipelines (report.json, HTML, rerun).

These are the internal contracts between the numerics and the outputs. Fields may be added (with
defaults); never renamed: report.json is built from them (DESIGN.md, "report.json contract").
"""
from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import numpy as np


class LatencyMethod(str, Enum):
    """The latency methods by name: one table (``LatencyResult.method``, report.json ``latency.methods``,
    the CLI's --latency-method). Here, beside the records, so that the CLI's choices need no numerics."""

    TAPOST = "tapost"
    S000 = "s000-rate-integral"  # logtools.latency_seeds.s000_rate_integral
    S002 = "s002-attitude-shift"  # logtools.latency_seeds.s002_attitude_shift
    XCORR = "xcorr-norm"  # |w| normalised cross-correlation (logtools.latency.coarse.xcorr_estimate)


#: the method names, in report order
LATENCY_METHODS: tuple[str, ...] = tuple(m.value for m in LatencyMethod)


@dataclass(frozen=True)
class MethodEstimate:
    latency_s: float
    sigma_s: float
    note: str = ""


@dataclass(frozen=True)
class LatencyResult:
    """Relative delay of the slave behind the master (DESIGN.md definition of ``latency_s``)."""

    latency_s: float  # value at the middle of the analysed window
    sigma_s: float
    drift_ppm: float  # d(latency)/dt in microseconds per second
    method: str
    window_s: tuple[float, float]  # master stamps as logged (absolute: UNIX or boot seconds)
    quality: dict = field(default_factory=dict)  # flags and figures: motion, periodicity, ...
    methods: dict[str, MethodEstimate] = field(default_factory=dict)
    # diagnostics for plots: lag grid (s) and normalised cost, per-window estimates
    cost_lag_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    cost: np.ndarray = field(default_factory=lambda: np.zeros(0))
    window_centers_s: np.ndarray = field(default_factory=lambda: np.zeros(0))  # master relative t
    window_latency_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    mounting_rpy_deg: tuple[float, float, float] | None = None  # rotation found from angular rate
    t_mid_rel_s: float = 0.0  # middle of the window, master relative seconds (where latency_s holds)

    @property
    def drift_reported_ppm(self) -> float | None:
        """``drift_ppm`` as the outputs state it: None where the method did not estimate a drift
        (``quality["drift_estimated"]`` False: a method that assumes none, or too few windows to fit one;
        ``quality["drift_not_estimated"]`` says which). ``drift_ppm`` then holds 0.0, what the compensation
        applies."""
        return None if self.quality.get("drift_estimated", True) is False else self.drift_ppm

    def latency_at(self, t_master_rel_s: np.ndarray) -> np.ndarray:
        """Latency (s) at master-relative instants, drift included."""
        return self.latency_s + self.drift_ppm * 1e-6 * (np.asarray(t_master_rel_s) - self.t_mid_rel_s)


#: the history names of the board's error states (logtools/alignment/run.py, _histories)
BOARD_STATE_PREFIXES = ("master_att_err_", "accel_misalign_")


@dataclass(frozen=True)
class AlignmentResult:
    """One transfer-alignment run (uncompensated or compensated)."""

    filter: str
    match: str
    mounting_rpy_deg: tuple[float, float, float]
    mounting_sigma_deg: tuple[float, float, float]
    gyro_bias_dph: tuple[float, float, float]
    accel_bias_mg: tuple[float, float, float]
    converged_s: float | None  # seconds from start until mounting sigma < threshold; None if never
    residual_rms: dict[str, float] = field(default_factory=dict)  # e.g. {"vel_m_s": .., "att_deg": ..}
    gyro_bias_sigma_dph: tuple[float, float, float] | None = None
    accel_bias_sigma_mg: tuple[float, float, float] | None = None
    delay_s: float | None = None  # delay state estimate, for delay-augmented filters
    delay_sigma_s: float | None = None
    #: the slave's position in the master's body frame (m): estimated (with its sigma), or as given
    #: (sigma None); None when velocity was not matched or no lever arm was modelled
    lever_arm_m: tuple[float, float, float] | None = None
    lever_arm_sigma_m: tuple[float, float, float] | None = None
    #: the mounting R (v_slave = R v_master) as conventions.quat_from_dcm (w >= 0), exact: mounting_rpy_deg is
    #: the canonical triple at the gimbal lock (pitch +-90 deg); None when the mounting is not determined
    mounting_quat_wxyz: tuple[float, float, float, float] | None = None
    observability: dict[str, bool] = field(default_factory=dict)  # state group -> observable?
    notes: tuple[str, ...] = ()
    #: each innovation channel's integrated correlation time (epochs): about 1 when the filter's noise model
    #: holds, larger when the data carry errors correlated in time that it does not model (a consumer
    #: board's EKF attitude error); None where not computed
    innovation_corr_epochs: tuple[float, ...] | None = None
    #: the mounting's sigma still fell at the end of the run (AlignmentConfig.settle_fall_ratio over its last
    #: settle_tail_frac): more data would tighten it; None where the mounting is not determined
    still_converging: bool | None = None
    # time histories for plots: t_s (master relative), states (N, k) with names, sigmas (N, k)
    history_t_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    history_names: tuple[str, ...] = ()
    history_x: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    history_sigma: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    residual_t_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    residual_names: tuple[str, ...] = ()
    residuals: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))

    @property
    def has_board_states(self) -> bool:
        """The filter carried a consumer board's error states (the master's attitude error where attitude
        was matched, the accelerometer triad's misalignment where velocity was)."""
        return any(n.startswith(BOARD_STATE_PREFIXES) for n in self.history_names)
