"""Every tuning number and switch of the latency estimator, in one frozen ``LatencyConfig``.

One section per stage (the package map in ``logtools.latency`` names the module of each). Each field
says in one line why it has its value and which benchmark (``benchmarks/bench_latency*.py``, the main
Monte Carlo unless named) or test set it. Change a value for one run with ``dataclasses.replace``::

    cfg = LatencyConfig()
    cfg = replace(cfg, windows=replace(cfg.windows, windows3_min_s=60.0))
    estimate(master, slave, config=cfg)

``stages`` is the one seam that is not a number: the refinement functions a run calls (None: the
package's own), for an ablation or a test that replaces one stage (see ``Stages``).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field


@dataclass(frozen=True)
class PrepareConfig:
    """Both units onto grids, the low-pass band, the motion check (``prepare``, ``inputs``)."""

    max_common_rate_hz: float = 200.0  # refinement grid cap: a 400-1000 Hz unit is low-passed then decimated (runtime)
    max_coarse_rate_hz: float = 100.0  # integer-lag search grid cap (runtime; the refinement is continuous)
    cutoff_fraction: float = 0.4  # the low-pass at most at this fraction of the common rate (80 % of Nyquist)
    #: the motion's band is the smaller of the two units' (each unit's noise, flexure, vibration widens its own
    #: only; the larger took a ship's fast flexure for motion: a 49 Hz cutoff) -- bench_latency_flexure
    band_common: bool = True
    band_min_cutoff_hz: float = 1.0  # the motion's band (signal/noise, the velocities' low-pass) at least here
    #: the rates' low-pass at least here: the Kalman fit's blocks must resolve the flexure (at 1 Hz, turning cars'
    #: IMU-only RMS 0.79 ms against a bound of 0.53; at 4 Hz 0.54) -- test_latency_flexure_band
    min_cutoff_hz: float = 4.0
    #: ... that floor at most this fraction of the common rate (a 10 Hz attitude-only slave was 7.7 ms off
    #: at 80 % of its Nyquist, right at 2 Hz) -- test_latency_flexure_band
    min_cutoff_fraction: float = 0.2
    band_factor: float = 3.0  # the low-pass cutoff at this x the motion's band (the noise above would bias the delay)
    refine_band_factor: float = 5.0  # refinement samples at this x the cutoff (band-limited: all the information) ...
    min_refine_rate_hz: float = 20.0  # ... and at least this rate
    #: a unit whose low-pass cutoff exceeds this fraction of its rate is put on its grid band-limited
    #: (``resample.to_uniform_band_limited``): a cubic spline read at a fixed offset from the samples delays a
    #: motion near the Nyquist frequency by up to 0.33 ms (15 Hz at 50 Hz); below this fraction by < 0.3 %
    #: of a sample interval (50 Hz slaves of a vibrating vehicle were up to 16 sigma off) -- test_latency_alias.py
    #: (test_a_50_hz_slave_...), bench_latency_hard.py set slow-vibrating
    band_limited_fraction: float = 0.15
    min_overlap_s: float = 5.0  # less overlap than this: an AnalysisError (test_latency short-log tests)
    #: stamps on a grid at least this coarse get a warning (a 1 ms logger clock: a floor of 0.29 ms); finer (a
    #: CSV written to the nanosecond, a 1 us clock) only enter the sigma budget: their floor of <= 2.9 us is
    #: below a tenth of the best sigma real logs give (0.02-0.03 ms, docs/latency.md)
    resolution_warn_s: float = 1e-5
    #: a unit's stamps put on its clock by an offset this uncertain (s) or more: said as a warning (a tlog's
    #: SYSTEM_TIME records sent in step with the millisecond: 0.29 ms; a DataFlash log's GPS week/ms: at least
    #: the 0.29 ms of its milliseconds; LogMeta channels' clock_sigma_s)
    clock_sigma_warn_s: float = 1e-4
    min_motion_snr: float = 2.0  # in-band motion/noise RMS below this: "no motion" AnalysisError (test_latency)
    low_motion_snr: float = 10.0  # ... below this: the "too_little_motion" flag (test_latency)
    low_motion_dps: float = 0.5  # ... or a master motion below this RMS (deg/s): the same flag
    min_motion_dps: float = 1e-3  # a master motion below this RMS (deg/s): "no motion" whatever its SNR
    #: the units' rates before the low-pass (``prepare.RawRates``) are let go after the first fit and made again
    #: when asked (the xcorr baseline) where they hold more than this: 4 h of two 200 Hz units are 138 MB, held
    #: through the velocity stage at the run's peak; below it, the time of making them again is spared
    raw_hold_max_bytes: float = 100e6
    accel_aided: bool = True  # accelerometer rows in the final GLS when both units log IMUs (bench_latency gyro-only)
    velocity_aided: bool = True  # velocity matching when both units log NED velocity (bench_latency no-velocity)


@dataclass(frozen=True)
class SpikeConfig:
    """Isolated spikes: one unit's IMU sample far off its neighbours while the other unit, at the same instant,
    shows nothing alike: replaced by its neighbours' mean for the latency (``spikes``)."""

    enabled: bool = True
    #: a sample's second difference this many robust sigmas above its neighbourhood's (and the whole series'):
    #: a candidate. The real logs' largest one-unit features stand at 31 (the elevator log's IMU2; its IMU at 4.8
    #: there), flipped bits of a float at 96-41467 -- test_latency_spikes
    min_sigmas: float = 50.0
    #: ... and this many times both neighbours' (an isolated spike's are half its own, of the other sign)
    isolation: float = 1.5
    half_width: int = 10  # the neighbourhood: this many samples each side
    #: the other unit's largest local z near the same instant at most this: nothing there (real impacts stand
    #: 27-137 high in the other unit too; its noise alone below 5) -- test_latency_spikes
    other_max_sigmas: float = 6.0
    #: "near": within this many steps of the slower unit (the coarse lag is good to a grid step)
    tolerance_steps: float = 2.0


@dataclass(frozen=True)
class SearchConfig:
    """The coarse search, periodic motion and the widened search (``coarse``, ``estimator``)."""

    #: an unbounded search evaluates the full-vector cost around this many best |w| peaks (6 missed a ship's
    #: true lag among 180 yaw-sway peaks) -- test_latency
    coarse_peaks: int = 48
    #: another minimum within this of the best normalised cost: periodic (noise-free best costs 1e-6..1e-5) --
    #: test_latency periodic tests
    periodic_margin: float = 1e-4
    periodic_rel_margin: float = 0.1  # ... or within this fraction of the best cost (the cost's spread on noisy data)
    #: the integer-lag minima re-ranked at their continuous minima (``coarse.subsample_minima``): a constant-
    #: frequency vibration makes minima a period apart and the grid favours whichever falls on a grid point
    #: (an aircraft vibrating at 8.56 Hz came out one period, 116 ms, off at sigma 0.05 ms) -- test_latency_alias
    subsample_rank: bool = True
    #: ... the minima within this x the cost a lag half a grid step off its minimum can add (the rates'
    #: derivative; the true lag 4.7 ms off the 10 ms grid added 0.94^2 of it) ...
    subsample_margin: float = 1.5
    subsample_candidates: int = 8  # ... at most this many (the best included): runtime, a bounded search each
    subsample_xtol: float = 0.01  # ... each minimum located to this fraction of a grid step
    subsample_max_rows: int = 30_000  # ... on every k-th grid row beyond this many (runtime: 45 ms a cost at 60 000)
    periodic_velocity: bool = True  # alternatives checked on the velocities where both units have them (test_latency)
    #: an alternative whose velocity residual RMS exceeds the estimate's this many times is rejected (3x the
    #: noise's power) -- test_latency
    periodic_velocity_ratio: float = 2.0
    search_widen: bool = True  # a suspect bounded result also searches the whole overlap (test_latency beyond max lag)
    search_edge_fraction: float = 0.9  # ... suspect: beyond this fraction of --max-lag
    #: ... or a normalised rate cost above this (good fits <= 0.006 on the real logs, 0.03 for an EKF attitude;
    #: a wrong lag 0.1-0.9) -- test_latency
    search_suspect_cost: float = 0.05
    search_widen_gain: float = 0.5  # the whole-overlap result replaces the bounded one below this x its cost
    #: a whole-overlap search's best lag (--max-lag auto, clocks that cannot be compared, or the widened search
    #: above, whose result replaces the bounded one only so) is a match only at a cost below this: the whole
    #: overlap holds far more lags than a bounded window, and a chance match among them is likelier (unrelated
    #: simulated vehicles matched at 0.23, 0.39 and 0.47 over 20 s of overlap at the lag found), so it must fit
    #: as a right lag does (the real pairs 1e-4 to 0.065, the worst a car's wheel odometry) -- test_latency
    whole_overlap_max_cost: float = 0.15
    #: the best lag leaves more than this fraction of the variance unexplained: no match (real pairs 1e-4 to 0.065,
    #: logs of different vehicles 0.91) -- test_latency
    no_match_cost: float = 0.5
    #: a latency (slave stamp - master stamp of one instant) beyond this magnitude is no clock offset at all: a log's
    #: clock reads UNIX time up to 2100 (4.1e9 s) or time since boot, so no two differ by more. Beyond it a time
    #: field was corrupt (int64 ns stamps wrapped: -2**64 ns = -1.8e10 s came out of --max-lag auto) -- test_latency
    max_latency_s: float = 4.2e9


@dataclass(frozen=True)
class RefineConfig:
    """The first fit, the band adaptation and the spectral GLS passes (``fit``, ``refine``, ``windows``)."""

    gls: bool = True  # weigh frequencies by motion / residual power (whitened Gauss-Newton): bench_latency
    gls_passes: int = 2  # whole-overlap GLS passes, the residual spectrum re-estimated before each (bench_latency)
    gls_taper_s: float = 2.0  # ramp of the GLS weights at the ends of the used data (whitening transients)
    adapt_band: bool = True  # narrow the band where the residuals outweigh the motion (no residual spectrum only)
    adapt_span_s: float = 300.0  # the first fit (and the band) on at most this central part (drift barely matters)
    min_adapt_cutoff_hz: float = 0.05  # the adapted cutoff at least this
    min_adapt_cycles: float = 20.0  # ... and at least this many cycles over the overlap
    adapt_gain: float = 0.7  # narrow only when the predicted variance drops below this fraction (> 20 % in sigma)
    adapt_min_ratio: float = 0.7  # ... and re-filter only where the new cutoff is below this x the old one
    gn_iters: int = 12  # Gauss-Newton iterations of the unwhitened fit (converges in 3-6)
    window_iters: int = 8  # ... of a drift window's fit
    gls_iters: int = 4  # whitened Gauss-Newton steps per GLS pass (converges in 2-3)


@dataclass(frozen=True)
class AccelConfig:
    """The accelerometer-aided GLS and its model check (``system``, ``refine``)."""

    gls_passes: int = 2  # aided passes, the 6-channel cross-spectrum re-estimated before each (bench_latency)
    min_sigma_s: float = 1e-4  # aided (and Kalman) fits only above this gyro-only sigma: below it they cannot matter
    lag_sigmas: float = 3.0  # the accelerometers' own delay beyond this many sigmas: the model check fails
    #: ... then an aided fit with that delay as a further unknown (a flexing ship: gyros alone 2.4 ms sigma,
    #: that delay solved 0.3 ms) -- bench_latency_flexure, test_latency
    lag_free: bool = True
    lag_max_s: float = 0.01  # ... kept while that delay is at most this (a linearised unknown)


@dataclass(frozen=True)
class FlexureConfig:
    """The Kalman (state-space flexure model) refinement (``refine``, ``flexure``)."""

    kalman: bool = True  # Kalman whitening after the spectral GLS (test_latency_flexure, bench_latency_flexure)
    #: farther than this many sigma from the spectral GLS, the two fits disagree (both go to the windows) --
    #: test_latency_flexure
    agree_sigmas: float = 5.0
    #: ... kept unless its windows disagree beyond this reduced chi-square and the spectral fit's checked sigma
    #: is the smaller (real logs whose disturbance is not flexure) -- bench_latency_flexure
    windows_chi2: float = 4.0
    iters: int = 6  # profile Newton steps (bench_latency_flexure: converged in 2-4)
    #: the Kalman fit takes the accelerometers on its own delay check (the 6-channel coherence model mismatched
    #: a turning car's) -- test_latency_flexure_band
    accel_own: bool = True
    #: "is this flexure?" (``is_flexure``): a model correlated longer than 1 / this (20 s) ... -- test_latency_flexure_band
    beta_min_1_s: float = 0.05
    sigma_max_deg: float = 1.0  # ... or beyond this sigma is not flexure (seed 000: 0.05 deg; benchmarks 0.02-0.1)
    ml_span_s: float = 120.0  # the model is fitted on at most this much of the overlap (its middle): runtime
    ml_blocks: int = 1500  # ... and on at most this many blocks: runtime
    decimate_factor: float = 2.5  # block rate = this x the low-pass cutoff (the low-passed noise near white)
    #: the likelihood wants this many blocks per unknown (4 kept 30 s records out, a 4.2 ms error at 0.9 ms) --
    #: bench_latency_hard short-flexure
    ml_blocks_per_unknown: float = 2.0
    max_ml_iter: int = 30  # L-BFGS-B iterations of the model's likelihood (runtime; converged well before)

    def is_flexure(self, beta_1_s: float, sigma_deg_max: float) -> bool:
        """The latency's criterion of a fitted flexure model (bandwidth beta, largest sigma per axis in
        degrees): a structure's flexure, so a Kalman candidate. Whether the alignment carries the model as
        states is the alignment's own, stricter question (``logtools.alignment.options.accepts_flexure_model``:
        a slower wander is not separable from the mounting)."""
        return bool(beta_1_s >= self.beta_min_1_s and sigma_deg_max <= self.sigma_max_deg)


@dataclass(frozen=True)
class WindowConfig:
    """The drift windows, the joint (L, drift) fit and its check (``windows``)."""

    window_s: float = 15.0  # nominal drift window (3..max_windows windows): bench_latency
    max_windows: int = 16  # at most this many windows (runtime)
    window_data_fraction: float = 0.9  # data over less of the span than this (gaps): windows in the runs of data
    min_window_s: float = 5.0  # ... each at least this long (bench_latency_hard dropout)
    windows3_min_s: float = 20.0  # overlaps this long get at least 3 drift windows (bench_latency_hard short)
    drift_search_ppm: float = 250.0  # a window's search band grows with the distance from the middle at this rate
    min_window_samples: int = 50  # a drift window needs this many refinement samples
    window_motion_fraction: float = 0.2  # windows with less motion than this x the median window's are left out
    #: ... and, where the fit has no accelerometers to aid it (gyros or attitude alone), windows whose motion
    #: beyond the master's noise is below this x the noisier unit's noise (``windows.window_snr``): a window of
    #: noise alone carries no delay, yet it locks on some lag with a linearised sigma of a few ms. On a log
    #: whose only motion is one turn the median is such a window, the fraction above keeps them all, and their
    #: line gave the drift: -502 +- 4.6 ppm for a true 0, the latency 3 sigma off (test_latency, one turn);
    #: "windows_disagree" fired at chi2 27-87 on one constant latency. With accelerometers the whole-overlap
    #: fit determined the drift of such logs (calm one-turn flights: latency errors within 1 sigma of 0.8-0.9
    #: ms); leaving the windows out there only tripled the sigma, so they stay
    window_min_snr: float = 0.5
    window_search_margin_steps: float = 2.0  # a window's lag search band: the drift's reach plus this many grid steps
    window_reject: float = 5.0  # a window this many sigma off the drift line is an outlier (a wrong minimum)
    window_drift: bool = True  # the windows' delays fitted with the joint fit's drift inside each (test_latency)
    window_drift_fraction: float = 0.1  # ... where it moves a window's delay end to end by more than this x sigma
    window_inflate: bool = True  # sigma inflated by the windows' scatter about the drift line (chi2 > 1)


@dataclass(frozen=True)
class GlsConfig:
    """The residual spectra, the whitening and the covariance's HAC floor (``gls``)."""

    smooth_hz: float = 0.05  # the residual spectrum smoothed over this band (a Markov spectrum is smooth there)
    floor: float = 1e-4  # PSD floor (fraction of the peak): the low-pass stop band is not amplified beyond it
    csd_bins: int = 15  # a cross-spectral matrix is smoothed over at least this many bins (conditioning)
    leverage_min_keep: float = 0.2  # a periodogram is scaled up by at most 1 / this (test_latency_velocity)
    hac_bandwidth_factor: int = 4  # Newey-West bandwidth = this x the lag where the scores decorrelate
    corr_max: float = 0.99  # |corr(L, drift)| at most this (the curvature and HAC parts may disagree)


@dataclass(frozen=True)
class VelocityConfig:
    """Velocity matching (``velocity``, ``velocity_pair``) and its fusion with the rate fit (``fusion``)."""

    max_cutoff_hz: float = 5.0  # the velocities low-passed at the rate fit's cutoff, at most this
    #: ... and at most this fraction of the slower nav rate (0.4: a 5 Hz nav velocity 6 ms late; 0.2 unbiased
    #: over 12 runs) -- test_latency_velocity
    cutoff_fraction: float = 0.2
    min_grid_hz: float = 20.0  # fit samples at 5x the cutoff, at least this (at most the slower nav rate)
    max_fit_samples: int = 60_000  # fit samples at most (runtime: a 4 h record at 1 Hz, one every 0.24 s)
    min_samples: int = 64  # finite velocity samples each unit needs
    iters: int = 6  # Gauss-Newton iterations per pass
    gls_passes: int = 2  # whitened passes after the first, the spectrum re-estimated before each
    taper_s: float = 2.0  # ramp of the weights at the ends of the used data (whitening transients)
    quanta_m_s: tuple[float, ...] = (0.1, 0.01, 0.001)  # the velocity grids recognised (MAVLink's cm/s)
    tilt: bool = True  # the slave's attitude error phi as unknowns: its velocity error (v - v_mid) x phi
    step_ratio: float = 10.0  # a jump of the residual's local mean beyond this x its median is a reset ...
    step_cycles: float = 2.0  # ... the means over this many cutoff periods either side (left out around it)
    step_sharp: float = 0.5  # ... keeping this much of it at half the scale (a step, not a manoeuvre)
    max_steps: int = 12  # more resets than this: no velocity fit
    window_min: int = 50  # samples a velocity drift window needs
    #: velocity stamps on a coarse grid floor its sigma at step / sqrt(12) -- bench_latency_hard ms-stamps
    stamp_resolution_floor: bool = True
    frame_min_deg: float = 0.2  # a frame rotation beyond this is undone before the fit (bench_latency_hard rotated-velocity)
    frame_min_rank: float = 0.02  # ... when the velocity varies in two directions (2nd/1st singular value)
    frame_iters: int = 3  # the fitted tilt, above tilt_exact_deg, undone exactly and the fit redone
    tilt_exact_deg: float = 0.05  # (the linear tilt model errs by |v| tilt^2 / 2) -- bench_latency_hard rotated-velocity
    #: the residual spectrum corrected for what the fitted columns take out (uncorrected: sigma 1.4x small on
    #: short records) -- test_latency_velocity
    leverage: bool = True
    edge_cycles: float = 4.0  # samples this many cutoff periods from a series' ends left out (mirrored filter ends)
    #: fused when it agrees: chi-square of (L) or (L, drift) below these (99.7 %) ... -- bench_latency
    agree_chi2: tuple[float, float] = (8.8, 11.6)
    fuse_flexure: bool = True  # ... and its sigma is the smaller, or the rate fit had to model flexure (bench_latency_flexure)


@dataclass(frozen=True)
class UncertaintyConfig:
    """The terms of ``sigma_s`` (``uncertainty``)."""

    sigma_calibration: float = 1.2  # Monte Carlo over the simulator: |error| <= 2 sigma in ~95 % of runs (bench_latency)
    sigma_floor_s: float = 5e-6  # model floor (interpolation, numerics)
    drift_prior_ppm: float = 100.0  # prior std of the relative clock drift (crystal clocks): test_latency
    #: stamps on a coarse grid floor the sigma at step / sqrt(12) per unit -- bench_latency_hard ms-stamps
    stamp_resolution_floor: bool = True
    #: spectral and Kalman fits disagreeing: the one kept has a sigma of at least this x their gap --
    #: test_latency_flexure
    flex_gap_cover: float = 0.5


@dataclass(frozen=True)
class OutputConfig:
    """The cost curve for the plots and the comparison methods (``estimator``)."""

    fine_cost_points: int = 41  # continuous cost samples around the estimate (plots; test_latency)
    fine_cost_sigmas: float = 5.0  # ... over +- this many sigma
    fine_cost_samples: int = 3  # ... or at least +- this many search-grid samples
    fine_cost_max_samples: int = 50_000  # ... on at most this many master samples (runtime)
    windows_disagree_chi2: float = 9.0  # the "windows_disagree" flag: their reduced chi-square beyond this (3 sigma)
    #: record (s) the seeds' grid searches get when run for comparison only (a 4 h log took 19 s) -- bench_latency
    compare_record_s: float = 600.0


@dataclass(frozen=True)
class StepConfig:
    """The clock-step check (``steps``): the windows' own delays against one line (L, drift) and against
    one line with an offset step at the best breakpoint (common drift). A unit's clock stepped or reset
    mid-log: one latency and drift do not describe the pair (sweep F1: a 20 ms step read as 240 ppm drift)."""

    check: bool = True  # run the check (test_clock_steps)
    window_s: float = 10.0  # the check's windows: about this long (shorter than the drift windows: where the step is)
    max_windows: int = 24  # ... at most this many (runtime: one search and fit each)
    min_windows: int = 5  # fewer windows with motion: no check (the step model needs 3 unknowns and spare windows)
    min_side: int = 2  # windows each side of a breakpoint at least (one window off the line is an outlier, not a step)
    #: a window's delay searched this far (s) about the fitted line: the steps it can measure (sweep B12: +500 ms;
    #: larger backward ones are split off by the parsers); with periodic motion at most ``periodic_band`` x the
    #: nearest alternative's distance (an alias is no step)
    search_s: float = 1.0
    periodic_band: float = 0.4
    #: the step model's chi-square below the line's by at least this (scaled by the step model's own reduced
    #: chi-square when above 1: the windows' sigmas are optimistic on real logs, chi2 63-86 with no step in
    #: sweep C07): 5 sigma for the one extra unknown, the choice among <= 24 breakpoints costing a factor ~24
    #: in the false-alarm rate (6e-7 x 24 ~ 1e-5)
    min_delta_chi2: float = 25.0
    min_step_sigmas: float = 5.0  # ... and the step beyond this many of its own (scaled) sigmas
    #: ... and below a smoothly curving drift's (a quadratic, as many unknowns) by this much: a clock whose
    #: drift changes over a long log (temperature) is no step (test_clock_steps slow drift)
    min_delta_vs_curve: float = 9.0
    #: ... and at least this large (s): below it a "step" is within what a window's motion centroid and a 1 ms
    #: stamp grid (0.29 ms) move the windows' delays
    min_step_s: float = 5e-4
    #: ... and beyond this many steps of the coarser stamp grid (``Ctx.stamp_resolution_s``): stamps truncated to
    #: a grid under a drifting clock carry a sawtooth error whose phase wraps by one grid step (a 50 Hz slave's
    #: 1 ms stamps at 5 ppm: a "step" of +0.54 +- 0.075 ms) -- test_latency_alias
    min_step_resolution: float = 1.5


@dataclass(frozen=True)
class Stages:
    """The refinement functions a run calls, None for the package's own (``refine.refine_flex``,
    ``refine.accel_aided``): the seam for an ablation or a test replacing a stage with the same signature."""

    refine_flex: Callable | None = None
    accel_aided: Callable | None = None


@dataclass(frozen=True)
class LatencyConfig:
    prepare: PrepareConfig = field(default_factory=PrepareConfig)
    spikes: SpikeConfig = field(default_factory=SpikeConfig)
    search: SearchConfig = field(default_factory=SearchConfig)
    refine: RefineConfig = field(default_factory=RefineConfig)
    accel: AccelConfig = field(default_factory=AccelConfig)
    flexure: FlexureConfig = field(default_factory=FlexureConfig)
    windows: WindowConfig = field(default_factory=WindowConfig)
    gls: GlsConfig = field(default_factory=GlsConfig)
    velocity: VelocityConfig = field(default_factory=VelocityConfig)
    uncertainty: UncertaintyConfig = field(default_factory=UncertaintyConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    steps: StepConfig = field(default_factory=StepConfig)
    stages: Stages = field(default_factory=Stages)


#: the configuration every default argument uses
DEFAULT = LatencyConfig()
