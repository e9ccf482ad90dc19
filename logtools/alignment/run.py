"""``run_alignment``: transfer alignment of the slave to the master (both on the master's clock).

Steps (each a function below, in this order): check the inputs -> slave IMU and master series (master
quality: frozen output, attitude jumps = EKF resets) -> delay window (the kinds with a delay state) ->
overlap -> coarse mounting (Wahba/Kabsch on the angular rates of both units) -> update epochs on the
slave's IMU stamps (``update_hz``, default 20 Hz) with the slave IMU's body increments folded per segment
-> slave initialised from the master at the first epoch -> filter passes (kf.py; flexure "auto" and the
noise recalibration may run it again) -> AlignmentResult with totals (coarse mounting combined with the
filter's residual), sigmas, convergence time, residual RMS, observability flags and decimated histories.
With ``board_errors="auto"`` the filter passes run without the board's states, and again with them when an
innovation channel of the first run is correlated in time, both on one preparation (:func:`_prepare`, what
comes before the filter passes: none of it depends on the board's states; :func:`_align_board_auto`).

What the caller knows goes in :class:`~logtools.alignment.options.AlignmentOptions`, the tuning in
:class:`~logtools.alignment.options.AlignmentConfig` (both documented field by field there).
"""
from __future__ import annotations

import weakref
from dataclasses import dataclass, fields, replace
from typing import Callable

import numpy as np

from logtools.conventions import (ARCMIN, ARCSEC, DEG, DEG_PER_H, G0_M_S2, MG, UG, dcm_from_euler, dcm_from_quat,
                                  euler_from_dcm, median_step_s, quat_from_dcm, quat_make_continuous, quat_mul,
                                  rotvec_from_quat, quat_conj, typical_step_s, wahba)
from logtools import earth
from logtools.dsp import as_trapezoid_integrates
from logtools.errors import AnalysisError
from logtools.inslog import InsLog
from logtools.navcheck import nav_gaps, output_validity
from logtools.rows import by_rows
from logtools.results import AlignmentResult
from logtools.strapdown import body_increments, compose_segments

from .imu_to_imu import axis_sigmas, finite_increasing, gimbal_canonical
from .kf import AlignInputs, FilterRun, FilterSettings, MasterSeries, run_filter
from .model import StateLayout, exp_so3, make_layout
from .noise import accel_noise_without_lever, d3_at, d3_sigma
from .options import CONFIG, MATCHES, AlignmentConfig, AlignmentOptions, FilterKind


def run_alignment(master: InsLog, slave: InsLog, *, filter: str | FilterKind = "kf", match: str = "vel+att",
                  smoother: bool = False, progress: Callable | None = None,
                  options: AlignmentOptions | None = None, config: AlignmentConfig = CONFIG,
                  board_decided: Callable[[bool], None] | None = None,
                  board_follow: Callable[[], bool] | None = None,
                  beside: Callable | None = None) -> AlignmentResult:
    """Transfer alignment; ``slave`` already on the master's clock (DESIGN.md). See the module doc.

    ``board_decided``: with ``board_errors="auto"``, called once with the decision as soon as it is made,
    before the filter with the board's states runs (True: it runs), so that a caller can start what depends
    on it. The result can still come without them, where that filter did not follow the data
    (``AlignmentResult.has_board_states`` says).

    ``board_follow``: with ``board_errors="auto"``, the decision is someone else's (another run's
    ``board_decided``): after the filter without the board's states, ``board_follow()`` says whether the
    filter runs again with them, on the same preparation; the result is the run without them or the one
    with them as it comes, exactly as ``board_errors=False`` or ``True`` would give it.

    ``beside``: a function like ``pipelines.parallel.submit`` (``beside(fn, *args, **kw)`` -> an object with
    ``result()`` and ``cancel()``). With ``flexure="auto"``, the pass with the flexure states then starts
    beside the rigid pass instead of after it, and is dropped where the rigid pass's residuals do not call for
    it: the same result, sooner where passes are slow (the CLI gives it to the uncompensated run: the delay
    left in its data makes the flexure pass follow almost always)."""
    opts = AlignmentOptions() if options is None else options
    kind = FilterKind.parse(filter)
    if match not in MATCHES:
        raise AnalysisError(f"match must be one of {', '.join(MATCHES)}, not {match!r}")
    if opts.board_auto:
        return _align_board_auto(master, slave, kind, match, smoother, progress, opts, config, board_decided,
                                 board_follow, beside)
    return _align(master, slave, kind, match, smoother, progress, opts, config, beside=beside)


def _align_board_auto(master: InsLog, slave: InsLog, kind: FilterKind, match: str, smoother: bool,
                      progress: Callable | None, opts: AlignmentOptions, config: AlignmentConfig,
                      board_decided: Callable[[bool], None] | None = None,
                      board_follow: Callable[[], bool] | None = None,
                      beside: Callable | None = None) -> AlignmentResult:
    """board_errors="auto": without the board's states first; when an innovation channel of that run is
    correlated in time (errors the white model leaves out), again with them (docs/alignment.md)."""
    prog = progress or (lambda f, s="": None)

    def first_prog(f: float, s: str = "") -> None:
        prog(0.5 * f, s)

    prep = _prepare(master, slave, kind, match, opts, config, first_prog)  # (the two runs' common part, once)
    first = _align(master, slave, kind, match, smoother, first_prog, replace(opts, board_errors=False), config, prep,
                   beside)
    if board_follow is not None:  # (the decision of another run: each run as it comes)
        if not board_follow():
            return first
        return _align(master, slave, kind, match, smoother, lambda f, s="": prog(0.5 + 0.5 * f, s),
                      replace(opts, board_errors=True), config, prep, beside)
    corr = max(first.innovation_corr_epochs or (1.0,))
    if board_decided is not None:
        board_decided(bool(corr > config.board_auto_corr_min))
    if not corr > config.board_auto_corr_min:
        return replace(first, notes=first.notes + (
            f"board error states not needed: no innovation channel is correlated over more than {corr:.1f} "
            f"epochs (at most {config.board_auto_corr_min:g}; --board-errors auto)",))
    res = _align(master, slave, kind, match, smoother, lambda f, s="": prog(0.5 + 0.5 * f, s),
                 replace(opts, board_errors=True), config, prep, beside)
    if _did_not_follow(res) and not _did_not_follow(first):
        # the states cannot explain what correlates the innovations (an unmodelled lever arm of metres:
        # tests/test_analyze_cli.py) and the larger filter lost the data: the run without them stands
        return replace(first, notes=first.notes + (
            f"board error states tried (an innovation channel correlated over {corr:.1f} epochs without them; "
            "--board-errors auto) but that filter did not follow the data; the run without them is reported",))
    return replace(res, notes=(
        f"board error states added (--board-errors auto): without them an innovation channel was correlated over "
        f"{corr:.1f} epochs (beyond {config.board_auto_corr_min:g}), errors in time the white model leaves out "
        f"(a consumer board's EKF attitude error, aliased vibration); that run gave the mounting "
        + " / ".join(f"{x:+.3f}" for x in first.mounting_rpy_deg) + " deg",) + res.notes)


#: the note of a run whose re-estimated measurement noise is beyond any INS's (the filter lost the data)
DID_NOT_FOLLOW = "residuals this large are no INS's noise"


def _did_not_follow(res: AlignmentResult) -> bool:
    return any(n.startswith(DID_NOT_FOLLOW) for n in res.notes)


def _align(master: InsLog, slave: InsLog, kind: FilterKind, match: str, smoother: bool, progress: Callable | None,
           opts: AlignmentOptions, config: AlignmentConfig, prep: Prepared | None = None,
           beside: Callable | None = None) -> AlignmentResult:
    """One alignment with the board's states as ``opts.board_errors`` (a bool) says; on ``prep`` when given
    (:func:`_prepare` of the same logs, kind, match and options but the board's states)."""
    prog = progress or (lambda f, s="": None)
    if prep is None:
        prep = _prepare(master, slave, kind, match, opts, config, prog)
    else:
        prog(0.0, "alignment: preparing")
    notes = list(prep.notes)
    prior = _mounting_prior(prep.coarse, dcm_from_quat(prep.inp.q0), opts, config, notes)
    prob = _Problem(kind, match, smoother, opts, config, master, prior, prep.win, prep.span_s, prep.noise,
                    prep.seed.prior_rad_s if prep.seed.applied else None, beside)
    run, lay, settings, sig0 = _filter_passes(prob, prep.inp, prep.src, progress, prog, notes)
    if prep.seed.applied:  # the bias estimates (and their history) are the seed plus the states
        xs = run.x.copy()
        xs[:, lay.gyro] += prep.seed.b_rad_s
        run = replace(run, x=xs)
    res = _result(run, lay, settings, sig0, kind, match, opts, config, notes)
    prog(1.0, "alignment done")
    return res


@dataclass(frozen=True)
class Prepared:
    """What an alignment prepares from the two logs before its filter: the delay window, the coarse mounting,
    the slave's noise, the gyro-bias seed, the filter's inputs (the slave's IMU over the overlap as the
    strapdown's increments), and the notes said on the way. None of it depends on the board's states:
    ``board_errors="auto"`` runs its two filters on one preparation (:func:`_align_board_auto`)."""

    src: str
    win: DelayWindow
    span_s: float
    coarse: CoarseMounting
    noise: SlaveNoise
    seed: GyroBiasSeed
    inp: AlignInputs
    notes: tuple[str, ...]


def _prepare(master: InsLog, slave: InsLog, kind: FilterKind, match: str, opts: AlignmentOptions,
             config: AlignmentConfig, prog: Callable) -> Prepared:
    """The preparation of :func:`_align` (the board's states aside)."""
    src = slave.meta.source_path or "slave"
    # one time base: relative times of logs with different t0 are not comparable (a no-op when the slave
    # is already rebased, as compensate() leaves it)
    if slave.meta.t0_ns != master.meta.t0_ns:
        slave = slave.rebased(master.meta.t0_ns)
    _check_inputs(master, slave, kind, match, src)
    notes: list[str] = []
    prog(0.0, "alignment: preparing")
    # the master's series and noise first, before the slave's copies (their temporaries are the stage's
    # largest: 4 h of a 200 Hz master, 0.5 GB beyond the 0.35 GB of the series)
    prepare_master(master, config)
    t_imu, gyro, accel = _slave_imu(slave, src)
    ms = _master_series_cached(master, config)
    win = _delay_window(kind, opts, config, master, ms, t_imu, gyro, notes)
    t_imu, gyro, accel, span_s = _overlap(master, ms, t_imu, gyro, accel, win, src)
    _note_master_gaps(ms, t_imu[0] - win.tau0_s, t_imu[-1] - win.tau0_s, notes)
    rates = _rates_on_grid(master, ms, t_imu, gyro, win.tau0_s, config)  # (the coarse mounting's and the seed's)
    if opts.mounting_guess_rpy_deg is not None:
        coarse = CoarseMounting(dcm_from_euler(np.radians(np.asarray(opts.mounting_guess_rpy_deg, float))), True)
    else:
        coarse = _coarse_mounting(master, slave, ms, rates, t_imu, win.tau0_s, accel, config)
        if coarse.note:
            notes.append(coarse.note)
    r0 = coarse.r0
    # (measured once: the seed and each pass's settings read it)
    noise = SlaveNoise(t_imu, gyro, accel,
                       accel_noise_without_lever(master, t_imu, gyro, accel, win.tau0_s, r0,
                                                 max_samples=config.noise_fit_samples,
                                                 chunk_s=config.noise_fit_chunk_s,
                                                 max_delay_s=config.noise_fit_max_delay_s,
                                                 min_rate_ratio=config.noise_fit_min_rate_ratio))
    seed = _gyro_bias_seed(master, ms, rates, win.tau0_s, r0, _gyro_bias_prior(opts, noise), config, notes)
    del rates  # (the coarse mounting's and the seed's only)
    # the filter's gyro-bias states carry what is left of the bias after the seed: the slave's increments are
    # taken with the seed removed (the bias states are linear, so this is the filter started from the seed)
    if seed.applied:  # (in place: the samples are this run's copy, not needed with the bias in them again)
        np.subtract(gyro, seed.b_rad_s, out=gyro)
    ep = _epochs(t_imu, gyro, accel, win.dt_upd_s, span_s, config, src,
                 notes, ms.t_s + win.tau0_s if win.paced else None, ms.gap if win.paced else None)
    del gyro, accel  # (the filter reads the increments: the samples go, 4 h of 200 Hz are 138 MB)
    ms_lever = _lever_rate_as_integrated(ms, t_imu, config)
    q0, v0, lever0 = _initial_state(master, slave, ms_lever, ep.t_s[0], win.tau0_s, r0, opts, src, notes)
    llh0 = _initial_position(master, slave, ep.t_s[0], opts, notes)
    inp = AlignInputs(ep.t_s, ep.seg_dq, ep.seg_dv_b, ep.seg_dt_s, ms_lever, q0, v0, llh0, r0, lever0, win.tau0_s,
                      ep.restart)
    return Prepared(src, win, span_s, coarse, noise, seed, inp, tuple(notes))


# ---- the steps of run_alignment ---------------------------------------------------------------------
@dataclass(frozen=True)
class DelayWindow:
    """The update rate and the delay the slave's stamps may carry: slave stamps t read the master at
    t - tau, tau within [lo_s, hi_s] (a single value without a delay state)."""

    update_hz: float
    dt_upd_s: float
    tau0_s: float  # the delay the filter starts from (kf-split: the constant part, shifted out)
    lo_s: float
    hi_s: float
    delay_state: bool  # the filter carries a delay state
    #: the updates at the master's own output instants (a master slower than the default update rate), not
    #: on a grid of update_hz (:func:`_epochs`)
    paced: bool = False


@dataclass(frozen=True)
class Epochs:
    """The update epochs on the slave's IMU stamps and the slave's increments between them."""

    t_s: np.ndarray  # (M+1,)
    seg_dq: np.ndarray  # (M, 4)
    seg_dv_b: np.ndarray  # (M, 3)
    seg_dt_s: np.ndarray  # (M,)
    restart: np.ndarray  # (M+1,) True after a gap in the slave's IMU


@dataclass(frozen=True)
class CoarseMounting:
    """The filter's start: the coarse mounting R0 (C_sm), whether it is a good start (else a wide prior), the
    note that says how it was found ("" for the rate fit), and the covariance (rad^2) of its error mu (s
    frame, model.py) from the fit's residuals; None where no fit gave one (the slave's own attitude, a
    given mounting, the identity)."""

    r0: np.ndarray
    ok: bool
    note: str = ""
    cov: np.ndarray | None = None
    #: d mu / d alpha: how the accelerometer triad's misalignment alpha (s frame) moves the start (zero
    #: where the specific forces took no part)
    d_force: np.ndarray | None = None


@dataclass(frozen=True)
class MountingPrior:
    """The prior of the coarse start's error: the mounting error mu (s frame, covariance rad^2), its
    covariance with the accelerometer triad's misalignment alpha (board_errors; a start that took a
    direction from the specific forces carries alpha) and the slave's initial attitude C_ns0 (the slave
    starts from the master through R0: its attitude error's prior is mu's, in the n frame)."""

    mount_cov: np.ndarray
    mount_alpha_cov: np.ndarray
    c_ns0: np.ndarray

    def sigmas(self) -> tuple[np.ndarray, np.ndarray]:
        """(mu's sigmas, s frame; phi's sigmas, n frame), rad."""
        s_m = np.sqrt(np.maximum(np.diag(self.mount_cov), 0.0))
        if np.array_equal(self.mount_cov, np.eye(3) * self.mount_cov[0, 0]):  # isotropic: the same in any frame
            return s_m, s_m.copy()
        att = self.c_ns0 @ self.mount_cov @ self.c_ns0.T
        return s_m, np.sqrt(np.maximum(np.diag(att), 0.0))


@dataclass(frozen=True)
class _Problem:
    """What the filter passes are set up from (everything but the prepared time series)."""

    kind: FilterKind
    match: str
    smoother: bool
    opts: AlignmentOptions
    config: AlignmentConfig
    master: InsLog
    prior: MountingPrior
    win: DelayWindow
    overlap_s: float
    noise: SlaveNoise  # the slave IMU's white noise over the overlap
    #: (3,) rad/s: the gyro-bias states' prior sigma where the bias was seeded (:class:`GyroBiasSeed`); None:
    #: the sensor grade's (``_gyro_bias_prior``)
    gyro_bias_prior_rad_s: np.ndarray | None = None
    #: run_alignment's ``beside``: the flexure pass started beside the rigid one (:func:`_filter_passes`)
    beside: Callable | None = None


@dataclass(frozen=True)
class GyroBiasSeed:
    """The slave's gyro bias measured before the filter: the mean of its rates less the master's inertial
    rates rotated by the coarse mounting (the latency's ``bias_diff_dph`` on the alignment's data), slave
    frame, rad/s. ``applied``: it is far beyond the sensor grade's prior, so the filter starts from it (its
    states then carry the rest) with the prior ``prior_rad_s`` (the grade's, widened by the seed's own
    uncertainty); otherwise the filter starts from zero as before."""

    b_rad_s: np.ndarray
    sigma_rad_s: np.ndarray  # the measurement's uncertainty (residuals, their correlation time, scale factor)
    applied: bool = False
    prior_rad_s: np.ndarray | None = None


def _check_inputs(master: InsLog, slave: InsLog, kind: FilterKind, match: str, src: str) -> None:
    if not (slave.has_gyro and slave.has_accel):
        raise AnalysisError(f"{src}: alignment needs the slave's IMU (angular rate and specific force)")
    if "att" in match and not master.has_quat:
        raise AnalysisError(f"{master.meta.source_path or 'master'}: match {match} needs the master's attitude")
    if "vel" in match and not master.has_vel:
        raise AnalysisError(f"{master.meta.source_path or 'master'}: match {match} needs the master's velocity")
    if kind.is_hinf:
        try:
            from . import hinf  # noqa: F401
        except ImportError as exc:
            raise AnalysisError(f"filter {kind.value} not available ({exc})") from exc


def _delay_window(kind: FilterKind, opts: AlignmentOptions, config: AlignmentConfig, master: InsLog,
                  ms: MasterSeries, t_imu: np.ndarray, gyro: np.ndarray, notes: list[str]) -> DelayWindow:
    # default update rate: config.default_update_hz, but not faster than the master's navigation output
    # (interpolated master samples between two updates would count the same information twice)
    nav_hz = 1.0 / median_step_s(ms.t_s)
    update_hz = float(opts.update_hz if opts.update_hz is not None else min(config.default_update_hz, nav_hz))
    delay_mode = kind.has_delay_state or bool(opts.delay_state)
    tau0 = float(opts.delay_s if opts.delay_s is not None else 0.0)
    if delay_mode and not kind.splits_delay and opts.delay_s is None:
        # start the delay state near the answer: the EKF's linearisation in the delay holds over a
        # fraction of the motion's period only (S004), so a coarse start keeps it from diverging
        tau0, why = _coarse_delay(master, ms, t_imu, gyro, float(opts.delay_max_s), config)
        notes.append(why)
    dt_upd = 1.0 / update_hz
    if kind.splits_delay:
        lo_tau, hi_tau = tau0 - dt_upd, tau0 + dt_upd
    else:
        dmax = float(opts.delay_max_s)
        lo_tau, hi_tau = (-dmax, dmax) if delay_mode else (tau0, tau0)
    paced = opts.update_hz is None and nav_hz < config.default_update_hz
    return DelayWindow(update_hz, dt_upd, tau0, lo_tau, hi_tau, delay_mode, paced)


def _overlap(master: InsLog, ms: MasterSeries, t_imu: np.ndarray, gyro: np.ndarray, accel: np.ndarray,
             win: DelayWindow, src: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The slave's IMU samples inside the overlap and the overlap's length (s): start and end on usable
    master output (an EKF that has not started yet outputs frozen values), for any delay in the window."""
    good = np.nonzero(ms.valid)[0] if ms.valid is not None else np.arange(len(ms.t_s))
    if len(good) < 3:
        raise AnalysisError(f"{master.meta.source_path or 'master'}: the master's attitude/velocity is frozen "
                            "or jumping over the whole log")
    t_a = max(t_imu[0], ms.t_s[good[0]] + win.hi_s)
    t_b = min(t_imu[-1], ms.t_s[good[-1]] + win.lo_s)
    if not t_b - t_a > 5 * win.dt_upd_s:
        raise AnalysisError(f"{src}: no time overlap between the master's nav and the slave's IMU "
                            f"(slave {t_imu[0]:.2f}..{t_imu[-1]:.2f} s, master {ms.t_s[0]:.2f}..{ms.t_s[-1]:.2f} s)")
    sel = (t_imu >= t_a) & (t_imu <= t_b)
    t_imu, gyro, accel = t_imu[sel], gyro[sel], accel[sel]
    if len(t_imu) < 10:
        raise AnalysisError(f"{src}: too few slave IMU samples in the overlap ({len(t_imu)})")
    _check_motion(gyro, accel, src)
    return t_imu, gyro, accel, float(t_b - t_a)


def _note_master_gaps(ms: MasterSeries, t_a: float, t_b: float, notes: list[str]) -> None:
    """A note of the gaps in the master's navigation output (:func:`_nav_gaps`) that reach into [t_a, t_b]
    (the overlap, master time): the filter has no measurement across them."""
    t, gap = ms.t_s, ms.gap
    k = np.nonzero(gap & (t[1:] > t_a) & (t[:-1] < t_b))[0]
    if len(k):
        d = t[k + 1] - t[k]
        notes.append(f"the master's navigation output has {len(k)} gap(s) in the overlap ({float(d.sum()):.2f} s "
                     f"in all, longest {float(d.max()):.2f} s, {float(t[k[np.argmax(d)]]):.1f} s into the log): "
                     "no updates across them")


def _epochs(t_imu: np.ndarray, gyro: np.ndarray, accel: np.ndarray, dt_upd: float, overlap_s: float,
            config: AlignmentConfig, src: str, notes: list[str], at_s: np.ndarray | None = None,
            at_gap: np.ndarray | None = None) -> Epochs:
    """The update epochs: slave IMU stamps every ``dt_upd``, or where ``at_s`` is given (the master's output
    instants on the slave's clock: a master slower than the default update rate), the slave IMU stamp
    nearest each. On a grid of its own, a slow master is read between its samples, interpolated over up to
    a whole step: a master's output in pairs 10 ms apart every 0.5 s (a median step of 0.25 s, a 4 Hz grid)
    gave a first-pass NIS/dof of 1900 and the mounting's sigma 0.19 arcmin where the pairs' own instants
    give 0.03 (tests/test_alignment.py, the paced-updates test). Inside the master's gaps (``at_gap``, its
    steps that are gaps) the grid's epochs stay, to propagate in steps (one step across 15 s of a 10 Hz
    master's gap put an aircraft's pitch 2.7 sigma off, a car's yaw 2.4); they have no update."""
    grid = np.arange(t_imu[0], t_imu[-1] + 1e-9, dt_upd)
    if at_s is not None and len(at_s) >= 2:
        in_gap = _in_gap(grid, at_s, at_gap) & (grid > at_s[0]) & (grid < at_s[-1])
        at = at_s[(at_s >= t_imu[0]) & (at_s <= t_imu[-1])]
        j = np.clip(np.searchsorted(t_imu, at), 1, len(t_imu) - 1)
        near = np.where(at - t_imu[j - 1] <= t_imu[j] - at, j - 1, j)
        filler = np.clip(np.searchsorted(t_imu, grid[in_gap] - 1e-9), 0, len(t_imu) - 1)
        idx = np.unique(np.concatenate([near, filler]))
    else:
        idx = np.unique(np.clip(np.searchsorted(t_imu, grid - 1e-9), 0, len(t_imu) - 1))
    if len(idx) < 5:
        raise AnalysisError(f"{src}: overlap too short for alignment ({overlap_s:.2f} s)")
    rv, dv, _ = body_increments(t_imu[idx[0]:idx[-1] + 1], gyro[idx[0]:idx[-1] + 1], accel[idx[0]:idx[-1] + 1])
    starts, stops = idx[:-1] - idx[0], idx[1:] - idx[0]
    seg_dq, seg_dv = compose_segments(rv, dv, starts, stops)
    t_ep = t_imu[idx]
    # gaps in the slave's IMU: the motion over them is unknown, so the slave's navigation restarts from
    # the master after each one (the mounting, biases and their covariance carry on)
    stamps = t_imu[idx[0]:idx[-1] + 1]
    steps = np.diff(stamps)
    gap_s = _imu_gap_s(stamps, config)
    seg_max = np.maximum.reduceat(steps, starts)
    restart = np.concatenate([[False], seg_max > gap_s])
    if restart.any():
        notes.append(f"{int(restart.sum())} gap(s) in the slave's IMU (longest {float(seg_max.max()):.2f} s): "
                     "its navigation restarted from the master after each")
    return Epochs(t_ep, seg_dq, seg_dv, np.diff(t_ep), restart)


def _initial_state(master: InsLog, slave: InsLog, ms: MasterSeries, t0: float, tau0: float, r0: np.ndarray,
                   opts: AlignmentOptions, src: str, notes: list[str]
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(q0, v0, lever0): the slave's attitude and velocity from the master at the first epoch (else from
    the slave's own), the lever arm the filter starts from."""
    lever0 = np.asarray(opts.lever_arm_m if opts.lever_arm_m is not None else np.zeros(3), float)
    c_nm0, v_m0, _, w_m0 = ms.sample(t0 - tau0)
    if c_nm0 is not None:
        q0 = quat_from_dcm(c_nm0 @ r0.T)
    elif slave.has_quat:
        tq, qs = slave.quat_wxyz()
        q0 = qs[int(np.clip(np.searchsorted(tq, t0), 0, len(tq) - 1))]
        notes.append("initial slave attitude from the slave's own attitude (the master has none)")
    else:
        raise AnalysisError(f"{src}: velocity matching needs an initial attitude: neither the master nor "
                            "the slave log has one")
    if v_m0 is not None:
        cm = c_nm0 if c_nm0 is not None else np.eye(3)
        v0 = v_m0 + cm @ np.cross(w_m0 if w_m0 is not None else np.zeros(3), lever0)
    elif slave.has_vel:
        tv, vs = slave.vel_ned_m_s()
        v0 = vs[int(np.clip(np.searchsorted(tv, t0), 0, len(tv) - 1))]
    else:
        v0 = np.zeros(3)
        notes.append("initial slave velocity set to zero (neither log has a velocity)")
    return q0, v0, lever0


def _setup(prob: _Problem, flexure: bool, board: bool = False) -> tuple[StateLayout, FilterSettings, np.ndarray]:
    """The state layout, filter settings and prior sigmas of one pass (with or without flexure states,
    with or without the board's error states)."""
    ly = make_layout(prob.match, flexure=flexure, lever_arm=bool(prob.opts.estimate_lever_arm),
                     delay=prob.win.delay_state, board_errors=board)
    st, s0 = _settings(prob.kind, ly, prob.master, prob.noise, prob.opts, prob.config,
                       prob.prior, prob.win.dt_upd_s, prob.win.tau0_s, (prob.win.lo_s, prob.win.hi_s),
                       prob.smoother, prob.gyro_bias_prior_rad_s)
    return ly, st, s0


def _filter_passes(prob: _Problem, inp: AlignInputs, src: str, progress: Callable | None, prog: Callable,
                   notes: list[str]) -> tuple[FilterRun, StateLayout, FilterSettings, np.ndarray]:
    """The forward pass, and where called for the pass with flexure states (flexure="auto") and the pass
    with the measurement noise re-estimated from the residuals."""
    opts, cfg = prob.opts, prob.config
    lay, settings, sig0 = _setup(prob, bool(opts.flexure) and not opts.flexure_auto, opts.board_errors)
    if prob.smoother:
        need_gb = len(inp.t_epoch_s) * lay.n**2 * 8 * 3 / 1e9
        if need_gb > 2.0:
            raise AnalysisError(f"{src}: the RTS smoother would store {need_gb:.1f} GB for {prob.overlap_s:.0f} s at "
                                f"{prob.win.update_hz:g} Hz; lower update_hz or run without the smoother")
    prog(0.05, "alignment filter")
    sub = (lambda f, s="": prog(0.05 + 0.9 * f, s)) if progress else None
    flex_ahead = None  # the flexure pass started beside the rigid one (prob.beside), with its setup
    if (prob.beside is not None and opts.flexure_auto and lay.flex_ang is None and not prob.smoother
            and len(inp.t_epoch_s) * lay.n * cfg.pass_bytes_per_state_epoch < cfg.hold_one_pass_min_bytes):
        ahead = _setup(prob, True, lay.has_board_states)
        flex_ahead = (ahead, prob.beside(run_filter, inp, ahead[1], progress=None, compiled=cfg.compiled_kf))
    try:
        run = run_filter(inp, settings, progress=sub, compiled=cfg.compiled_kf)
    except BaseException:
        if flex_ahead is not None:
            flex_ahead[1].cancel()
        raise
    nis_rigid = _mean_nis(run)
    if opts.flexure_auto and lay.flex_ang is None and nis_rigid > cfg.flex_auto_nis * lay.n_meas:
        # residuals far beyond the noise model: is it a flexing slave? The flexure states are kept when
        # they explain most of the excess (mean NIS down by flex_auto_gain at least)
        dropped = flex_ahead is None and _run_bytes(run) >= cfg.hold_one_pass_min_bytes
        if dropped:
            del run
        if flex_ahead is not None:
            (lay_f, st_f, sig0_f), pending = flex_ahead
            run_f = pending.result()
        else:
            lay_f, st_f, sig0_f = _setup(prob, True, lay.has_board_states)
            run_f = run_filter(inp, st_f, progress=None, compiled=cfg.compiled_kf)
        if _mean_nis(run_f) < cfg.flex_auto_gain * nis_rigid:
            notes.append(f"flexure states added (mean NIS/dof {nis_rigid / lay.n_meas:.1f} without them, "
                         f"{_mean_nis(run_f) / lay_f.n_meas:.1f} with)")
            lay, settings, sig0, run = lay_f, st_f, sig0_f, run_f
        elif dropped:
            del run_f
            run = run_filter(inp, settings, progress=None, compiled=cfg.compiled_kf)
    elif flex_ahead is not None:  # (the rigid pass stands: the flexure pass beside it is not wanted)
        flex_ahead[1].cancel()
    if lay.flex_ang is not None:
        notes.append(f"flexure states (seed 000 eq 8): sigma {_fmt3(np.degrees(sig0[lay.flex_ang]))} deg, "
                     f"beta {settings.flex_beta:.3g} 1/s")
    recal = _recalibrated(run, lay, settings, opts, cfg) if opts.recalibrate_noise else None
    if recal is not None:
        # the residuals are far larger than the noise model says (real data: vibration, EKF smoothing,
        # flexure), or far smaller (a master's navigation at 1-2 Hz, whose third differences measure the
        # motion): rerun with the measurement noise taken from the first pass's residuals
        nis0 = _mean_nis(run)
        settings = recal
        del run  # (its histories are not held while the second pass runs: 4 h at 19 Hz are 0.2 GB)
        run = run_filter(inp, settings, progress=None, compiled=cfg.compiled_kf)
        ratio = nis0 / lay.n_meas
        ratio_text = f"{ratio:.1f}" if ratio >= 0.1 else f"{ratio:.2g}"
        notes.append(f"measurement noise re-estimated from the residuals (first pass NIS/dof {ratio_text}): "
                     f"velocity {settings.r_vel_m_s:.3g} m/s, attitude {settings.r_att_rad / DEG:.3g} deg")
        if settings.r_vel_m_s > cfg.implausible_r_vel_m_s or settings.r_att_rad > cfg.implausible_r_att_deg * DEG:
            notes.append(DID_NOT_FOLLOW + ": the filter did not follow the data (a wrong "
                         "start, an uncompensated delay or reset, other units); the mounting is doubtful")
    if lay.master_att is not None:
        s_mk = np.degrees(sig0[lay.master_att][0])
        notes.append(f"master attitude error states: first-order Markov, sigma {s_mk:.3g} deg, correlation time "
                     f"{settings.master_att_tau_s:.3g} s")
    if lay.accel_mis is not None:
        am = np.degrees(run.x[-1, lay.accel_mis])
        am_s = np.degrees(np.sqrt(run.p_diag[-1, lay.accel_mis]))
        notes.append("slave accelerometer triad misalignment from its gyro triad (x/y/z): "
                     + " / ".join(f"{a:+.2f} +- {b:.2f}" for a, b in zip(am, am_s)) + " deg")
        lim = cfg.accel_misalign_implausible_sigmas * np.degrees(sig0[lay.accel_mis])
        if np.any(np.abs(am) > lim):
            notes.append(f"the accelerometer triad misalignment came out beyond "
                         f"{cfg.accel_misalign_implausible_sigmas:g} sigma, far beyond its prior: no board's triads "
                         "are that far apart, the velocity matching is not explained by it (the master's velocity, "
                         "a lever arm, scale factors); the mounting is doubtful")
    return run, lay, settings, sig0

# ---- inputs ---------------------------------------------------------------------------------------
def _slave_imu(slave: InsLog, src: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = slave.t_imu_s()
    g = slave.gyro_rad_s()
    a = slave.accel_m_s2()
    ok = np.isfinite(t) & np.isfinite(g).all(1) & np.isfinite(a).all(1)
    if not ok.all():
        t, g, a = t[ok], g[ok], a[ok]
    if len(t) < 10:
        raise AnalysisError(f"{src}: the slave's IMU has fewer than 10 finite samples")
    d = np.diff(t)
    if np.any(d < 0):
        order = np.argsort(t, kind="stable")
        t, g, a = t[order], g[order], a[order]
        d = np.diff(t)
    keep = np.concatenate([[True], d > 0])
    if keep.all():  # nothing to drop: one C-ordered copy each (what the masked copies were), not three
        return t.copy(), np.array(g, order="C"), np.array(a, order="C")
    return t[keep], g[keep], a[keep]


_LAST_MASTER: list = []  # [(weak ref to the master, {key: value})]: what was prepared for the last master


def _for_master(master: InsLog, key: tuple, make: Callable[[], object]):
    """``make()``, kept under ``key`` for the same master object (analyze runs the alignment two or three
    times against one master; InsLog is immutable); held weakly: it goes when the master does (a batch does
    not keep the last pair's master)."""
    if not (_LAST_MASTER and _LAST_MASTER[0][0]() is master):
        ref = weakref.ref(master)
        _LAST_MASTER[:] = [(ref, {})]
        weakref.finalize(master, _forget_master, ref)
    memo = _LAST_MASTER[0][1]
    if key not in memo:
        memo[key] = make()
    return memo[key]


def _master_series_cached(master: InsLog, config: AlignmentConfig = CONFIG) -> MasterSeries:
    """:func:`_master_series`, prepared once for the same master object and rate settings."""
    def make() -> MasterSeries:
        ms = _master_series(master, config)
        for f in fields(ms):  # shared between runs: read-only
            v = getattr(ms, f.name)
            if isinstance(v, np.ndarray):
                v.flags.writeable = False
        return ms

    return _for_master(master, ("series", config.lever_rate_max_half_span_s, config.lever_rate_attenuation,
                                config.nav_shared_stamps, config.nav_gap_steps), make)


def prepare_master(master: InsLog, config: AlignmentConfig = CONFIG) -> None:
    """What every run against ``master`` prepares (its series at the navigation rate, its attitude's and
    velocity's noise), prepared now and kept for this master object: runs forked after this share it (copy
    on write) instead of each preparing its own (0.9 s of CPU for a 1 h pair of 200 Hz logs; the series
    are about 350 MB at 4 h). A master a run cannot use is left for that run to say so."""
    try:  # (the noise first: its temporaries are not held beside the series)
        _master_attitude_noise(master, config)
        _master_velocity_noise(master, config)
        _master_series_cached(master, config)
    except AnalysisError:
        pass


def _master_attitude_noise(master: InsLog, config: AlignmentConfig = CONFIG) -> float | None:
    """The white noise of the master's attitude (rad, :func:`_nav_noise` of its rotation from the first
    attitude), None with fewer than 9 attitudes; once per master."""
    def make() -> float | None:
        tq, q = master.quat_wxyz()
        if len(q) <= 8:
            return None
        q0 = quat_conj(q[:1])
        return _nav_noise(tq, by_rows(lambda qb: rotvec_from_quat(quat_mul(q0, qb)), quat_make_continuous(q)),
                          config)

    return (_for_master(master, ("attitude noise", config.bursty_step_ratio), make) if master.has_quat
            else None)


def _master_velocity_noise(master: InsLog, config: AlignmentConfig = CONFIG) -> float | None:
    """The white noise of the master's velocity (m/s, :func:`_nav_noise`), None without one; once per master."""
    return (_for_master(master, ("velocity noise", config.bursty_step_ratio),
                        lambda: _nav_noise(*master.vel_ned_m_s(), config)) if master.has_vel else None)


def _nav_noise(t: np.ndarray, y: np.ndarray, config: AlignmentConfig = CONFIG) -> float:
    """:func:`_hf_sigma` of a navigation output ``y`` at stamps ``t``; from the third divided differences at
    the stamps (``noise.d3_at``) where the stream comes in bursts (its typical step beyond
    config.bursty_step_ratio of its median one): there the plain third differences mix steps of 10 ms and
    0.5 s and measure the motion, not the noise (a master's attitude and velocity in pairs 10 ms apart
    every 0.5 s: 0.53 deg and 0.89 m/s for 0.0007 deg and 0.0025 m/s, the mounting 0.7 arcmin off at a
    sigma of 2.2 where a plain 2 Hz master gave 0.02 at 0.03)."""
    ok = np.isfinite(t) & np.isfinite(y).all(axis=1)
    if not ok.all():
        t, y = t[ok], y[ok]
    if len(t) >= 8 and _bursty(t, config):
        return d3_sigma(d3_at(t, y))
    return _hf_sigma(y)


def _bursty(t: np.ndarray, config: AlignmentConfig = CONFIG) -> bool:
    """The stamps ``t`` come in bursts: their typical step beyond config.bursty_step_ratio of their median."""
    return len(t) >= 3 and typical_step_s(t) > config.bursty_step_ratio * median_step_s(t)


def _forget_master(ref) -> None:
    if _LAST_MASTER and _LAST_MASTER[0][0] is ref:
        _LAST_MASTER.clear()


def forget_master(master: InsLog) -> None:
    """Let go of what was prepared for ``master`` (its series at the navigation rate: 4 h of 200 Hz is
    about 350 MB) once its alignment runs are done; a later run prepares it again."""
    if _LAST_MASTER and _LAST_MASTER[0][0]() is master:
        _LAST_MASTER.clear()


def _master_series(master: InsLog, config: AlignmentConfig = CONFIG) -> MasterSeries:
    src = master.meta.source_path or "master"
    t_nav = master.t_nav_s()
    if len(t_nav) < 3:
        raise AnalysisError(f"{src}: the master has fewer than 3 navigation samples")
    quat = vel = acc = w = None
    cols_t = []
    if master.has_quat:
        tq, q = master.quat_wxyz()
        cols_t.append(tq)
    if master.has_vel:
        tv, v = master.vel_ned_m_s()
        cols_t.append(tv)
    if master.has_quat and master.has_vel:
        t, q, v = _nav_common_stamps(tq, q, tv, v, config)  # q, v at t
    else:
        t = np.unique(cols_t[0])
        if master.has_quat:
            q = q[np.searchsorted(tq, t)]
        else:
            v = v[np.searchsorted(tv, t)]
    del cols_t  # (the streams' own stamps: the series' are t; what is no longer needed goes at once below, 4 h
    tq = tv = None  # of a 200 Hz master's series being 0.35 GB)
    if len(t) < 3:
        raise AnalysisError(f"{src}: the master's attitude and velocity overlap in fewer than 3 samples")
    if master.has_quat:
        ok = np.isfinite(q).all(1)
        quat = quat_make_continuous(q / np.linalg.norm(q, axis=1, keepdims=True))
        q = None
    else:
        ok = np.ones(len(t), bool)
    if master.has_vel:
        ok &= np.isfinite(v).all(1)
    every = bool(ok.all())  # (nothing to drop: no copies)
    t = t if every else t[ok]
    if len(t) < 3:
        raise AnalysisError(f"{src}: the master has fewer than 3 finite navigation samples")
    gap = _nav_gaps(t, config)
    w_t = None
    if quat is not None:
        quat = quat if every else quat[ok]
        # body rate relative to NED in the master frame (lever arm): from the master's gyro when it has
        # one (minus the earth rate), else from its attitude differenced over ~0.1 s (a noisy rate in H
        # would bias the lever-arm estimate toward zero: errors in variables)
        if master.has_gyro:
            w, w_t = _gyro_rate_nm(master, t, quat)
        if w is None:
            w = _rate_from_attitude(t, quat, config, gap)
    if master.has_vel:
        vel = v if every else v[ok]
        v = None
        acc = _derivative(t, vel, span_s=0.1, gap=gap)
    # a bursty output's long steps are judged like gaps: against the gyro integrated over them, not the rate
    # at their middle (pairs 0.2 s apart every 2 s from a multirotor: 26 of 30 long steps called EKF
    # resets, 53 of 59 updates skipped)
    judged_apart = gap | (np.diff(t) > config.bursty_step_ratio * median_step_s(t)) if _bursty(t, config) else gap
    valid, resets = _master_quality(master, t, quat, vel, judged_apart, config)
    # across a gap the motion is unknown: no measurement from the interpolation over it (the samples that
    # bound it go with it: the filter reads both samples around an instant)
    valid[:-1] &= ~gap
    valid[1:] &= ~gap
    return MasterSeries(t, quat, vel, acc, w, valid, resets, w_t_s=w_t, gap=gap)


def _nav_gaps(t: np.ndarray, config: AlignmentConfig = CONFIG) -> np.ndarray:
    """(K-1,) True at the steps of the master's navigation stamps ``t`` longer than config.nav_gap_steps of
    its typical steps (``typical_step_s``: telemetry's bursts are no gaps): samples missing (a dropout, a
    log cut out). Linearly interpolated across such a gap, the attitude and velocity are measurements of a
    motion the master never output: a 5 s gap in a simulated aircraft's 200 Hz master took the mounting's
    sigma from 0.01-0.03 to 0.45-0.68 arcmin, its pitch 3.7 arcmin off (tests/test_alignment.py, the
    master-gap test)."""
    return nav_gaps(t, config.nav_gap_steps)


def _gyro_rate_nm(master: InsLog, t: np.ndarray, quat: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(w, stamps): the master's body rate relative to NED (its gyro less the earth rate, master frame) on the
    gyro's own stamps over the navigation stamps ``t`` (one sample beyond each end), for the lever arm's
    velocity: a rigid-body vibration between two navigation samples (a car's 8-20 Hz under a 20 Hz output)
    moves the slave's velocity by w x r at the filter's epochs, and the rate interpolated from the navigation
    rate has none of it (an independent simulator's car: its lever arm 1.15 m off at a sigma of 0.023 m).
    The earth rate in the body frame (slow) is interpolated from the navigation stamps. (None, None) without
    two finite gyro samples there."""
    tg, g = finite_increasing(master.t_imu_s(), master.gyro_rad_s())
    i0 = max(int(np.searchsorted(tg, t[0], side="right")) - 2, 0)
    i1 = min(int(np.searchsorted(tg, t[-1], side="left")) + 2, len(tg))
    tg, g = tg[i0:i1], g[i0:i1]
    if len(tg) < 2:
        return None, None
    lat = np.radians(master.lat_lon_alt()[1][0, 0]) if master.has_pos else np.radians(45.0)
    w_ie_n = earth.earth_rate_ned(lat)
    w_ie_b = by_rows(lambda qb: np.einsum("kji,j->ki", dcm_from_quat(qb), w_ie_n), quat)
    return g - _interp_cols(tg, t, w_ie_b), tg


def _lever_rate_as_integrated(ms: MasterSeries, t_imu: np.ndarray, config: AlignmentConfig = CONFIG
                              ) -> MasterSeries:
    """``ms`` with its rate (the lever arm's velocity C_nm (w x r)) as the slave's strapdown carries it: the
    slave integrates the lever arm's acceleration from point samples at its own rate by the trapezoid, which
    keeps x / tan(x) of a motion at frequency f (x = pi f / rate) and nothing the filter could model above
    half its rate (``logtools.dsp.as_trapezoid_integrates``). The rate taken whole made the filter fit
    C_nm (w x r) to a velocity that carried 0.41-0.77 of a 12-20 Hz vibration's w x r at a 50 Hz slave: a
    car's lever arm came out at 0.63-0.8 of itself, 3.7-4.9 sigma off (with a 200 Hz slave, within 1.4
    sigma). A slow motion is unchanged (x -> 0). The gyro is first resampled band-limited to at least
    ``config.lever_rate_grid_hz``: the filter reads it by linear interpolation.

    Only a rate from the master's gyro: one from its attitude is differenced over ~0.1 s, with nothing fast
    left in it (``_rate_from_attitude``)."""
    if ms.w_nm_m is None or ms.w_t_s is None or len(t_imu) < 2:
        return ms
    tw = ms.w_t_s
    up = int(np.ceil(config.lever_rate_grid_hz * median_step_s(tw) - 1e-9))
    t_w, w = as_trapezoid_integrates(tw, ms.w_nm_m, 1.0 / median_step_s(t_imu), _imu_gap_s(tw, config), upsample=up)
    return replace(ms, w_nm_m=w, w_t_s=t_w)


def _nav_common_stamps(tq: np.ndarray, q: np.ndarray, tv: np.ndarray, v: np.ndarray, config: AlignmentConfig
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, quat, vel) of a master whose attitude and velocity come with their own stamps and rates.

    Where they share (nearly) all stamps (one EKF output), the shared stamps. Else the sparser stream's
    stamps inside the other's span, the denser interpolated at them (the attitude by normalised linear
    interpolation of sign-continuous quaternions, the velocity linearly; samples in a gap of the
    interpolated stream, :func:`_nav_gaps`, dropped): each measurement used once, at its own instant, at
    the sparser rate (the filter's update rate follows it), the interpolation's small error left to the
    measurement noise the filter estimates from its residuals."""
    t_shared = np.intersect1d(tq, tv)
    if len(t_shared) >= config.nav_shared_stamps * min(len(np.unique(tq)), len(np.unique(tv))):
        return t_shared, q[np.searchsorted(tq, t_shared)], v[np.searchsorted(tv, t_shared)]
    okq, okv = np.isfinite(q).all(1), np.isfinite(v).all(1)
    tq, q, tv, v = tq[okq], q[okq], tv[okv], v[okv]
    tq, iq = np.unique(tq, return_index=True)
    tv, iv = np.unique(tv, return_index=True)
    q, v = q[iq], v[iv]
    if len(tq) < 2 or len(tv) < 2:
        return np.zeros(0), q[:0], v[:0]
    q = quat_make_continuous(q / np.linalg.norm(q, axis=1, keepdims=True))
    if len(tv) <= len(tq):  # attitude onto the velocity's stamps
        t = tv[(tv >= tq[0]) & (tv <= tq[-1])]
        src_t, src_y = tq, q
    else:
        t = tq[(tq >= tv[0]) & (tq <= tv[-1])]
        src_t, src_y = tv, v
    j = np.clip(np.searchsorted(src_t, t), 1, len(src_t) - 1)
    t = t[~_nav_gaps(src_t, config)[j - 1]]
    y = _interp_cols(t, src_t, src_y)
    if len(tv) <= len(tq):
        return t, y / np.linalg.norm(y, axis=1, keepdims=True), v[np.searchsorted(tv, t)]
    return t, q[np.searchsorted(tq, t)], y


def _rate_from_attitude(t: np.ndarray, quat: np.ndarray, config: AlignmentConfig = CONFIG,
                        gap: np.ndarray | None = None) -> np.ndarray:
    """Body rate relative to NED (master frame) from the attitude, central differences over +- h.

    h is the longest span (at most config.lever_rate_max_half_span_s: the fewer the samples differenced, the noisier
    the rate, and a noisy rate in H biases the lever arm toward zero, errors in variables) whose
    attenuation of the motion stays below config.lever_rate_attenuation at its rate-weighted mean frequency (the
    difference quotient's gain is sin(2 pi f h) / (2 pi f h)). A fixed +- 0.05 s took 2-6 % off a
    multirotor's 1-2 Hz rates: with a 2.9 m lever arm and flexure states its mounting came out 2.5 arcmin
    off at a sigma of 0.37 arcmin; +- one 100 Hz sample: 0.6 arcmin. ``gap`` (:func:`_nav_gaps`): no
    difference reaches across one."""
    dt_med = median_step_s(t)
    half_max, atten = config.lever_rate_max_half_span_s, config.lever_rate_attenuation

    def diff_rate(y: np.ndarray, half_s: float, rot: bool) -> np.ndarray:
        i0, i1 = _span_indices(len(t), max(int(round(half_s / dt_med)), 1), gap)
        span = np.maximum(t[i1] - t[i0], 1e-9)[:, None]
        return (rotvec_from_quat(quat_mul(quat_conj(y[i0]), y[i1])) if rot else y[i1] - y[i0]) / span

    w = diff_rate(quat, half_max, True)
    dw = diff_rate(w, half_max, False)
    motion = float(np.sqrt(np.mean(np.sum((w - w.mean(axis=0)) ** 2, axis=1))))
    f_hz = float(np.sqrt(np.mean(np.sum(dw ** 2, axis=1)))) / (2.0 * np.pi * motion) if motion > 0 else 0.0
    # sin(x)/x = 1 - x^2/6: below the attenuation a up to x = sqrt(6 a)
    h = np.sqrt(6.0 * atten) / (2.0 * np.pi * f_hz) if f_hz > 0 else np.inf
    if h >= half_max:
        return w
    return diff_rate(quat, h, True)


def _master_quality(master: InsLog, t: np.ndarray, quat: np.ndarray | None, vel: np.ndarray | None,
                    gap: np.ndarray | None = None, config: AlignmentConfig = CONFIG
                    ) -> tuple[np.ndarray, np.ndarray]:
    """(valid mask, reset times) of the master's output (``logtools.navcheck``), its attitude increments
    checked against its own gyro where it logs one; ``gap``: its gaps (:func:`_nav_gaps`), over which the
    attitude's change is checked against the gyro integrated across the gap (:func:`_resets_across_gaps`)."""
    rate = None
    if quat is not None and len(t) > 3 and master.has_gyro:
        tg, g = finite_increasing(master.t_imu_s(), master.gyro_rad_s())
        if len(tg) >= 2:
            rate = np.linalg.norm(_interp_cols(0.5 * (t[:-1] + t[1:]), tg, g), axis=1)
    valid, resets = output_validity(t, quat, vel, rate, gap)
    if rate is not None and gap is not None and gap.any():
        resets = np.sort(np.concatenate([resets, _resets_across_gaps(t, quat, gap, tg, g, config)]))
    return valid, resets


def _resets_across_gaps(t: np.ndarray, quat: np.ndarray, gap: np.ndarray, tg: np.ndarray, g: np.ndarray,
                        config: AlignmentConfig) -> np.ndarray:
    """The ends of the gaps in the master's navigation over which its attitude changed otherwise than its gyro
    turned (an EKF reset while its output was missing): its gyro integrated over the gap, where no gap in the
    gyro interrupts it, against the attitude's change, beyond config.gap_reset_min_deg plus
    config.gap_reset_scale of the rotation. At the gap's end, where the master's output is back: the slave's
    attitude restarts from it there, not from an attitude interpolated inside the gap."""
    out = []
    imu_gap = _imu_gap_s(tg, config)
    for k in np.flatnonzero(gap):
        i0, i1 = np.searchsorted(tg, [t[k], t[k + 1]])
        if i1 - i0 < 2 or tg[i0] - t[k] > imu_gap or t[k + 1] - tg[i1 - 1] > imu_gap:
            continue
        if np.any(np.diff(tg[i0:i1]) > imu_gap):
            continue
        rv, _, _ = body_increments(tg[i0:i1], g[i0:i1], np.zeros((i1 - i0, 3)))
        dq = compose_segments(rv, np.zeros_like(rv), np.array([0]), np.array([len(rv)]))[0]
        turned = float(np.linalg.norm(rotvec_from_quat(dq)[0]))
        q_gyro = quat_mul(quat[k:k + 1], dq)  # the attitude at the gap's end the gyro says (earth rate aside)
        off = float(np.linalg.norm(rotvec_from_quat(quat_mul(quat_conj(q_gyro), quat[k + 1:k + 2]))[0]))
        if off > np.radians(config.gap_reset_min_deg) + config.gap_reset_scale * turned:
            out.append(t[k + 1])
    return np.asarray(out, float)


def _interp_cols(t: np.ndarray, tp: np.ndarray, yp: np.ndarray) -> np.ndarray:
    """Each column of ``yp`` (n, k), sampled at ``tp``, linearly interpolated at ``t`` (clamped at the ends)."""
    return np.stack([np.interp(t, tp, yp[:, i]) for i in range(yp.shape[1])], -1)


def _span_indices(n: int, k: int, gap: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(i - k, i + k) for the samples i of a series of n, clipped to its ends and, where ``gap`` (n-1,) marks
    steps that are gaps, to the stretch between gaps that holds i."""
    idx = np.arange(n)
    if gap is None or not gap.any():
        return np.clip(idx - k, 0, n - 1), np.clip(idx + k, 0, n - 1)
    cut = np.nonzero(gap)[0]
    stretch = np.concatenate([[0], np.cumsum(gap)])
    first = np.concatenate([[0], cut + 1])[stretch]
    last = np.concatenate([cut, [n - 1]])[stretch]
    return np.maximum(idx - k, first), np.minimum(idx + k, last)


def _derivative(t: np.ndarray, y: np.ndarray, span_s: float, gap: np.ndarray | None = None) -> np.ndarray:
    """Central difference over ~span_s (noise-tolerant), one-sided at the ends and at gaps (``gap``: the
    steps that are gaps, :func:`_nav_gaps`)."""
    i0, i1 = _span_indices(len(t), max(int(round(0.5 * span_s / median_step_s(t))), 1), gap)
    return by_rows(lambda j0, j1: (y[j1] - y[j0]) / np.maximum(t[j1] - t[j0], 1e-9)[:, None], i0, i1)


def _check_motion(gyro: np.ndarray, accel: np.ndarray, src: str) -> None:
    if np.ptp(gyro, axis=0).max() < 1e-9 and np.ptp(accel, axis=0).max() < 1e-9:
        raise AnalysisError(f"{src}: no motion: the slave's IMU readings are constant over the overlap")


@dataclass(frozen=True)
class RateGrid:
    """The two units' angular rates on one grid of slave times (``AlignmentConfig.rate_grid_s``), the master's
    ``tau0`` earlier: what the coarse mounting fits and the gyro-bias seed averages, interpolated once."""

    t_s: np.ndarray
    w_s: np.ndarray  # the slave's gyro
    #: the master's gyro, else its attitude's rate (relative to NED: no earth rate in it); None: neither
    w_m: np.ndarray | None
    inertial: bool  # w_m is the master's gyro
    n_master: int  # the master's finite gyro samples behind w_m (0 where it is the attitude's rate)


def _rates_on_grid(master: InsLog, ms: MasterSeries, t_imu: np.ndarray, gyro: np.ndarray, tau0: float,
                   config: AlignmentConfig = CONFIG) -> RateGrid:
    """The grid's times inside a gap of either unit's rates are left out: interpolated across one, a rate is
    a straight line where the other unit turned (an aircraft whose master's IMU and navigation stopped for
    15 s of 90: a gyro-bias seed of -200/-140/13 deg/h for a true 1/-1/1, the filter's yaw 0.24 arcmin off at
    a sigma of 0.013; tests/test_alignment.py, the master-gap test)."""
    grid = np.arange(t_imu[0], t_imu[-1], config.rate_grid_s)
    gap = _in_gap(grid, t_imu, _imu_gaps(t_imu, config))
    w_m, n_master, tm = None, 0, None
    if master.has_gyro:
        tm, gm = master.t_imu_s(), master.gyro_rad_s()
        okm = np.isfinite(gm).all(1)
        n_master = int(okm.sum())
        tm, gm = tm[okm], gm[okm]
        gap |= _in_gap(grid - tau0, tm, _imu_gaps(tm, config))
    elif ms.w_nm_m is not None:  # (the attitude's rate, at the navigation stamps)
        gap |= _in_gap(grid - tau0, ms.t_s, ms.gap)
    grid = grid[~gap]
    if tm is not None:
        w_m = _interp_cols(grid - tau0, tm, gm) if len(grid) else np.zeros((0, 3))
    elif ms.w_nm_m is not None:
        w_m = _interp_cols(grid - tau0, ms.w_stamps_s, ms.w_nm_m)
    return RateGrid(grid, _interp_cols(grid, t_imu, gyro), w_m, master.has_gyro, n_master)


def _imu_gap_s(stamps: np.ndarray, config: AlignmentConfig = CONFIG) -> float:
    """A step of IMU stamps beyond this is a gap (config.imu_gap_s, config.imu_gap_periods)."""
    return max(config.imu_gap_s, config.imu_gap_periods * median_step_s(stamps))


def _imu_gaps(stamps: np.ndarray, config: AlignmentConfig = CONFIG) -> np.ndarray:
    """(n-1,) True at the steps of IMU stamps beyond :func:`_imu_gap_s`; empty with fewer than two stamps."""
    return np.diff(stamps) > _imu_gap_s(stamps, config) if len(stamps) >= 2 else np.zeros(0, bool)


def _in_gap(t: np.ndarray, stamps: np.ndarray, gap_steps: np.ndarray) -> np.ndarray:
    """True at the times ``t`` that fall inside a step of ``stamps`` marked in ``gap_steps`` (len - 1) or
    outside the stamps' span (where an interpolation holds the end value)."""
    if len(stamps) < 2:
        return np.ones(len(t), bool)
    return (gap_steps[np.clip(np.searchsorted(stamps, t), 1, len(stamps) - 1) - 1]
            | (t < stamps[0]) | (t > stamps[-1]))


def _coarse_mounting(master: InsLog, slave: InsLog, ms: MasterSeries, rates: RateGrid, t_imu: np.ndarray,
                     tau0: float, accel: np.ndarray | None = None, config: AlignmentConfig = CONFIG
                     ) -> CoarseMounting:
    """Wahba/Kabsch on angular rates (``rates``): min sum |w_s - R w_m|^2 by SVD of sum w_s w_m^T. Where the
    rates turn about one axis only, the specific forces' motion joins them (``accel``: the slave's, at t_imu);
    then the slave's own attitude; then that joint fit however weakly it is determined (not ok: a wider
    prior); else the identity (not ok). A fit comes with its error covariance and its sensitivity to the
    accelerometer triad's misalignment (:func:`_wahba_covariance`)."""
    grid, w_m = rates.t_s, rates.w_m
    weak = None  # a joint rate + specific-force start that is only weakly determined

    if w_m is not None and len(grid) > 2:
        w_s = rates.w_s
        # remove slow parts (biases, earth rate) so the fit sees the motion
        w_s = w_s - w_s.mean(0)
        w_m = w_m - w_m.mean(0)
        b = w_s.T @ w_m
        sv = np.linalg.svd(b, compute_uv=False)
        motion = np.sqrt(sv / max(len(grid), 1))  # rms rate on the principal axes
        if sv[0] > 0 and motion[1] > 2e-3 and sv[1] / sv[0] > 1e-3:
            r = wahba(b)[0]
            return CoarseMounting(r, True, "", *_wahba_covariance(r, [(1.0, w_m, w_s, False)]))
        why = "coarse mounting: too little rotation about two axes for the rate fit"
        # a car turning on a level road rotates about one axis: its accelerations (speed changes along the
        # track, centripetal across it) give another direction, and two fix a rotation. Rates and specific
        # forces (motion parts, each set normalised by its power) in one Wahba problem
        f_m = _master_specific_force(master, ms, grid - tau0) if config.coarse_joint and accel is not None else None
        if f_m is not None:
            f_s = _interp_cols(grid, t_imu, accel)
            f_m, f_s = f_m - f_m.mean(0), f_s - f_s.mean(0)
            pw, pf = float(np.trace(w_m.T @ w_m)), float(np.trace(f_m.T @ f_m))
            bf = f_s.T @ f_m
            motion_f = np.sqrt(np.linalg.svd(bf, compute_uv=False) / max(len(grid), 1))  # m/s^2 rms
            # two directions of real motion, not noise: the rates' first and the specific forces' first, or
            # the specific forces' first two (whether they differ, the joint fit's singular values say)
            f_min = config.coarse_min_force_m_s2
            real = motion_f[0] > f_min and (motion[0] > 2e-3 or motion_f[1] > f_min)
            if real and pw > 0 and pf > 0:
                B = b / pw + bf / pf
                svj = np.linalg.svd(B, compute_uv=False)
                r = wahba(B)[0]
                cov, d_f = _wahba_covariance(r, [(1.0 / pw, w_m, w_s, False), (1.0 / pf, f_m, f_s, True)])
                if svj[1] / svj[0] >= config.coarse_joint_ratio:
                    return CoarseMounting(r, True, why + "; rates and specific forces together instead", cov, d_f)
                weak = CoarseMounting(r, False, why + "; rates and specific forces together, weakly determined "
                                      "(wider prior)", cov, d_f)
    elif w_m is None:
        why = "coarse mounting: the master has no angular rate or attitude"
    else:
        why = "coarse mounting: no stretch where both units' rates are logged (gaps)"
    if slave.has_quat and ms.quat is not None:
        ts, qs = slave.quat_wxyz()
        qm = _interp_cols(ts - tau0, ms.t_s, ms.quat)
        inside = (ts - tau0 >= ms.t_s[0]) & (ts - tau0 <= ms.t_s[-1])
        if inside.sum() >= 1:
            m = np.einsum("kji,kjl->il", dcm_from_quat(qs[inside]), dcm_from_quat(qm[inside]))  # sum C_sn C_nm
            return CoarseMounting(wahba(m)[0], True, why + "; used the slave's own attitude instead")
    if weak is not None:
        return weak
    return CoarseMounting(np.eye(3), False, why + "; started from a zero mounting")


def _wahba_covariance(r: np.ndarray, parts: list[tuple[float, np.ndarray, np.ndarray, bool]]
                      ) -> tuple[np.ndarray, np.ndarray]:
    """(covariance, d mu / d alpha) of the error mu (s frame; R = (I - [mu x]) R_hat) of the weighted Wahba
    fit R_hat = argmin sum_j a_j sum_k |y_jk - R x_jk|^2, from its residuals. ``parts``: (a_j, x_j master,
    y_j slave, is_specific_force), each (n, 3); rad^2.

    Linearised, y - R_hat x = [u x] mu + noise with u = R_hat x: mu = H^-1 sum_j a_j sum_k [u x]^T r_k,
    H = sum_j a_j sum_k K(u_k), K(u) = |u|^2 I - u u^T. With residuals of variance s_j^2 per axis,
    correlated over tau_j samples (:func:`_correlation_time`: a smooth motion's residuals carry fewer
    independent samples than grid points), Cov = H^-1 S H^-1, S = sum_j a_j^2 s_j^2 tau_j sum_k K(u_k).
    A misaligned accelerometer triad, f_s = (I + [alpha x]) R f_m, is no noise: it moves mu by
    H^-1 A_f alpha (A_f the specific forces' part of H), the second value."""
    h = np.zeros((3, 3))
    s = np.zeros((3, 3))
    a_f = np.zeros((3, 3))
    for a, x, y, force in parts:
        u = x @ r.T
        k = np.sum(u * u) * np.eye(3) - u.T @ u
        res = y - u
        h += a * k
        s += a * a * float(np.mean(res * res)) * _correlation_time(res) * k
        if force:
            a_f += a * k
    try:
        h_inv = np.linalg.inv(h)
    except np.linalg.LinAlgError:
        return np.diag(np.full(3, np.inf)), np.zeros((3, 3))
    return h_inv @ s @ h_inv, h_inv @ a_f


def _mounting_prior(coarse: CoarseMounting, c_ns0: np.ndarray, opts: AlignmentOptions, config: AlignmentConfig,
                    notes: list[str]) -> MountingPrior:
    """The prior of the coarse start's error (:class:`MountingPrior`). The option where given; else
    config.mounting_prior_deg per axis after a good start (config.mounting_prior_weak_deg after a weak one),
    widened to what the coarse fit's own covariance says (at most config.mounting_prior_max_deg per axis):
    a start that took an axis from noisy specific forces can be degrees off, and an axis the motion then
    leaves undetermined keeps its prior. With board_errors the fit's sensitivity to the accelerometer
    triad's misalignment joins it, as a covariance with that state."""
    z = np.zeros((3, 3))
    if opts.mounting_sigma_deg is not None:
        return MountingPrior(np.eye(3) * (float(opts.mounting_sigma_deg) * DEG) ** 2, z, c_ns0)
    base = (config.mounting_prior_deg if coarse.ok else config.mounting_prior_weak_deg) * DEG
    cov = coarse.cov
    if not (config.mounting_prior_from_fit and cov is not None and np.all(np.isfinite(cov))):
        return MountingPrior(np.eye(3) * base**2, z, c_ns0)
    s_a = _accel_misalign_sigma_rad(opts, config) if opts.board_errors else 0.0
    # a weak start's sensitivity is no linearisation to trust (its H is nearly singular); its wide prior
    # stands alone
    d = coarse.d_force if (coarse.ok and coarse.d_force is not None) else z
    cov = 0.5 * (cov + cov.T) + s_a**2 * (d @ d.T)
    # the floor in every direction (eigenvalues raised to it: where none exceeds it, exactly the isotropic
    # prior of a fit without a covariance); the cap scales an axis (and its covariances)
    lam, vec = np.linalg.eigh(cov)
    cov = np.eye(3) * base**2 if lam.max() <= base**2 else (vec * np.maximum(lam, base**2)) @ vec.T
    sig = np.sqrt(np.diag(cov))
    hi = max(config.mounting_prior_max_deg * DEG, base)
    sc = np.minimum(1.0, hi / sig)
    cov = sc[:, None] * cov * sc[None, :]
    cross = s_a**2 * (sc[:, None] * d)  # Cov(mu, alpha) = d Cov(alpha)
    sig = sig * sc
    if np.any(sig > base * 1.001):
        notes.append(f"mounting prior widened to {_fmt3(np.degrees(sig))} deg (slave x/y/z) by the coarse "
                     f"fit's own covariance (from {base / DEG:g} deg)")
    return MountingPrior(cov, cross, c_ns0)


def _board_prior_cov(lay: StateLayout, sig: np.ndarray, prior: MountingPrior, start_att_rad: float) -> np.ndarray:
    """The initial covariance with the board's states: diag(sig^2) with the covariance between the coarse
    start's error and the accelerometer triad's misalignment alpha (:class:`MountingPrior`): on the mounting
    state where the filter carries one, else on the slave's initial attitude (velocity matching: the
    mounting is the attitude's, phi0 = C_ns0 mu0).

    The slave's initial attitude stays independent of the mounting state, though it starts from the master
    through R0 (phi0 = C_ns0 mu0 - eta0 to first order). Tied so, the filter trusts the start to the master's
    attitude error (0.1 deg): on the ArduPlane box_pilot EKF3 pair, whose navigation frame is 6 deg from its
    IMU's (the rate fit's start), the first pass diverged (NIS 1e8); independent, it does not. Where the
    filter carries the mounting, that attitude's prior also takes ``start_att_rad`` per axis (the master's
    output frame off its IMU's: AlignmentConfig.board_start_att_deg), so that the attitude matching does
    not lend the mounting information the motion does not hold."""
    p = np.diag(sig**2)
    c = prior.c_ns0
    pm, pma = prior.mount_cov, prior.mount_alpha_cov
    if lay.mount is not None:
        p[lay.att, lay.att] += np.eye(3) * start_att_rad**2
        p[lay.mount, lay.mount] = pm
        if lay.accel_mis is not None:
            p[lay.mount, lay.accel_mis] = pma
            p[lay.accel_mis, lay.mount] = pma.T
    elif lay.accel_mis is not None:
        p[lay.att, lay.att] = c @ pm @ c.T
        p[lay.att, lay.accel_mis] = c @ pma
        p[lay.accel_mis, lay.att] = (c @ pma).T
    return p


def _master_specific_force(master: InsLog, ms: MasterSeries, t: np.ndarray) -> np.ndarray | None:
    """The master's specific force (m/s^2, master body frame) at t: its accelerometers where it logs them,
    else from its navigation solution (an INS logging only its output), C_bn (dv/dt - g_n), the small
    Coriolis and transport terms left out (a coarse start). None without either."""
    if master.has_accel:
        ta, fa = master.t_imu_s(), master.accel_m_s2()
        ok = np.isfinite(fa).all(1)
        if ok.sum() >= 2:
            return _interp_cols(t, ta[ok], fa[ok])
    if ms.acc is None or ms.quat is None:
        return None
    ok = np.isfinite(ms.acc).all(1) & np.isfinite(ms.quat).all(1)
    if ok.sum() < 2:
        return None
    a_n = _interp_cols(t, ms.t_s[ok], ms.acc[ok])
    q = _interp_cols(t, ms.t_s[ok], ms.quat[ok])
    f_n = a_n - np.array([0.0, 0.0, G0_M_S2])
    return np.einsum("kji,kj->ki", dcm_from_quat(q / np.linalg.norm(q, axis=1, keepdims=True)), f_n)


def _coarse_delay(master: InsLog, ms: MasterSeries, t_imu: np.ndarray, gyro: np.ndarray, max_s: float,
                  config: AlignmentConfig = CONFIG) -> tuple[float, str]:
    """(tau0, note): the lag (slave stamp - master stamp) minimising the mismatch of the angular-rate
    MAGNITUDES (independent of the mounting), coarse (10 ms) then fine (1 ms); times inside a gap of
    either unit's rates left out (a car's master stopped for 15 s of 90: 122 ms for 80)."""
    if master.has_gyro:
        tm, gm = master.t_imu_s(), master.gyro_rad_s()
        okm = np.isfinite(gm).all(1)
        tm, wm = tm[okm], np.linalg.norm(gm[okm], axis=1)
        gap_m = _imu_gaps(tm, config)
    elif ms.w_nm_m is not None:
        tm, wm = ms.w_stamps_s, np.linalg.norm(ms.w_nm_m, axis=1)
        gap_m = _nav_gaps(tm, config)
    else:
        return 0.0, "delay state started at 0 (the master has no angular rate or attitude)"
    ws = np.linalg.norm(gyro, axis=1)
    lo, hi = max(t_imu[0], tm[0] + max_s), min(t_imu[-1], tm[-1] - max_s)
    if hi - lo < 2.0 or np.std(ws) < 1e-3:
        return 0.0, "delay state started at 0 (too little motion or overlap for a coarse delay)"
    gap_s = _imu_gaps(t_imu, config)

    def cost(lags: np.ndarray, step: float) -> np.ndarray:
        grid = np.arange(lo, hi, step)
        s_w = np.interp(grid, t_imu, ws)
        if not (gap_m.any() or gap_s.any()):
            return np.array([np.mean((s_w - np.interp(grid - lag, tm, wm)) ** 2) for lag in lags])
        out_s = _in_gap(grid, t_imu, gap_s)

        def one(lag: float) -> float:
            ok = ~(out_s | _in_gap(grid - lag, tm, gap_m))
            return float(np.mean((s_w[ok] - np.interp(grid[ok] - lag, tm, wm)) ** 2)) if ok.any() else np.inf
        return np.array([one(lag) for lag in lags])

    lags = np.arange(-max_s, max_s + 1e-9, 0.01)
    best = lags[int(np.argmin(cost(lags, 0.01)))]
    fine = np.arange(best - 0.015, best + 0.015 + 1e-9, 0.001)
    tau0 = float(fine[int(np.argmin(cost(fine, 0.0025)))])
    return tau0, f"delay state started at {tau0 * 1e3:+.0f} ms (angular-rate magnitudes)"


def _initial_position(master: InsLog, slave: InsLog, t0: float, opts: AlignmentOptions, notes: list[str]
                      ) -> np.ndarray:
    for log in (master, slave):
        if log.has_pos:
            tp, p = log.lat_lon_alt()
            i = int(np.clip(np.searchsorted(tp, t0), 0, len(tp) - 1))
            return np.array([np.radians(p[i, 0]), np.radians(p[i, 1]), p[i, 2]])
    lat = float(opts.lat_deg if opts.lat_deg is not None else 45.0)
    notes.append(f"no position in either log: latitude {lat:g} deg assumed (earth rate, gravity)")
    return np.array([np.radians(lat), 0.0, 0.0])


# ---- noise and priors -----------------------------------------------------------------------------
def _hf_sigma(y: np.ndarray) -> float:
    """White-noise sigma from third differences (robust: MAD); smooth motion cancels."""
    if len(y) < 8:
        return 0.0
    return d3_sigma(np.diff(y, n=3, axis=0))


class SlaveNoise:
    """The slave IMU's white noise (:func:`_hf_sigma` of its gyros, rad/s, and of its accelerometers,
    m/s^2) and its sample step (s), measured once per alignment run, when made (the samples are not held):
    the prior, the seed and every filter pass's settings read them (each is a median over the whole
    overlap). ``accel_without_lever``: the accelerometers' measured without the lever arm's acceleration
    (``noise.accel_noise_without_lever``; None where it could not be), the smaller taken: a rigid-body
    vibration's w' x r is motion the filter models."""

    def __init__(self, t_imu: np.ndarray, gyro: np.ndarray, accel: np.ndarray,
                 accel_without_lever: float | None = None):
        self.dt_s = median_step_s(t_imu)
        self.gyro = _hf_sigma(gyro)
        own = _hf_sigma(accel)
        self.accel = own if accel_without_lever is None else min(own, accel_without_lever)


def _arw_rad_s(opts: AlignmentOptions, noise: SlaveNoise) -> float:
    """The slave gyro's angle random walk (rad/sqrt(s)): the option, else from the data (with a floor)."""
    if opts.gyro_arw_dpsh is not None:
        return float(opts.gyro_arw_dpsh) * DEG / 60.0
    return max(noise.gyro * np.sqrt(noise.dt_s), 0.002 * DEG / 60.0)


def _gyro_bias_prior(opts: AlignmentOptions, noise: SlaveNoise) -> float:
    """The gyro bias's prior sigma (rad/s) from the sensor grade its noise reveals (navigation grade ~0.002
    deg/rt-h, MEMS ~0.2-1 deg/rt-h: 300 x ARW, 2..2000 deg/h); the option overrides."""
    arw_dpsh = _arw_rad_s(opts, noise) / (DEG / 60.0)
    return float(_given(opts.gyro_bias_sigma_dph, np.clip(300.0 * arw_dpsh, 2.0, 2000.0))) * DEG_PER_H


def _gyro_bias_seed(master: InsLog, ms: MasterSeries, rates: RateGrid, tau0: float, r0: np.ndarray,
                    prior_rad_s: float, config: AlignmentConfig, notes: list[str]) -> GyroBiasSeed:
    """The slave's gyro bias measured as the mean of w_s - R0 w_m over the overlap (w_m the master's inertial
    rate: its gyro, else its attitude's rate plus the earth rate; R0 the coarse mounting, fitted on the rates'
    motion parts, so the means are what it leaves), with its uncertainty: the residuals' variance over their
    independent samples (their correlation time) and a gyro scale-factor error on the mean rate
    (config.gyro_bias_seed_scale_factor). Applied where it exceeds config.gyro_bias_seed_sigmas x both the
    sensor grade's prior and its own uncertainty on some axis: a MEMS turn-on bias of 1 deg/s against a 2 deg/h
    prior was a prior outlier the filter could not reach, and the mounting and lever arm absorbed it
    (docs/alignment.md, "A large gyro bias")."""
    none = GyroBiasSeed(np.zeros(3), np.full(3, np.inf))
    if not config.gyro_bias_seed:
        return none
    grid, w_m, w_s = rates.t_s, rates.w_m, rates.w_s
    if len(grid) < 20 or w_m is None:
        return none
    if rates.inertial:
        if rates.n_master < 2:
            return none
    elif ms.quat is not None:
        # the attitude's rate is relative to NED: the gyros also sense the earth's rate (transport rate left out)
        lat = np.radians(master.lat_lon_alt()[1][0, 0]) if master.has_pos else np.radians(45.0)
        q = _interp_cols(grid - tau0, ms.t_s, ms.quat)
        c_nm = dcm_from_quat(q / np.linalg.norm(q, axis=1, keepdims=True))
        w_m = w_m + np.einsum("kji,j->ki", c_nm, earth.earth_rate_ned(lat))
    else:
        return none
    ok = np.isfinite(w_m).all(1) & np.isfinite(w_s).all(1)
    if ok.sum() < 20:
        return none
    u = w_m[ok] @ r0.T
    b = w_s[ok].mean(0) - u.mean(0)
    res = w_s[ok] - u - b
    n = len(res)
    tau = np.minimum(_correlation_times(res), n / 10.0) if np.all(np.ptp(res, axis=0) > 0) else np.full(3, n / 10.0)
    sig = np.sqrt(np.mean(res * res, axis=0) * np.maximum(tau, 1.0) / n
                  + (config.gyro_bias_seed_scale_factor * u.mean(0)) ** 2)
    k = config.gyro_bias_seed_sigmas
    if not (np.all(np.isfinite(b)) and np.any((np.abs(b) > k * prior_rad_s) & (np.abs(b) > k * sig))):
        return GyroBiasSeed(b, sig)
    prior = np.sqrt(prior_rad_s**2 + sig**2)
    notes.append(f"slave gyro bias measured before the filter (mean rate difference): {_fmt3(b / DEG_PER_H)} deg/h "
                 f"(x/y/z), beyond {k:g} x its prior of {prior_rad_s / DEG_PER_H:.3g} deg/h: the filter starts from it, "
                 f"prior {_fmt3(prior / DEG_PER_H)} deg/h")
    return GyroBiasSeed(b, sig, True, prior)


def _settings(kind: FilterKind, lay: StateLayout, master: InsLog, noise: SlaveNoise, opts: AlignmentOptions,
              config: AlignmentConfig, prior: MountingPrior, dt_upd: float, tau0: float, tau_bounds: tuple[float, float],
              smoother: bool, gyro_prior: np.ndarray | None = None) -> tuple[FilterSettings, np.ndarray]:
    """The filter settings and prior sigmas: noise densities, priors and measurement noise from the
    options, else from the data (with floors). ``gyro_prior``: the gyro-bias states' prior sigma (rad/s)
    where the bias was seeded, else the sensor grade's."""
    dt_imu = noise.dt_s
    # slave noise densities from the data (sample sigma * sqrt(dt)), with floors
    arw = _arw_rad_s(opts, noise)
    if opts.accel_vrw_ug_psh is not None:
        vrw = float(opts.accel_vrw_ug_psh) * UG
    else:
        vrw = max(noise.accel * np.sqrt(dt_imu), 5.0 * UG)
    vrw_ug = vrw / UG
    # bias priors from the sensor grade its noise reveals (navigation grade ~0.002 deg/rt-h, 20 ug/rt-Hz;
    # MEMS ~0.2-1 deg/rt-h, 150-400 ug/rt-Hz); options override
    sg_gyro = _gyro_bias_prior(opts, noise)
    sg_acc = float(_given(opts.accel_bias_sigma_mg,
                          np.clip(0.01 * vrw_ug * max(1.0, vrw_ug / 50.0), 0.1, 50.0))) * MG
    # measurement noise from the master's data, with floors
    if opts.r_att_arcsec is not None:
        r_att = float(opts.r_att_arcsec) * ARCSEC
    elif (att_noise := _master_attitude_noise(master, config)) is not None:
        r_att = max(att_noise, config.r_att_floor_arcsec * ARCSEC)
    else:
        r_att = 10.0 * ARCSEC
    if opts.r_vel_m_s is not None:
        r_vel = float(opts.r_vel_m_s)
    elif (vel_noise := _master_velocity_noise(master, config)) is not None:
        r_vel = max(vel_noise, config.r_vel_floor_m_s)
    else:
        r_vel = 0.01
    n = lay.n
    sig = np.zeros(n)
    qc = np.zeros(n)
    s_mount, s_att = prior.sigmas()
    sig[lay.att] = s_att
    qc[lay.att] = arw**2
    # a seeded bias (GyroBiasSeed): the prior covers the seed's error; the bias instability stays the grade's
    sig[lay.gyro] = sg_gyro if gyro_prior is None else gyro_prior
    qc[lay.gyro] = (0.01 * sg_gyro) ** 2 / 3600.0
    if lay.vel is not None:
        sig[lay.vel] = 0.1
        qc[lay.vel] = vrw**2
        sig[lay.accel] = sg_acc
        qc[lay.accel] = (0.01 * sg_acc) ** 2 / 3600.0
    if lay.mount is not None:
        sig[lay.mount] = s_mount
    # flexure="auto" starts from config.flex_auto_* (seed 000's model) where the options give none
    auto = opts.flexure_auto
    beta = float(_given(opts.flex_beta, config.flex_auto_beta_1_s if auto else 0.5))
    if lay.flex_ang is not None:
        s_l = np.broadcast_to(np.asarray(_given(opts.flex_sigma_deg, config.flex_auto_sigma_deg if auto else 0.05),
                                         float), (3,)) * DEG
        sig[lay.flex_ang] = s_l
        sig[lay.flex_rate] = s_l * beta
        qc[lay.flex_rate] = 4.0 * beta**3 * s_l**2
    if lay.lever is not None:
        sig[lay.lever] = float(_given(opts.lever_arm_sigma_m, config.lever_arm_sigma_m))
    mk_tau = float(_given(opts.master_att_err_tau_s, config.master_att_err_tau_s))
    if lay.master_att is not None:  # first-order Markov: stationary sigma, qc = 2 sigma^2 / tau
        s_m = float(_given(opts.master_att_err_deg, config.master_att_err_deg)) * DEG
        sig[lay.master_att] = s_m
        qc[lay.master_att] = 2.0 * s_m**2 / mk_tau
    if lay.accel_mis is not None:
        sig[lay.accel_mis] = _accel_misalign_sigma_rad(opts, config)
    if lay.delay is not None:
        if kind.splits_delay:
            sig[lay.delay] = dt_upd / np.sqrt(3.0)
        else:
            sig[lay.delay] = float(_given(opts.delay_sigma_s, 0.1))
    p0_cov = None
    if lay.has_board_states:
        p0_cov = _board_prior_cov(lay, sig, prior, config.board_start_att_deg * DEG)
        sig = np.sqrt(np.diag(p0_cov))
    st = FilterSettings(kind=kind, layout=lay, p0_sigma=sig, p0_cov=p0_cov, qc=qc, r_vel_m_s=r_vel, r_att_rad=r_att,
                        flex_beta=beta, master_att_tau_s=mk_tau, delay_bounds_s=tau_bounds,
                        hinf_gamma=float(opts.hinf_gamma), smoother=smoother, att_only_fej=config.att_only_fej,
                        dynamics_fej=config.dynamics_fej)
    return st, sig


def _given(value, default):
    """An option's value where given (not None), else its default."""
    return default if value is None else value


def _accel_misalign_sigma_rad(opts: AlignmentOptions, config: AlignmentConfig) -> float:
    """The accelerometer triad misalignment's prior sigma per axis (rad): the option, else the configuration's
    (the state's prior and the coarse start's sensitivity to it share it)."""
    return float(_given(opts.accel_misalign_sigma_deg, config.accel_misalign_sigma_deg)) * DEG


def _run_bytes(run: FilterRun) -> int:
    """The memory a pass's histories hold."""
    return sum(v.nbytes for v in vars(run).values() if isinstance(v, np.ndarray))


def _mean_nis(run: FilterRun) -> float:
    v = run.nis[np.isfinite(run.nis)]
    return float(np.mean(v[len(v) // 10:])) if len(v) else float("nan")


def _recalibrated(run: FilterRun, lay: StateLayout, st: FilterSettings, opts: AlignmentOptions,
                  config: AlignmentConfig = CONFIG) -> FilterSettings | None:
    """Settings with the measurement noise from the residual RMS when the mean NIS exceeds 3 x dof (raised
    to it), or is below config.recalibrate_low_nis_frac of it (lowered to it, not below the floors); where the
    user did not fix the noise."""
    nis = _mean_nis(run)
    high = nis > 3.0 * lay.n_meas
    if not (high or nis < config.recalibrate_low_nis_frac * lay.n_meas):
        return None
    e = run.innov[np.isfinite(run.innov).all(1)]
    e = e[len(e) // 10:]
    if not len(e):
        return None
    r_vel, r_att = st.r_vel_m_s, st.r_att_rad

    def moved(r: float, rms: float, floor: float) -> float:
        return max(r, rms) if high else min(r, max(rms, floor))

    col = 0
    if lay.uses_vel:
        if opts.r_vel_m_s is None:
            r_vel = moved(r_vel, float(np.sqrt(np.mean(e[:, :3] ** 2))), config.r_vel_floor_m_s)
        col = 3
    if lay.uses_att and opts.r_att_arcsec is None:
        r_att = moved(r_att, float(np.sqrt(np.mean(e[:, col:col + 3] ** 2))), config.r_att_floor_arcsec * ARCSEC)
    if r_vel == st.r_vel_m_s and r_att == st.r_att_rad:
        return None
    return replace(st, r_vel_m_s=r_vel, r_att_rad=r_att)


# ---- result ---------------------------------------------------------------------------------------
def _euler_jacobian(r: np.ndarray) -> np.ndarray:
    """d euler(exp(-[mu x]) R) / d mu at mu = 0 (central differences)."""
    j = np.zeros((3, 3))
    e = 1e-6
    for i in range(3):
        d = np.zeros(3)
        d[i] = e
        a = euler_from_dcm(exp_so3(-d) @ r)
        b = euler_from_dcm(exp_so3(d) @ r)
        diff = a - b
        diff = (diff + np.pi) % (2 * np.pi) - np.pi
        j[:, i] = diff / (2 * e)
    return j


def _result(run: FilterRun, lay: StateLayout, st: FilterSettings, sig0: np.ndarray, kind: FilterKind, match: str,
            opts: AlignmentOptions, config: AlignmentConfig, notes: list[str]) -> AlignmentResult:
    """The AlignmentResult of the final pass: the values at the last epoch (the smoother's: the middle),
    the sigmas scaled by the a-posteriori variance factor, the notes in the order of the steps."""
    ne = len(run.t_s)
    k_rep = ne // 2 if run.smoothed else ne - 1
    # a-posteriori variance factor: when the residuals exceed the noise model (mean NIS > dof), the
    # reported sigmas are scaled by sqrt(NIS/dof) (the filter's own histories are left as they are)
    nis_m = _mean_nis(run)
    sig_scale = float(np.sqrt(max(1.0, nis_m / lay.n_meas))) if np.isfinite(nis_m) else 1.0
    if sig_scale > 1.05:
        notes.append(f"reported sigmas scaled by {sig_scale:.2f} = sqrt(mean NIS / dof)")
    corr_min = config.innov_corr_min
    if corr_min is None and lay.has_board_states:
        corr_min = config.board_innov_corr_min
    corr = _innovation_correlation_factor(run) if corr_min is not None else 1.0
    if corr_min is not None and corr > corr_min:
        # the filter takes the master's errors as white; correlated in time (its EKF's attitude error, a
        # Markov process), they carry fewer independent samples than epochs: sigmas widened by
        # sqrt(integrated correlation time in epochs), as the latency's sigma already is
        sig_scale *= float(np.sqrt(corr))
        notes.append(f"reported sigmas widened by {np.sqrt(corr):.2f} = sqrt(the innovations' correlation time, "
                     f"{corr:.1f} epochs): the master's errors are correlated in time")
    mnt = _mounting(run, lay, k_rep, sig_scale, config, notes)
    gb = run.x[k_rep, lay.gyro] / DEG_PER_H
    gbs = sig_scale * np.sqrt(run.p_diag[k_rep, lay.gyro]) / DEG_PER_H
    if lay.accel is not None:
        ab = run.x[k_rep, lay.accel] / MG
        abs_ = sig_scale * np.sqrt(run.p_diag[k_rep, lay.accel]) / MG
    else:
        ab = np.full(3, np.nan)
        abs_ = np.full(3, np.nan)
        notes.append("accelerometer bias not estimated: attitude matching only")
    obs = _observability(run, lay, sig0, k_rep, mnt.sig_axes if mnt.determined else None, config, notes)
    rn, resid, rms = _residual_summary(run, lay, notes)
    if run.n_reinit:
        notes.append(f"the master's attitude jumped {run.n_reinit} time(s) (EKF reset): slave attitude restarted")
    if run.n_skipped:
        notes.append(f"{run.n_skipped} of {ne} updates skipped: the master's output was frozen, jumping or missing")
    # histories, decimated to at most max_history_rows (the last epoch kept)
    step = max(int(np.ceil(ne / int(opts.max_history_rows))), 1)
    rows = np.arange(0, ne, step)
    if rows[-1] != ne - 1:
        rows = np.append(rows, ne - 1)
    names, cols, sigs = _histories(run, lay, mnt.hist_deg, mnt.sig_e, rows)
    lever_m, lever_sig = _lever_arm(run, lay, sig0, k_rep, sig_scale, opts, config, notes)
    delay_s = delay_sig = None
    if lay.delay is not None:
        delay_s = float(run.tau_hat[k_rep])
        delay_sig = float(sig_scale * np.sqrt(run.p_diag[k_rep, lay.delay]))
    if run.smoothed:
        notes.append("RTS smoother: values are the smoothed estimates at the middle of the run")
    if np.isfinite(run.gamma).any():
        g = run.gamma[np.isfinite(run.gamma)]
        notes.append(f"H-infinity gamma: median {np.median(g):.3g}, min {g.min():.3g}")
    return AlignmentResult(
        mounting_quat_wxyz=mnt.quat_wxyz,
        filter=kind.value, match=match, mounting_rpy_deg=mnt.rpy_deg, mounting_sigma_deg=mnt.sigma_deg,
        gyro_bias_dph=tuple(float(x) for x in gb), accel_bias_mg=tuple(float(x) for x in ab),
        converged_s=mnt.converged_s, still_converging=mnt.still_converging, residual_rms=rms,
        gyro_bias_sigma_dph=tuple(float(x) for x in gbs), accel_bias_sigma_mg=tuple(float(x) for x in abs_),
        delay_s=delay_s, delay_sigma_s=delay_sig, lever_arm_m=lever_m, lever_arm_sigma_m=lever_sig,
        observability=obs, notes=tuple(notes), innovation_corr_epochs=_innovation_correlation_times(run),
        history_t_s=run.t_s[rows].copy(), history_names=tuple(names), history_x=cols,
        history_sigma=sigs, residual_t_s=run.t_s[rows].copy(), residual_names=tuple(rn),
        residuals=resid[rows],
    )


@dataclass(frozen=True)
class MountingSummary:
    """The mounting total (coarse mounting combined with the filter's residual) and its history."""

    determined: bool  # False: the master has no attitude
    rpy_deg: tuple[float, float, float]
    sigma_deg: tuple[float, float, float]  # scaled by the a-posteriori variance factor
    sig_e: np.ndarray  # (M+1, 3) rad, unscaled: the history's sigma
    hist_deg: np.ndarray  # (M+1, 3) yaw continuous around the final value
    converged_s: float | None  # from the start, by the forward filter's sigma (config.converged_arcmin)
    #: (3,) rad, unscaled: the rotation's sigma about each reported angle's own axis at the reported epoch
    #: (imu_to_imu.axis_sigmas; defined at the gimbal lock too): what observability is judged on
    sig_axes: np.ndarray | None = None
    quat_wxyz: tuple[float, float, float, float] | None = None  # the mounting's exact rotation
    gimbal: bool = False  # rpy_deg is the canonical triple at the gimbal lock
    still_converging: bool | None = None  # (AlignmentResult.still_converging)


def _innovation_correlation_factor(run: FilterRun) -> float:
    """The median over the innovation channels of their integrated correlation time (epochs, 1 + 2 sum of
    the autocorrelation up to its first zero crossing), at most a tenth of the epochs with an update (1.0
    when too few). The median, not the largest: a channel that carries little of the mounting (the
    attitude's on an agile multirotor) would widen every sigma by its own correlation."""
    inn = run.innov
    if inn is None or inn.ndim != 2:
        return 1.0
    return _correlation_time(inn[np.isfinite(inn).all(axis=1)])


def _innovation_correlation_times(run: FilterRun) -> tuple[float, ...] | None:
    """Each varying innovation channel's integrated correlation time (epochs), at most a tenth of the epochs."""
    inn = run.innov
    if inn is None or inn.ndim != 2:
        return None
    x = inn[np.isfinite(inn).all(axis=1)]
    return tuple(float(min(t, len(x) / 10.0)) for t in _correlation_times(x))


def _correlation_time(x: np.ndarray) -> float:
    """The median over the columns of ``x`` (n, k) of their integrated correlation time (samples, 1 + 2 sum
    of the autocorrelation up to its first zero crossing), at most n / 10; 1.0 for fewer than 20 rows or
    no varying column."""
    taus = _correlation_times(x)
    return float(min(np.median(taus), len(x) / 10.0)) if len(taus) else 1.0


def _correlation_times(x: np.ndarray) -> np.ndarray:
    """Each varying column's integrated correlation time (see _correlation_time; not bounded); empty for
    fewer than 20 rows or no varying column."""
    if x.ndim != 2 or x.shape[0] < 20:
        return np.zeros(0)
    x = x - x.mean(axis=0)
    var = np.sum(x * x, axis=0)
    x = x[:, var > 0]
    if x.shape[1] == 0:
        return np.zeros(0)
    n = len(x)
    nfft = 1 << int(np.ceil(np.log2(2 * n)))
    tot = np.sum(x * x, axis=0)
    taus = []
    for c in range(x.shape[1]):  # over the (at most 6) channels, one spectrum at a time: the same transforms
        f = np.fft.rfft(x[:, c], nfft)  # as all columns' at once, a sixth of their memory (4 h: 0.1 GB)
        ac = np.fft.irfft(f * np.conj(f), nfft)[:n] / tot[c]
        del f
        neg = np.nonzero(ac[1:] <= 0)[0]
        m = int(neg[0]) if len(neg) else n - 1
        taus.append(1.0 + 2.0 * float(np.sum(ac[1:m + 1])))
    return np.asarray(taus)


def _mounting(run: FilterRun, lay: StateLayout, k_rep: int, sig_scale: float, config: AlignmentConfig,
              notes: list[str]) -> MountingSummary:
    ne = len(run.t_s)
    if lay.mount is not None:
        r_ep = run.r_hat
    elif run.c_nm is not None:
        r_ep = np.einsum("kji,kjl->kil", run.c_ns, run.c_nm)  # C_sn C_nm
    else:
        notes.append("mounting not determined: the master has no attitude")
        nan3 = (float("nan"),) * 3
        return MountingSummary(False, nan3, nan3, np.full((ne, 3), np.nan), np.full((ne, 3), np.nan), None)
    if lay.mount is None:  # velocity matching: average the last tenth (master attitude noise) ...
        # ... of the epochs with an update: at the others the master's attitude is interpolated across a gap
        # (a 5 Hz master's 1.8 s gap near a log's end put an aircraft's roll 0.9 arcmin off, 6.7 sigma)
        n_avg = max(ne // 10, 1) + 1
        upd = np.flatnonzero(np.isfinite(run.nis[:k_rep + 1]))
        last = upd[-n_avg:] if len(upd) else np.arange(max(k_rep + 1 - n_avg, 0), k_rep + 1)
        r_fin = wahba(r_ep[last].sum(0))[0]  # their mean rotation
    else:
        r_fin = r_ep[k_rep]
    quat = tuple(float(x) for x in quat_from_dcm(r_fin))
    p_fwd = run.p_mount_fwd if run.p_mount_fwd is not None else run.p_mount
    snap_min = config.gimbal_snap_min_deg * DEG
    gimbal, rpy_g, sig_g, delta = gimbal_canonical(r_fin, sig_scale ** 2 * run.p_mount[k_rep],
                                                   config.gimbal_snap_sigmas, snap_min)
    if gimbal:
        # the gimbal lock: the Euler angles' Jacobian is singular (roll and yaw turn about one axis), the
        # rotation is not; the canonical triple with the rotation's sigmas (imu_to_imu.gimbal_canonical), the
        # history in the same convention where it is at the lock too
        rpy = rpy_g
        mount_sig = tuple(float(x) for x in np.degrees(sig_g))

        def lock_sigmas(p: np.ndarray) -> np.ndarray:  # the canonical triple's sigmas, the snap left out
            s_z = np.sqrt(np.maximum(p[:, 2, 2], 0.0))
            return np.stack([s_z, np.sqrt(np.maximum(p[:, 0, 0] + p[:, 1, 1], 0.0)), s_z], axis=1)

        sig_e = lock_sigmas(run.p_mount)
        snap_k, rpy_k, _, _ = gimbal_canonical(r_ep, run.p_mount, config.gimbal_snap_sigmas, snap_min)
        hist_rad = np.where(snap_k[:, None], rpy_k, euler_from_dcm(r_ep))
        sig_f = lock_sigmas(p_fwd)
        side = "difference" if rpy[1] > 0 else "sum"
        notes.append(f"mounting pitch {np.degrees(rpy[1]):+.0f} deg (the estimate {np.degrees(delta):.2g} deg "
                     f"from it, within {config.gimbal_snap_sigmas:g} sigma): the gimbal lock, where roll and yaw "
                     f"turn about one axis; reported as roll 0 and yaw their {side} (scipy's as_euler), sigmas "
                     "the rotation's about each angle's axis; the exact rotation is mounting_quat_wxyz")
    else:
        jac = _euler_jacobian(r_fin)
        rpy = euler_from_dcm(r_fin)
        cov_e = np.einsum("ij,kjl,ml->kim", jac, run.p_mount, jac)
        sig_e = np.sqrt(np.maximum(np.einsum("kii->ki", cov_e), 0.0))
        mount_sig = tuple(float(x) for x in sig_scale * np.degrees(sig_e[k_rep]))
        hist_rad = euler_from_dcm(r_ep)
        cov_f = np.einsum("ij,kjl,ml->kim", jac, p_fwd, jac)
        sig_f = np.sqrt(np.maximum(np.einsum("kii->ki", cov_f), 0.0))
    mount_rpy = tuple(float(x) for x in np.degrees(rpy))
    # keep yaw continuous around the final value
    hist_mount = rpy_unwrap(np.degrees(hist_rad), np.degrees(rpy))
    # convergence (forward filter sigma; the smoother's is not a convergence)
    conv = None
    thr = np.array(config.converged_arcmin) * ARCMIN / DEG
    ok = (np.degrees(sig_f) < thr).all(1)
    if ok[-1]:
        bad = np.nonzero(~ok)[0]
        first = 0 if len(bad) == 0 else bad[-1] + 1
        conv = float(run.t_s[first] - run.t_s[0])
    sig_axes = axis_sigmas(rpy, run.p_mount[k_rep])
    return MountingSummary(True, mount_rpy, mount_sig, sig_e, hist_mount, conv, sig_axes, quat, bool(gimbal),
                           _still_converging(run.t_s, sig_f, config))


def _still_converging(t_s: np.ndarray, sig_f: np.ndarray, config: AlignmentConfig) -> bool | None:
    """Whether the forward filter's mounting sigma (epochs, 3) of some angle fell by more than
    config.settle_fall_ratio over the last config.settle_tail_frac of the run."""
    if len(t_s) < 2 or not np.isfinite(sig_f[-1]).all():
        return None
    k0 = int(np.searchsorted(t_s, t_s[-1] - config.settle_tail_frac * (t_s[-1] - t_s[0])))
    with np.errstate(divide="ignore", invalid="ignore"):
        fall = sig_f[min(k0, len(t_s) - 1)] / sig_f[-1]
    return bool(np.any(fall > config.settle_fall_ratio))


def _observability(run: FilterRun, lay: StateLayout, sig0: np.ndarray, k_rep: int, sig_axes: np.ndarray | None,
                   config: AlignmentConfig, notes: list[str]) -> dict[str, bool]:
    """Observable: the sigma shrank below config.observable_shrink x its prior; a mounting angle's sigma is
    the rotation's about that angle's own axis (``sig_axes``, rad), not the Euler angle's (singular at the
    gimbal lock, where the rotation is as determined as anywhere)."""
    obs: dict[str, bool] = {}
    shrink = config.observable_shrink
    p_fin = np.sqrt(run.p_diag[k_rep])
    if sig_axes is not None:
        # the prior's smallest axis: a prior widened about one axis (its own frame, not the Euler angles')
        # never makes an axis look determined that only fell to the others' prior
        s0m = np.degrees(np.min(sig0[lay.mount] if lay.mount is not None else sig0[lay.att]))
        for i, ax in enumerate(("roll", "pitch", "yaw")):
            obs[f"mounting_{ax}"] = bool(np.degrees(sig_axes[i]) < shrink * s0m)
    for name, sl in (("gyro_bias", lay.gyro), ("accel_bias", lay.accel), ("lever_arm", lay.lever)):
        if sl is None:
            continue
        for i, ax in enumerate("xyz"):
            obs[f"{name}_{ax}"] = bool(p_fin[sl][i] < shrink * sig0[sl][i])
    if lay.delay is not None:
        obs["delay"] = bool(p_fin[lay.delay] < shrink * sig0[lay.delay])
    unobs = [k for k, v in obs.items() if not v]
    if unobs:
        notes.append("not observable with this motion (sigma did not shrink below "
                     f"{shrink:g} x prior): {', '.join(unobs)}; they hold the prior, not estimates (null in report.json)")
    return obs


def _residual_summary(run: FilterRun, lay: StateLayout, notes: list[str]
                      ) -> tuple[list[str], np.ndarray, dict[str, float]]:
    """(names, residual history in reported units, RMS and mean NIS after the initial transient)."""
    ne = len(run.t_s)
    rn: list[str] = []
    scale = []
    if lay.uses_vel:
        rn += ["vel_n_m_s", "vel_e_m_s", "vel_d_m_s"]
        scale += [1.0] * 3
    if lay.uses_att:
        rn += ["att_n_deg", "att_e_deg", "att_d_deg"]
        scale += [1.0 / DEG] * 3
    resid = run.innov * np.array(scale)
    rms: dict[str, float] = {}
    valid = np.isfinite(resid).all(1)
    half = valid & (np.arange(ne) >= ne // 10)  # skip the initial transient
    if not half.any():  # (every update in the first tenth: a master whose output stopped early)
        half = valid

    def rms_of(cols: slice) -> float:
        return float(np.sqrt(np.mean(resid[half, cols] ** 2))) if half.any() else float("nan")

    if lay.uses_vel:
        rms["vel_m_s"] = rms_of(slice(0, 3))
    if lay.uses_att:
        a0 = 3 if lay.uses_vel else 0
        rms["att_deg"] = rms_of(slice(a0, a0 + 3))
    nis = run.nis[valid]
    rms["nis_mean"] = float(np.mean(nis[len(nis) // 10:])) if len(nis) else float("nan")
    rms["nis_dof"] = float(lay.n_meas)
    if rms["nis_mean"] > 3.0 * lay.n_meas:
        notes.append(f"residuals {np.sqrt(rms['nis_mean'] / lay.n_meas):.1f}x larger than the noise model: "
                     "unmodelled flexure, lever arm or delay? sigmas are optimistic")
    return rn, resid, rms


def _lever_arm(run: FilterRun, lay: StateLayout, sig0: np.ndarray, k_rep: int, sig_scale: float,
               opts: AlignmentOptions, config: AlignmentConfig, notes: list[str]
               ) -> tuple[tuple | None, tuple | None]:
    """The lever arm: estimated (a state), or the one given (not estimated), else not modelled (None)."""
    if lay.lever is not None:
        lever_m = tuple(float(x) for x in run.lever_hat[k_rep])
        lever_sig = tuple(float(x) for x in sig_scale * np.sqrt(np.maximum(run.p_diag[k_rep, lay.lever], 0.0)))
        prior = float(sig0[lay.lever][0])
        if np.linalg.norm(lever_m) > config.lever_arm_implausible_sigmas * prior:
            notes.append(f"lever arm estimate {np.linalg.norm(lever_m):.3g} m is far beyond its prior "
                         f"({prior:g} m per axis): it is absorbing something else (an uncompensated delay?)")
        return lever_m, lever_sig
    if opts.lever_arm_m is not None and lay.uses_vel:
        return tuple(float(x) for x in np.asarray(opts.lever_arm_m, float)), None
    if opts.lever_arm_m is not None and not opts.estimate_lever_arm and np.any(np.asarray(opts.lever_arm_m) != 0):
        notes.append(f"the lever arm given ({_fmt3(opts.lever_arm_m)} m) acts on velocity matching only: not used "
                     "with attitude matching alone")
    return None, None


def _fmt3(v) -> str:
    return "/".join(f"{float(x):.3g}" for x in v)


def rpy_unwrap(hist_deg: np.ndarray, ref_deg: np.ndarray) -> np.ndarray:
    """Wrap each angle history to within 180 deg of the reference value."""
    return ref_deg + (hist_deg - ref_deg + 180.0) % 360.0 - 180.0


def _histories(run: FilterRun, lay: StateLayout, hist_mount: np.ndarray, sig_e: np.ndarray, rows: np.ndarray
               ) -> tuple[list[str], np.ndarray, np.ndarray]:
    """The reported histories (names, values, sigmas) at the epochs ``rows`` (taken first: 4 h of epochs at
    19 Hz are 0.2 GB of whole histories)."""
    names: list[str] = []
    cols: list[np.ndarray] = []
    sigs: list[np.ndarray] = []
    x = run.x[rows]
    sd = np.sqrt(np.maximum(run.p_diag[rows], 0.0))

    def add(sl, labels, scale):
        names.extend(labels)
        cols.append(x[:, sl] * scale)
        sigs.append(sd[:, sl] * scale)

    names.extend(["mount_roll_deg", "mount_pitch_deg", "mount_yaw_deg"])
    cols.append(hist_mount[rows])
    sigs.append(np.degrees(sig_e[rows]))
    add(lay.att, ["att_err_n_arcmin", "att_err_e_arcmin", "att_err_d_arcmin"], 1.0 / ARCMIN)
    if lay.vel is not None:
        add(lay.vel, ["vel_err_n_m_s", "vel_err_e_m_s", "vel_err_d_m_s"], 1.0)
    add(lay.gyro, ["gyro_bias_x_dph", "gyro_bias_y_dph", "gyro_bias_z_dph"], 1.0 / DEG_PER_H)
    if lay.accel is not None:
        add(lay.accel, ["accel_bias_x_mg", "accel_bias_y_mg", "accel_bias_z_mg"], 1.0 / MG)
    if lay.flex_ang is not None:
        add(lay.flex_ang, ["flex_ang_x_arcmin", "flex_ang_y_arcmin", "flex_ang_z_arcmin"], 1.0 / ARCMIN)
    if lay.master_att is not None:
        add(lay.master_att, ["master_att_err_n_arcmin", "master_att_err_e_arcmin", "master_att_err_d_arcmin"],
            1.0 / ARCMIN)
    if lay.accel_mis is not None:
        add(lay.accel_mis, ["accel_misalign_x_deg", "accel_misalign_y_deg", "accel_misalign_z_deg"], 1.0 / DEG)
    if lay.lever is not None:
        names.extend(["lever_arm_x_m", "lever_arm_y_m", "lever_arm_z_m"])
        cols.append(run.lever_hat[rows])
        sigs.append(sd[:, lay.lever])
    if lay.delay is not None:
        names.append("delay_s")
        cols.append(run.tau_hat[rows, None])
        sigs.append(sd[:, [lay.delay]])
    return names, np.concatenate(cols, axis=1), np.concatenate(sigs, axis=1)
