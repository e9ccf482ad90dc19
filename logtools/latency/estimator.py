"""The estimate: the stages in order (``tapost``), the widened search, the other methods, ``estimate``."""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from logtools.conventions import euler_from_dcm
from logtools.errors import AnalysisError
from logtools.inslog import InsLog
from logtools.latency import spikes
from logtools.latency.beside import Beside
from logtools.latency.candidates import fit_all
from logtools.latency.coarse import Coarse, coarse, xcorr_estimate
from logtools.latency.config import DEFAULT, LatencyConfig
from logtools.latency.fit import best_cutoff, refine, residual
from logtools.latency.fusion import periodic_by_velocity, velocity_step
from logtools.latency.gls import NoiseModel, noise_model
from logtools.latency.inputs import motion_snr, series_on_grid
from logtools.latency.methods import METHODS, Method, run_seed
from logtools.latency.prepare import Ctx, prepare, refiltered_ctx
from logtools.latency.quality import cost_curve, quality_record
from logtools.latency.steps import clock_step
from logtools.latency.uncertainty import RateSigma, budget, centroid_term, drift_prior, fused, jitter_sigma_s, rate_sigma
from logtools.latency.velocity_pair import VelocityPair, velocity_pair
from logtools.latency.windows import Overlap, fit_window_chi2
from logtools.resample import UniformSeries
from logtools.results import LatencyResult, MethodEstimate

Progress = Callable[[float, str], None] | None


@dataclass(frozen=True)
class Samples:
    """The refinement samples of the master over the analysed window [w0, w1] (its slave counterpart
    exists at the coarse lag), and the grid they come from."""

    grid: UniformSeries
    ok0: np.ndarray  # on ``grid``: master samples whose slave counterpart exists at the coarse lag
    t_m: np.ndarray
    a: np.ndarray
    valid: np.ndarray
    w0: float
    w1: float

    @property
    def t_mid(self) -> float:
        return 0.5 * (self.w0 + self.w1)


def check_motion(ctx: Ctx) -> tuple[float, float, float, float]:
    """(master motion deg/s, its SNR, the slave's, its SNR); AnalysisError without enough motion."""
    cfg = ctx.cfg
    motion_dps, snr = motion_snr(ctx.master, ctx.band_cutoff_hz)
    motion_s_dps, snr_s = motion_snr(ctx.slave, ctx.band_cutoff_hz)
    need = cfg.prepare.min_motion_snr
    still = cfg.prepare.min_motion_dps
    if min(snr, snr_s) < need or motion_dps < still:
        if motion_dps >= still and snr_s < need <= snr:  # the master moves; the slave's rate is noise
            raise AnalysisError(
                f"the slave's angular rate is mostly noise (signal/noise {snr_s:.2g}, need {need:g}) while "
                f"the master moves {motion_dps:.3g} deg/s RMS" + (
                    " (derived from attitude: its stamps too irregular or too coarse?)"
                    if ctx.slave.source == "attitude" else ""))
        for unit, role in ((ctx.master, "master"), (ctx.slave, "slave")):
            if int(np.count_nonzero(unit.grid.valid)) < 10:  # (motion_snr's 0: no stretch of the rate read)
                raise AnalysisError(
                    f"the {role}'s angular rate has no stretch regular enough to read: its stamps come in bursts or "
                    "with gaps everywhere (a telemetry log on receive stamps? its messages' own time fields are "
                    "the default)")
        raise AnalysisError(
            f"not enough motion to estimate the latency: {motion_dps:.3g} deg/s RMS on the master "
            f"(signal/noise {min(snr, snr_s):.2g}, need {need:g})")
    return motion_dps, snr, motion_s_dps, snr_s


def _refine_grid(ctx: Ctx) -> UniformSeries:
    """The master at ~5x the low-pass cutoff (both units are band-limited there, so a denser grid adds no
    information, only time; the residuals' correlation is handled by the HAC)."""
    m = ctx.master
    return series_on_grid(m.itp, ctx.dt_r) if abs(ctx.dt_r - ctx.dt_s) > 1e-12 else m.grid


def analysed_window(ctx: Ctx, co: Coarse) -> Samples:
    """The master samples whose slave counterpart exists at the coarse lag, and their span."""
    gr = _refine_grid(ctx)
    t_m, a, valid = gr.t_s, gr.values, gr.valid
    ok0 = valid & ctx.slave.itp.ok(t_m + co.d0_s)
    min_s = ctx.cfg.prepare.min_overlap_s
    if ok0.sum() * ctx.dt_r < min_s:
        raise AnalysisError(f"overlap at the estimated lag {co.d0_s:.3f} s is only "
                            f"{ok0.sum() * ctx.dt_r:.1f} s (need {min_s:g} s)")
    idx = np.flatnonzero(ok0)
    w0, w1 = float(t_m[idx[0]]), float(t_m[idx[-1]])
    sel = (t_m >= w0) & (t_m <= w1)
    return Samples(gr, ok0, t_m[sel], a[sel], valid[sel], w0, w1)


def first_fit(ctx: Ctx, co: Coarse, smp: Samples) -> tuple[Ctx, Samples, float, NoiseModel | None]:
    """The first fit, on the central part (at most ``adapt_span_s``, where drift barely matters), no drift:
    the delay the windows search around, and the residual spectrum for the GLS. Without a spectrum (very
    short data) the band is re-chosen from the residual instead, and the units re-filtered (a new ``Ctx``).
    Returns (ctx, samples, the central delay, the noise model or None)."""
    cfg = ctx.cfg
    t_m, a, valid, t_mid = smp.t_m, smp.a, smp.valid, smp.t_mid
    cs = np.abs(t_m - t_mid) <= 0.5 * cfg.refine.adapt_span_s
    itp = ctx.slave.itp
    first = refine(t_m[cs], a[cs], valid[cs], itp, co.d0_s, 0.0, t_mid, fit_drift=False, cfg=cfg)
    d_center = first.latency_s if first.ok else co.d0_s
    noise = None
    if cfg.refine.gls and first.ok:
        cr = residual(t_m[cs], a[cs], valid[cs], itp, first, t_mid)
        noise = noise_model(cr, np.any(cr != 0.0, axis=1), ctx.dt_r, cfg=cfg)
    if cfg.refine.adapt_band and first.ok and noise is None:
        new_cut = best_cutoff(t_m[cs], a[cs], valid[cs], residual(t_m[cs], a[cs], valid[cs], itp, first, t_mid),
                              ctx.dt_r, ctx.cutoff_hz, float(np.ptp(t_m[cs])), cfg=cfg)
        if new_cut < cfg.refine.adapt_min_ratio * ctx.cutoff_hz:
            ctx = refiltered_ctx(ctx, new_cut)
            gr = _refine_grid(ctx)
            sel = (gr.t_s >= smp.w0) & (gr.t_s <= smp.w1)
            smp = replace(smp, grid=gr, t_m=gr.t_s[sel], a=gr.values[sel], valid=gr.valid[sel])
    return ctx, smp, d_center, noise


def _velocity_pair(ctx: Ctx) -> VelocityPair | None:
    return velocity_pair(*ctx.vel_src, ctx.band_cutoff_hz, ctx.master.itp, cfg=ctx.cfg)


def velocity_stage(ctx: Ctx, smp: Samples, rs: RateSigma, fit_drift: bool, flexure: bool,
                   pair: Beside | None = None) -> tuple[dict | None, VelocityPair | None, RateSigma]:
    """Velocity matching (both units with NED velocity): its quality entry, the pair, and the rate fit's
    estimate fused with it where they agree (``fusion.velocity_step``). ``pair``: the pair of this ``ctx``,
    being made in a thread."""
    if ctx.vel_src is None:
        return None, None, rs
    vp = pair.result() if pair is not None else _velocity_pair(ctx)
    vel_q, fusion = velocity_step(ctx, vp, smp.w0, smp.w1, smp.t_mid, fit_drift, rs.latency_s, rs.drift,
                                  rs.sigma_latency_s, rs.sigma_drift, rs.corr_ld, flexure=flexure)
    return vel_q, vp, fused(rs, fusion)


def best_instant(rs: RateSigma, V: np.ndarray | None, smp: Samples, fit_drift: bool
                 ) -> tuple[float, float, float | None]:
    """The instant where the latency is best determined (uncorrelated with the drift): the middle of the
    window when the motion is spread evenly, elsewhere when it is not (DESIGN.md quotes the middle).
    Returns (t, latency there, its variance or None at the middle)."""
    t_mid = smp.t_mid
    if not (fit_drift and np.isfinite(rs.sigma_drift) and rs.sigma_drift > 0 and np.isfinite(rs.sigma_latency_s)):
        return t_mid, rs.latency_s, None
    t_best = float(np.clip(t_mid - V[0, 1] / V[1, 1], smp.w0, smp.w1))
    lat_best = float(rs.latency_s + rs.drift * (t_best - t_mid))
    v_best = V[0, 0] + 2 * (t_best - t_mid) * V[0, 1] + (t_best - t_mid) ** 2 * V[1, 1]
    return t_best, lat_best, v_best


def tapost(ctx: Ctx, progress: Progress, *, overlap: bool = False, threads_done: Callable[[], None] | None = None,
           co: Coarse | None = None) -> tuple[LatencyResult, Coarse]:
    """tapost's method, stage by stage (the package map names each stage's module). ``overlap``: the velocity
    pair (its interpolants and lever-arm rows: a third of the stage) made in a thread beside the rate fit,
    which it does not need (the same numbers, sooner where a core is free). ``threads_done``: called once no
    thread of this call runs any more (at the velocity stage; at once without the thread), before the rest of
    the stage: a caller may fork there. ``co``: the coarse search of this ``ctx`` where it was made already
    (``despiked``)."""
    pair = Beside(_velocity_pair, ctx) if overlap and ctx.vel_src is not None else None
    if pair is None and threads_done is not None:
        threads_done()
        threads_done = None
    try:
        return _tapost(ctx, progress, pair, threads_done, co)
    finally:
        if pair is not None:  # (an error before the pair was used: the thread ends before the caller goes on)
            pair.join()


def _tapost(ctx: Ctx, progress: Progress, pair: Beside | None, threads_done: Callable[[], None] | None,
            co: Coarse | None = None) -> tuple[LatencyResult, Coarse]:
    ctx0 = ctx

    def prog(f: float, stage: str) -> None:
        if progress is not None:
            progress(f, stage)

    cfg = ctx.cfg
    motion = check_motion(ctx)
    prog(0.1, "coarse |w| and rotation-solved cost")
    co = coarse(ctx) if co is None else co
    prog(0.35, "refinement")
    smp = analysed_window(ctx, co)
    ctx, smp, d_center, noise = first_fit(ctx, co, smp)
    ctx.raw.release()  # (the refit at another cutoff was the last to need them)
    t_mid, w0, w1 = smp.t_mid, smp.w0, smp.w1
    prog(0.55, "windows and drift")
    ov = Overlap(smp.t_m, smp.a, smp.valid, ctx.slave.itp, w0, w1)
    fin, centers, lats, sigs = fit_all(ctx, ov, d_center, 0.0, cfg.windows.drift_search_ppm, noise)
    prog(0.8, "drift")
    fit_drift = len(centers) >= 3
    rs = rate_sigma(fin, centers, lats, sigs, t_mid, ctx, fit_window_chi2(fin, centers, lats, sigs, t_mid))
    if ctx.vel_src is not None:
        prog(0.85, "velocity matching")
    if pair is not None:
        pair.join()
        if ctx.master is not ctx0.master:  # (first_fit low-passed the units again: the pair of their new rates)
            pair = None
    if threads_done is not None:
        threads_done()
    vel_q, vp, rs = velocity_stage(ctx, smp, rs, fit_drift, fin.flex is not None, pair)
    rs, V = drift_prior(rs, fit_drift, cfg)
    if not fit_drift:
        rs = centroid_term(rs, ctx, smp.t_m, smp.valid, t_mid)
    jit_sigma = jitter_sigma_s(ctx, w0, w1)
    t_best, lat_best, v_best = best_instant(rs, V, smp, fit_drift)
    alts, alts_out = list(co.alternatives_s), []
    if alts and cfg.search.periodic_velocity and vel_q is not None and vel_q["agrees"]:
        alts, alts_out = periodic_by_velocity(ctx, vp, alts, co.d0_s, rs.latency_s, rs.drift, t_mid, fit_drift)
    spread = max(abs(x - co.d0_s) for x in alts) if alts else None
    sb = budget(rs, V, v_best, jit_sigma, spread, cfg, float(np.hypot(*ctx.clock_sigma_s)))
    rpy = tuple(float(x) for x in np.degrees(euler_from_dcm(fin.R)))
    gr = smp.grid
    nanfrac = float(1.0 - np.mean(smp.ok0[(gr.t_s >= w0) & (gr.t_s <= w1)]))
    c_lag, c_val = cost_curve(ctx, co, rs.latency_s, rs.drift, t_mid, w0, w1, sb.sigma_s)
    quality = quality_record(ctx, co, fin, motion, rs, sb, fit_drift=fit_drift, gls=noise is not None,
                             n_windows=len(centers), window=(w0, w1), nan_fraction=nanfrac, vel_q=vel_q, alts=alts,
                             alts_out=alts_out, jit_sigma=jit_sigma, best=(t_best, lat_best), rpy=rpy)
    # one line (L, drift) or a clock step: the windows' own delays judged (steps.clock_step)
    quality["clock_step"] = clock_step(ctx, ov, fin.latency_s, fin.drift, co.alternatives_s, co.d0_s)
    res = LatencyResult(
        latency_s=float(rs.latency_s), sigma_s=float(sb.sigma_s),
        drift_ppm=float(rs.drift * 1e6) if fit_drift else 0.0,
        method=Method.TAPOST.value, window_s=(ctx.t0_abs_s + w0, ctx.t0_abs_s + w1), quality=quality,
        cost_lag_s=c_lag, cost=c_val,
        window_centers_s=centers, window_latency_s=lats, mounting_rpy_deg=rpy, t_mid_rel_s=float(t_mid))
    return res, co


def despiked(ctx: Ctx, master: InsLog, slave: InsLog, max_lag_s: float | None, *, accelerometers: bool,
             velocity: bool, cfg: LatencyConfig, threads: bool
             ) -> tuple[Ctx, InsLog, InsLog, Coarse | None, list[dict]]:
    """Stage 1b (``spikes``): the IMU samples of one unit far off their neighbours, with nothing alike in the
    other unit at the coarse lag, replaced by their neighbours' mean, and the pair prepared again from them
    (said in the warnings); else the same pair. Returns (ctx, master, slave, the coarse search of ctx or None,
    the replaced samples' records: ``spikes.records``)."""
    if ctx.master.source != "gyro" or ctx.slave.source != "gyro":
        return ctx, master, slave, None, []
    cands = spikes.candidates(master, slave.rebased(master.meta.t0_ns), cfg.spikes)
    if not cands:  # (the common case: no coarse search here, tapost's own runs beside its velocity pair)
        return ctx, master, slave, None, []
    try:
        check_motion(ctx)
        co = coarse(ctx)
    except AnalysisError:  # (tapost's own stages say why)
        return ctx, master, slave, None, []
    if co.best_cost > cfg.search.no_match_cost:  # no match: no instant of one unit is known in the other
        return ctx, master, slave, co, []
    found = spikes.alone(cands, co.d0_s, cfg.spikes)
    if not found:
        return ctx, master, slave, co, []
    notes = [spikes.describe(role, found, log.t_imu_s(), log.t0_s)
             for role, log in (("master", master), ("slave", slave)) if any(r == role for r, _ in found)]
    replaced = spikes.records(found, {"master": master, "slave": slave})
    master, slave = spikes.mend(master, slave, replaced)
    ctx = prepare(master, slave, max_lag_s, accelerometers=accelerometers, velocity=velocity, cfg=cfg,
                  threads=threads)
    return replace(ctx, warnings=ctx.warnings + tuple(notes)), master, slave, None, replaced


def suspect(res: LatencyResult, max_lag_s: float, cfg: LatencyConfig = DEFAULT) -> bool:
    """A bounded search's result that may be a minimum of the window, not of the data: at (or past) the
    window's edge, or fitting the rates poorly (the true delay beyond --max-lag: a car 3.5 s late came out
    3.08 s at sigma 25 ms, a multirotor 5 s late -1.81 s at sigma 0.5 ms)."""
    return bool(abs(res.latency_s) > cfg.search.search_edge_fraction * max_lag_s
                or res.quality.get("vector_cost_min", 0.0) > cfg.search.search_suspect_cost)


def widened(res: LatencyResult, ctx: Ctx) -> LatencyResult:
    """The whole overlap searched as well (``ctx``, the bounded search's, unbounded); its result replaces the
    bounded one where it fits the rates clearly better (cost below ``search_widen_gain`` x), and a warning says
    what was found either way."""
    max_lag_s = ctx.max_lag_s
    c0 = float(res.quality.get("vector_cost_min", np.nan))
    try:
        wide, _ = tapost(replace(ctx, max_lag_s=None), None)
    except AnalysisError as exc:
        wide, why = None, exc.problem
    c1 = float(wide.quality.get("vector_cost_min", np.nan)) if wide is not None else np.nan
    # (the bounded search's refinement may walk past the window: where it ended, said as such)
    where = (f"ended at {res.latency_s * 1e3:+.1f} ms" + (", past its edge" if abs(res.latency_s) > max_lag_s else ""))
    better = wide is not None and c1 < ctx.cfg.search.search_widen_gain * c0
    if better and c1 <= ctx.cfg.search.whole_overlap_max_cost:
        q = dict(wide.quality)
        q["warnings"] = list(q.get("warnings", [])) + [
            f"the search within +-{max_lag_s:g} s {where} and fitted the rates poorly (cost {c0:.3g}) or lay at "
            f"the edge: the whole overlap was searched and {wide.latency_s:+.4f} s fits far better (cost "
            f"{c1:.3g}); widen --max-lag or use --max-lag auto to search so directly"]
        q["search_widened"] = True
        return replace(wide, quality=q)
    q = dict(res.quality)
    q["search_widened"] = False
    if better:  # (a far better fit, yet not one a right lag gives: a chance match in the wider search)
        ov = wide.quality.get("overlap_s")
        note = (f"the whole overlap, searched as well, fits better at {wide.latency_s:+.4f} s but still poorly (cost "
                f"{c1:.3g}" + (f" over {ov:.0f} s of overlap" if ov is not None else "") + "; a right lag fits below "
                f"{ctx.cfg.search.whole_overlap_max_cost:g}), which is not taken")
        q["search_widened_rejected"] = note
    else:
        note = (f"the whole overlap, searched as well, fits no better (cost {c1:.3g} at {wide.latency_s:+.4f} s)"
                if wide is not None else f"a whole-overlap search could not run ({why})")
    q["warnings"] = list(q.get("warnings", [])) + [
        f"the search within +-{max_lag_s:g} s {where}, at its edge or fitting the rates poorly (cost {c0:.3g}); "
        + note]
    return replace(res, quality=q)


def check_plausible(latency_s: float, ctx: Ctx) -> None:
    """AnalysisError (one line) for a latency no pair of logs can have: not finite, beyond
    ``search.max_latency_s`` (no two clocks differ by more), or outside the lags at which the two logs overlap
    at all (the slave's span shifted back by it misses the master's: the estimate rests on no common data)."""
    lim = ctx.cfg.search.max_latency_s
    if not np.isfinite(latency_s) or abs(latency_s) > lim:
        raise AnalysisError(f"estimated latency {latency_s:+.6g} s is physically impossible (beyond +-{lim:g} s, "
                            "more than any two clocks differ): a corrupt time field in either log?")
    m, s = ctx.master.itp, ctx.slave.itp
    lo, hi = s.t_first_s - m.t_last_s, s.t_last_s - m.t_first_s  # the slave at t + L meets the master for L in these
    if not lo < latency_s < hi:
        raise AnalysisError(f"estimated latency {latency_s:+.6g} s lies outside the lags at which the two logs "
                            f"overlap at all ({lo:+.6g} .. {hi:+.6g} s): no common data supports it")


def _run_methods(names: list[str], method: str, ctx: Ctx, master: InsLog, slave: InsLog, max_lag_s: float | None,
                 config: LatencyConfig, prog: Callable[[int, str], None] | None
                 ) -> tuple[dict[str, MethodEstimate], AnalysisError | None]:
    """The methods ``names`` in turn (``estimate``'s comparison, or a headline other than tapost with it):
    each one's estimate, or NaN with why it could not run; the headline ``method``'s failure is returned
    (the run's failure) and ends the loop."""
    methods: dict[str, MethodEstimate] = {}
    for i, name in enumerate(names):
        if prog is not None:
            prog(i, name)
        try:
            if name == Method.TAPOST:
                r, _ = tapost(ctx, None)
                me = MethodEstimate(r.latency_s, r.sigma_s, "")
            elif name == Method.XCORR:
                me = xcorr_estimate(ctx)
            else:
                me = run_seed(name, master, slave, max_lag_s, headline=name == method, cfg=config)
        except AnalysisError as exc:
            if name == method:
                return methods, exc
            me = MethodEstimate(float("nan"), float("nan"), f"cannot run: {exc.problem}")
        except Exception as exc:  # noqa: BLE001 - a comparison method must never crash the run
            if name == method:
                raise
            me = MethodEstimate(float("nan"), float("nan"), f"failed: {type(exc).__name__}: {exc}")
        methods[name] = me
    return methods, None


def estimate(master: InsLog, slave: InsLog, *, method: str = "tapost", max_lag_s: float | None = 2.0,
             compare: bool = True, progress: Progress = None, accelerometers: bool = True,
             velocity: bool = True, config: LatencyConfig = DEFAULT, beside: Callable | None = None,
             overlap: bool = False) -> LatencyResult:
    """Latency (s) and drift (ppm) of ``slave`` behind ``master``; see the package docstring (``logtools.latency``).

    ``max_lag_s`` bounds the search at face value (both logs' absolute stamps); ``None`` searches the
    whole overlap (unrelated clocks). Raises AnalysisError (one line) for no/too short overlap, no motion,
    NaN-only data. With ``compare`` every other method that can run is stored in ``methods`` (a method
    that cannot run is stored with NaN and its reason). ``accelerometers=False`` keeps the tapost method
    on the gyros alone (no accelerometer-aided GLS); ``velocity=False`` leaves the units' velocities out
    (no velocity matching). ``config``: every tuning number and switch (``LatencyConfig``). ``beside``: a
    function like ``pipelines.parallel.submit`` (``beside(fn, *args)`` -> an object with ``result()`` and
    ``cancel()``) that runs the comparison methods while the tapost headline is computed (the CLI forks them:
    the same numbers, sooner); None runs them after it, here. ``overlap``: the two units are prepared in two
    threads and the tapost headline makes its velocity pair in a thread beside its rate fit (``tapost``), the
    comparison methods forked by ``beside`` once that thread has ended (the same numbers, sooner: the CLI, up
    to about 1 h of 200 Hz logs, where the arrays side by side fit).
    """
    if method not in METHODS:
        raise AnalysisError(f"unknown latency method {method!r} (choose from {', '.join(METHODS)})")

    def prog(f: float, stage: str) -> None:
        if progress is not None:
            progress(float(f), stage)

    prog(0.0, "preparing")
    ctx = prepare(master, slave, max_lag_s, accelerometers=accelerometers, velocity=velocity, cfg=config,
                  threads=overlap)
    co, replaced = None, []
    if method == Method.TAPOST and config.spikes.enabled:  # (the comparison methods read the same samples)
        ctx, master, slave, co, replaced = despiked(ctx, master, slave, max_lag_s, accelerometers=accelerometers,
                                                    velocity=velocity, cfg=config, threads=overlap)
    others = [x for x in METHODS if x != method] if compare else []
    beside_started: list = []
    start_beside = None
    if beside is not None and method == Method.TAPOST and others:
        def start_beside() -> None:  # (forked once the headline's own thread is done)
            beside_started.append(beside(_run_methods, others, method, ctx, master, slave, max_lag_s, config, None))
    methods: dict[str, MethodEstimate] = {}
    head: LatencyResult | None = None
    err: AnalysisError | None = None
    # the headline first: its failure is the run's failure
    try:
        if method == Method.TAPOST:
            head, _ = tapost(ctx, lambda f, st: prog(0.05 + 0.75 * f, st), overlap=overlap,
                             threads_done=start_beside, co=co)
            if max_lag_s is not None and config.search.search_widen and suspect(head, max_lag_s, config):
                prog(0.78, "whole-overlap search")
                head = widened(head, ctx)
            cost = float(head.quality.get("vector_cost_min", 0.0))
            if cost > config.search.no_match_cost:
                wider = head.quality.get("search_widened_rejected")
                raise AnalysisError(
                    f"the two units' angular rates match at no lag searched (best normalised cost {cost:.2f}; "
                    "0 = identical, 1 = unrelated)" + (f"; {wider}" if wider else "")
                    + ": logs of different vehicles or of different times?")
            if max_lag_s is None and cost > config.search.whole_overlap_max_cost:
                ov = head.quality.get("overlap_s")
                raise AnalysisError(
                    f"the two units' angular rates match at no lag of the whole overlap (the best, "
                    f"{head.latency_s:+.4f} s, fits poorly: normalised cost {cost:.2f}"
                    + (f" over {ov:.0f} s of overlap" if ov is not None else "")
                    + f"; a right lag fits below {config.search.whole_overlap_max_cost:g}, 0 = identical, 1 = "
                    "unrelated): logs of different vehicles or of different times?")
            methods[Method.TAPOST.value] = MethodEstimate(head.latency_s, head.sigma_s, "")
    except BaseException:
        for pending in beside_started:
            pending.cancel()
        raise
    if beside_started:
        prog(0.8, "comparison methods")
        more, err = beside_started[0].result()
    else:
        names = ([method] if method != Method.TAPOST else []) + others
        more, err = _run_methods(names, method, ctx, master, slave, max_lag_s, config,
                                 lambda i, name: prog(0.8 + 0.2 * i / max(1, len(others) + 1), name))
    methods.update(more)
    if err is not None:
        raise err
    if head is None:
        me = methods[method]
        if not np.isfinite(me.latency_s):
            raise AnalysisError(f"latency method {method} could not run: {me.note}")
        g = ctx.master.grid
        head = LatencyResult(latency_s=me.latency_s, sigma_s=me.sigma_s, drift_ppm=0.0, method=method,
                             window_s=(ctx.t0_abs_s + float(g.t_s[0]), ctx.t0_abs_s + float(g.t_s[-1])),
                             quality={"note": me.note, "warnings": list(ctx.warnings), "drift_estimated": False,
                                      "drift_not_estimated": f"{method} estimates no drift (it assumes the clocks "
                                                             "run at one rate; the compensation applies none)"},
                             t_mid_rel_s=float(0.5 * (g.t_s[0] + g.t_s[-1])))
    check_plausible(head.latency_s, ctx)
    if replaced:  # (the later stages read the logs so too: ``spikes.mend``)
        head = replace(head, quality={**head.quality, "replaced_samples": replaced})
    prog(1.0, "done")
    return replace(head, methods={k: methods[k] for k in METHODS if k in methods})
