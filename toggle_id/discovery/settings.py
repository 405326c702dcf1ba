"""The numbers of the discovery loop a user may change (``discover`` node of conf/experiment/discover.yaml): the one
home of their defaults (:class:`DiscoverJobSettings` is the node's schema, ``jobs/schema.py``)."""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..effects import EFFECTS_BY_NAME
from ..errors import ConfigError
from ..simulate import FD_TIERS, SolverSettings, precise_jacobian
from .derivatives import DERIVATIVES


@dataclass
class DiscoverSettings:
    """Numbers of the discovery loop a user may change (conf/experiment/discover.yaml, node ``discover``).

    - top_k: candidates refitted per iteration at least (the best scouts; more while a scout explains more than
      the best accepted refit, or, with none accepted yet, while a scout is significant by its own fit at
      ``alpha``); alpha: level of the F-test an effect must pass
      (BIC must improve too); max_effects: most effects added; candidates: effect names to consider (None: all).
    - screen_alpha: a candidate is scouted only if its score or profile statistic at the polished fit exceeds
      the χ²(1) quantile of this level (1: always).
    - alpha_diag: level of the residual tests; acf_lags, ccf_lags, ccf_step: their lags (samples).
    - baseline_nfev, refit_nfev, null_nfev, scout_nfev: polish budgets (residual evaluations) of the
      baseline, a refit, the nominal re-polish guarding an acceptance, and a scout; rounds / refit_rounds:
      restarts of the baseline and guard / refit polishes while they still improve.
    - second_point: also linearise at the nominal start (large effects bend the polished fit; see the package
      docstring); gauge: report the representatives nearest the reference along the exact symmetries;
      grid_points: magnitudes per probe (the 1-D search before a scout).
    - hold_gauge: during the loop's polishes, hold one parameter per exact symmetry of x_B (K_l, K_i, m_C; see
      :data:`GAUGE_HELD`) at its value — the same fits without the flat directions that stall the trust region
      in long valleys; an effect that breaks a symmetry (``Effect.breaks``) frees its parameter again.
    - fd_tier: the integrator of the long polishes' finite-difference Jacobians: ``precise`` (the default), at
      fd_rel_step (1e-4: smaller steps drown in the adaptive integrator's step-selection noise), or ``jacobian``
      (:data:`toggle_id.simulate.JACOBIAN` at a 1e-3 step, about half the cost, each polish finished by a PRECISE
      round, the screening grids in it too; residuals, statistics, sensitivities and scouts stay PRECISE) — ~20 %
      faster, but it moved verdicts of the adversarial set (README), so it is not the default;
      jacobian_reuse: k > 0 lets the long polishes' rounds follow each finite-difference Jacobian by up to k
      Broyden updates (the secant update in coordinates scaled by the parameters' sizes, from the residuals scipy
      evaluated anyway: no simulation), each polish then finished by a round with fresh Jacobians throughout; 0
      (the default) is every Jacobian by finite differences — an experiment towards issue 14, not yet judged
      on the adversarial set; screen_tier: the integrator of the screening — the score tests' magnitude profiles
      and the scouts' short polishes, residuals and Jacobians alike, each scout's end point simulated once more in
      the residuals' tier for its SSE: ``precise`` (the default: profiles in the Jacobians' tier, scouts PRECISE)
      or ``jacobian`` (:data:`toggle_id.simulate.JACOBIAN` at its step: a third of the stiff tier's steps;
      docs/performance.md); derivatives: ``fd`` (the default: finite differences as above) or ``analytic``
      (:mod:`.derivatives`: forward sensitivities of the PRECISE steps, one simulation for every column, for the
      polishes' Jacobians and the sensitivities; differences where they do not apply — backlash, dead time):
      two to four orders more accurate than the differences, but measured no faster on two cores (the retrace's
      fixed cost; docs/performance.md) and the polishes' paths differ, so not the default;
      jac_rel_step: (log-)step of the sensitivities J; rank_rtol: relative singular-value cut-off of J; absorbed_ratio: ‖s⊥‖/‖s‖ below which an effect counts
      as absorbed by the free parameters.
    - noise_std: known measurement noise (m), only reported as rms/noise (the discover job: None takes
      ``data.noise_m`` of a simulated record); parallel: threaded simulation batches.
    - noise_max_order: largest order of the AR noise model, its order chosen by BIC; every test is prewhitened
      by it (0: white noise assumed); cv_folds, cv_block: folds and block length (samples) of the time-block
      cross-validation an effect must lower the out-of-sample error of (short blocks: the whitened errors are
      nearly independent, and long blocks would take a whole transient out); cv_alpha: level of the one-sided
      test the drop must pass against the noise's spread of it (:func:`.stats.out_of_sample`; 0.5, the default:
      any drop — 0.05 refused rec06's true Coulomb friction, F 72, z 1.2); cv_rcond: where the cross-validation's
      linearised refit of a fold is truncated, relative to the largest singular value of the sensitivities
      (:func:`.stats.block_cv`; 1e-8, the default, keeps directions finer than the finite differences resolve: on
      rec15_d1 of the held-out draw 1e-4 to 1e-3 brings it near a refit of every fold; opt-in until the adversarial
      set is re-run with it); bonferroni: a forward step chooses among
      the m candidates it has left, so its judge's F-tests are at ``alpha``/m (false: at ``alpha``, as before
      2026-12-03); structure_bins: bins per signal of
      the structure test and localisation; scout_all: scout every candidate of the library from its grid, whatever
      its score (global screening; false: only those whose score passes ``screen_alpha``); next_leaders: while
      nothing of a round is supported, a score leader whose refit explains nothing is set aside and the next
      significant leaders are refitted, whatever their scouts (:func:`.forward.next_leaders`); backward: drop,
      at the end, every accepted effect the others make unnecessary. explain_fraction: when structure is left,
      an accepted effect still counts as an explanation if it removed at least this fraction of the structure
      energy of the model without it (:func:`.localise.structure_energy`: it explains most of what it was added
      for); otherwise it is compensating. The same on the validation record, when it is left with structure and
      its prediction error is more than validation_material times the fitted record's RMS error (below that it
      is predicted to about its noise, and the structure there is the parameters' small mismatch: rec14's
      second record, 1.035 times, would demote a real Coulomb torque that barely shows on it). catch_all: when
      structure is left, fit a generic force on slider B
      (any piecewise-linear function of its speed and position) and a generic error of the position reading
      on top of the final model; if they are supported, an accepted effect they make unnecessary is compensating,
      not added (:mod:`.catchall`); with none accepted, the report says what they reach, and when a forward step
      supports no refit and they are supported, every library effect of their kind the scouts left untried (a
      force on the slider, an error of the reading) is refitted first. catch_all_keep: an
      effect is still needed beside them if its removal is significant in sample and costs at least this fraction
      of the error reduction it brings to the final model; a rival tied with a kept effect, switched on in its
      place there, is needed by the same rule, and the tie is resolved for the effect where it is not.
      catch_all_calibrated: an effect significant beside them that keeps less than catch_all_keep is still needed
      if it keeps catch_all_keep of what it would keep were it true (the final model simulated noise-free and
      refitted without it, then with the generic terms: :func:`.catchall.share_if_true`).
      catch_all_share_min: where a true one would keep less than this share there, the generic terms span it and
      the check cannot see it: the plain floor rules (rec25_d1, a scale error's offset part kept 0.2 % against 0.3 %).
      cogging_whole_tol: an accepted cogging torque whose n_cog lies farther than this from a whole number is
      compensating, whether structure is left or not: a motor's cogging repeats a whole number of times per
      revolution (its slots and poles), so a fitted fraction stands in for something else that repeats with a
      position (:func:`.periodic.implausible`); one accepted within it is held at that whole number from the step
      that adds it (:func:`.periodic.whole_counts`). signature_min_periods: a cogging torque that removed little of
      the structure energy (which position bins cannot see) still explains when the residual without it repeats at
      its whole n_cog over at least this many periods of the motor angle's range, significantly after the scan, and
      with it does not (:meth:`.toggle_plant.TogglePlant.own_signature`: a real ripple beside an effect the library
      lacks; a localised error fits a low count over a few periods only); over as many periods with no ripple seen
      (hidden under what the library lacks), it is judged by the catch-all check. cogging_min_periods (10 by default):
      the cogging torque is probed and fitted only at counts n_cog of which the record's motor-angle range holds at
      least this many periods (:func:`.periodic.cogging_floor`; 0: every count the library allows): over a few
      periods a sinusoid in the angle is a smooth function of the position, and a low count then stands in for a force
      the library lacks (rec38 of the adversarial set: n_cog 1.0006, 2.2 periods, beside a quadratic drag). A true
      ripple of fewer periods is then left to the report's periodic look. beside_generic (on by default): when a
      forward step supports nothing and the catch-all's generic terms are supported, the effects of no kind they
      contain (a cogging torque, a dead time, a backlash, the saturations) are refitted beside them and accepted
      where the judge supports them there and they lower the error without them (:func:`.catchall.beside_generic`).
    - ambiguity_alpha: two supported effects whose fits the record cannot tell apart — Vuong's test of the two
      non-nested models (:func:`.stats.vuong`) not significant at this level — are reported together as
      *ambiguous*, never one of them as added (0: off, the better fit is added). encompassing: a tie Vuong's
      test leaves is judged by the model with both effects (:func:`.ties.settle_ties_by_encompassing`): an effect
      needed beside its rival, and the rival not beside it, is named — by the judge at ``alpha``, and where that
      needs neither, with the F-tests at ``ambiguity_alpha`` (the pairwise level; BIC and cross-validation as
      judged).
    - stronger_starts: a refit that is significant by its own fit but dismissed is repeated from these
      multiples (≥ 1) of its magnitude's distance from "off" (the larger of the refit's and the grid's best),
      from the baseline's nominal parameters; where one ends lower it is converged and judged again — a refit
      started small can stop where nominal parameters absorb the effect (:func:`.refit.stronger_magnitudes`);
      empty: off. weaker_starts: when the accepted effect's magnitude ends at the edge of its feasible domain
      (:data:`.forward.AT_BOUND` of the way), its final polish also starts from the nominal fit as given with the
      magnitude at these fractions (< 1) of its distance from "off" — a lash or a threshold run to its bound sits
      where the SSE no longer moves with it (docs/discovery.md, *open problems*); empty: off. reanchor_rtol: when
      the polish from the nominal fit as given wins and changes an added effect's parameters by more than this share
      of their values, the nominal fit as given is polished once more at the values reached (≤ 0: off).
      edge_widen, edge_widenings: when the accepted effect's magnitude, one x_B fixes only relative to the
      mechanism's or the current's scale, still ends at the edge of its domain in the loop's gauge, the room from
      "off" to that edge grows ``edge_widen`` (> 1) times and the fit is polished again, while it ends at the edge and
      gains, at most ``edge_widenings`` times (0: off); the report says where the value it states at the reference
      scale lies outside the library's domain (:func:`.forward.widened_at_edge`). By default twice the room, once:
      the mechanism's scale, read from all the mechanical parameters, is itself uncertain by tens of per cent on a
      machine 15–40 % off the reference (probe q4: the fit's c_B at the reference scale 1.165·10⁴ N·s/m, the
      truth's 8331), and a wider allowance lets a stand-in wander (rec22's third route: a compensating load force
      pressed on its domain in a gauge at 0.17 times the reference).
      rescreen_points, rescreen_span, rescreen_prominence: when the accepted effect's final polish ends above 1.5
      times the record's own noise, the error is profiled along each of its parameters (a phase and a count
      aside) on ``rescreen_points`` values within ``rescreen_span`` of its value, the others held; where a point
      lies below the fit by more than ``rescreen_prominence`` times the noise, the fit is polished again from
      there and kept where it ends lower (:func:`.forward.rescreened`; 0 points: off). The report profiles the
      final model's effects the same way and says where the cost is rough (:mod:`.landscape`).
      other_starts_above: an accepted refit that converged above this many times the record's own noise (read off
      its third differences, :func:`toggle_id.fast.difference_noise`; a quarter of σ under AR(1) ρ 0.9 noise, so
      only where its residual holds structure by the noise-aware structure test too,
      :func:`.residual.structure_left_at`) is polished again from the baseline's other
      starts (the job's reference values, the nominal fit as given; the one the baseline came from last), each
      moved into the baseline's gauge (:func:`.gauge.in_gauge_of`) with the refit's effect values carried to its
      scales and its domains widened for them (:func:`.gauge.carried`, :func:`.gauge.domains_at`), its magnitude
      screened there
      (:func:`.refit.screened_starts`), in order until a polish ends within 1.5 times the noise (a start whose
      polish comes back to the refit's own error is left there); the lowest error is judged. While no supported
      refit of an iteration ends within this many times the noise, the dismissed candidates whose score is
      significant are polished once from each other start too (by least squares; again only where what is left
      holds structure), strongest score first, until one
      ends within 1.5 times the noise (:func:`.refit.from_other_starts`: a 3-ms dead time the baseline hid,
      refitted from there to τ_d ≈ 0, reaches 0.989 µm from the reference values). The baseline and its start bend
      the nominal parameters towards what the effect does, and a large
      effect's refit from there can stop in a valley far from its optimum (a drive limit at 162 µm: 14.08 µm from
      the baseline's start, 1.40 µm from the reference values; docs/discovery.md, *A large threshold effect*). At 5
      no white-noise record of the adversarial set reaches it (their nominal fits end within 3.5 σ). 0: off.
    - max_seconds: the loop's time budget (null: none): after it no further route is started (the first always
      runs to its end, and a route under way finishes); the report lists the routes left as skipped and the
      conclusion says so. A record with structure left runs the loop again from other nominal fits, which on a
      large effect with the slow backlash kernel took over an hour (docs/discovery.md, the 0.2-mm lash probe).
    - routes: when the loop runs again from the further nominal fits it is given (:mod:`.routes`): ``unexplained``
      (when structure is left after the first run: before saying so, try another nominal basin), ``always`` or
      ``never``; route_rtol: a route whose baseline RMS agrees with an earlier route's to this (relative) lies in
      the same basin and is skipped. route_max_ratio: an alternative route (another method's nominal fit) whose
      baseline RMS is more than this many times the lowest route's so far is a worse optimum of the nominal model,
      not a near-equal one, and is skipped (0: every alternative runs). The near-equal optima the routes are for
      lie within 1.13 of each other where measured (rec12: 2.028–2.13 µm; rec17: 8.048 and 9.104 µm; rec22: 3.073
      and 3.077 µm); the far ones at 1.97–44 (rec01: 5.93 against 3.00 µm; rec45: 29.0 against 3.05; rec47: 21.8
      against 1.59; rec11: 126.8 against 2.86), where the fast route's loop ran 19–41 min (rec45, rec01, rec47,
      rec21) to end where it began, never reported (docs/discovery.md, *routes*).
    - glitch_k: samples of the baseline's residual that jump away from their neighbours by more than this many robust
      standard deviations are glitches of the measurement (:func:`toggle_id.residuals.glitches`), reported and
      left out of every fit and test (the model takes them as measured); 0: none looked for.
    - robust_structure: the structure test's verdict from the smaller of its classical statistic and the robust one
      (:func:`.stats.structure_test`: local noise variances from first differences, under an AR model whose
      order a heteroscedasticity-robust criterion chose) instead of the classical one alone. Noise that is
      louder in motion is then not read as structure (rec19's machine, fits linearised, 40 draws: classical 40,
      robust 2 at the 1 % level), and what an outside effect leaves where the residual is large is still found
      (smooth at 1 kHz, it barely enters the differences: rec22's drag 258 on 3 dof, the bump of rec01 3324 on
      12). Both statistics are always reported; false: the classical verdict alone.
    - prediction_error: fit every model of the loop the prediction-error way (Ljung ch. 7): least squares on the
      residual prewhitened by the AR model of the current model's residual less what functions of the states and
      the input express (:func:`.residual.fitting_noise`; estimated for the baseline and again after each
      accepted effect), instead of ordinary least squares. Where that noise model is white the least-squares fit
      is kept. The judge's comparisons refit both models under the larger one's noise model either way; the fits
      the loop reports must show the gain too (check ``reported_fits``), and with ordinary least squares a
      coloured record's judge and fits can disagree: on rec33 (a slider viscous friction under AR(1) noise,
      ρ = 0.9) the prewhitened refits favour the friction (F 84.8) while its least-squares refit leaves it at
      "off"; with prediction-error fits it is accepted (README, adversarial table). false: least squares.
    - unconverged_share: the structure test also asks whether the fit reached its minimum
      (:func:`.localise.convergence`): a fit is unconverged, its structure left, when its own parameters explain
      more than this share of its whitened residual at the test's level (a fit stopped far off: 0.5–0.98; converged
      fits: below 0.01, a backlash fit's kink included).
    - min_effective_fraction: the final residual's noise model must leave at least this share of its samples
      independent (:attr:`.noise.NoiseModel.effective_fraction`; AR(1): (1 − ρ)/(1 + ρ), 0.02 at ρ ≈ 0.96, a
      correlation time of ~25 samples). A noise model slower than that is as slow as the motion, and a slow error
      the model lacks passes for it: structure is then left (the result unexplained) and no effect accepted under
      it is called added (:func:`.residual.slow_noise`). 0 turns the check off.
    - level_min_count: the heteroscedasticity-robust F-test reads the noise's variance from its level along the
      motion and time (bins of at least this many samples, :func:`.localise.level_basis`) instead of each
      sample's squared residual alone, which a few large residuals can dominate (:func:`.stats.robust_f`;
      100 is the tried value). 0 (the default): per sample (HC3). Opt-in until the adversarial set is re-run with
      it: the per-sample form also blocks stand-ins whose influence sits where a missing effect leaves the residual
      large, and the level form lets several of those through (docs/discovery.md, *Open problems*).
    - pair_look: where the current model and every supported single refit of a step lie above ``pair_above``
      times the record's own noise (its third differences, :func:`toggle_id.fast.difference_noise`) and what the
      step leaves holds structure by the noise-aware structure test (:func:`.residual.structure_left_at`), the pairs
      of this many single refits of lowest error are refitted together and judged (:mod:`.pairs`), until one ends
      within that band; a supported pair lower than the step's best single effect, significant beside it where
      it is one of the two, and, above the band, leaving no structure, adds both. 0 (the default): off. Opt-in until the adversarial set is re-run with it.
    - pe_guard_alpha: with ``prediction_error``, a prediction-error fit whose raw SSE exceeds the least-squares
      fit it started from by more than the noise allows at this level (:func:`.noise.prediction_error_drift`) is
      refused and that model is fitted by least squares (asked again of the next); and the judge, when the larger
      model's refit under the noise model of its residual drifts so, judges the loop's least-squares fits unwhitened
      with the F-test and BIC deflated by the residual's serial correlation (:meth:`.validation.Judge.serial_evidence`;
      on rec15_d1 it found the true offset and then let two stand-ins through). 0 (the default): off; opt-in until
      the set is re-run with it.
    """

    top_k: int = 3
    alpha: float = 1e-3
    max_effects: int = 3
    candidates: tuple[str, ...] | None = None
    screen_alpha: float = 0.01
    alpha_diag: float = 0.01
    acf_lags: int = 20
    ccf_lags: int = 50
    ccf_step: int = 5
    baseline_nfev: int = 60
    refit_nfev: int = 40
    null_nfev: int = 30
    scout_nfev: int = 8
    refit_rounds: int = 2
    rounds: int = 3
    second_point: bool = True
    gauge: bool = True
    hold_gauge: bool = True
    grid_points: int = 10
    fd_tier: str = "precise"
    jacobian_reuse: int = 0
    screen_tier: str = "precise"
    derivatives: str = "fd"
    fd_rel_step: float = 1e-4
    jac_rel_step: float = 1e-4
    rank_rtol: float = 1e-7
    absorbed_ratio: float = 1e-4
    noise_std: float | None = None
    parallel: bool = True
    noise_max_order: int = 8
    cv_folds: int = 5
    cv_block: int = 10
    cv_alpha: float = 0.5
    cv_rcond: float = 1e-8
    bonferroni: bool = True
    structure_bins: int = 12
    scout_all: bool = True
    next_leaders: bool = True
    backward: bool = True
    explain_fraction: float = 0.5
    validation_material: float = 1.5
    catch_all: bool = True
    catch_all_keep: float = 0.1
    catch_all_calibrated: bool = True
    catch_all_share_min: float = 0.02
    cogging_whole_tol: float = 0.1
    signature_min_periods: float = 10.0
    cogging_min_periods: float = 10.0
    beside_generic: bool = True
    ambiguity_alpha: float = 0.05
    encompassing: bool = True
    stronger_starts: tuple[float, ...] = (3.0, 10.0)
    weaker_starts: tuple[float, ...] = (1 / 3, 1 / 10)
    reanchor_rtol: float = 0.1
    edge_widen: float = 2.0
    edge_widenings: int = 1
    rescreen_points: int = 61
    rescreen_span: float = 0.25
    rescreen_prominence: float = 0.1
    other_starts_above: float = 5.0
    routes: str = "unexplained"
    route_rtol: float = 1e-3
    route_max_ratio: float = 1.5
    max_seconds: float | None = None
    glitch_k: float = 8.0
    robust_structure: bool = True
    prediction_error: bool = True
    unconverged_share: float = 0.1
    min_effective_fraction: float = 0.02
    level_min_count: int = 0
    pe_guard_alpha: float = 0.0
    pair_look: int = 0
    pair_above: float = 1.2

    @property
    def jacobian(self) -> tuple[SolverSettings, float]:
        """The integrator and relative step of the polishes' finite-difference Jacobians (``fd_tier``)."""
        return precise_jacobian(self.fd_tier, self.fd_rel_step)

    @property
    def screen(self) -> tuple[SolverSettings, float] | None:
        """The integrator and relative step of the screening (``screen_tier``); None: as the loop's own."""
        return None if self.screen_tier == "precise" else precise_jacobian(self.screen_tier, self.fd_rel_step)

    def validate(self) -> DiscoverSettings:
        """Raise ConfigError naming the first bad value; normalise ``candidates``."""
        for name in ("alpha", "screen_alpha", "alpha_diag", "fd_rel_step", "jac_rel_step", "rank_rtol",
                     "absorbed_ratio", "noise_std"):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))):
                raise ConfigError(f"discover.{name} must be a number, got {v!r}")
        if not isinstance(self.top_k, int) or self.top_k < 1:
            raise ConfigError(f"discover.top_k must be a positive integer, got {self.top_k!r}")
        if not 0.0 < float(self.alpha) < 1.0:
            raise ConfigError(f"discover.alpha must lie in (0, 1), got {self.alpha!r}")
        if not 0.0 < float(self.screen_alpha) <= 1.0:
            raise ConfigError(f"discover.screen_alpha must lie in (0, 1], got {self.screen_alpha!r}")
        if not 0.0 < float(self.alpha_diag) < 1.0:
            raise ConfigError(f"discover.alpha_diag must lie in (0, 1), got {self.alpha_diag!r}")
        reuse = self.jacobian_reuse
        if not isinstance(reuse, int) or isinstance(reuse, bool) or reuse < 0:
            raise ConfigError(f"discover.jacobian_reuse must be a non-negative integer (0: off), "
                              f"got {self.jacobian_reuse!r}")
        if not isinstance(self.max_effects, int) or self.max_effects < 0:
            raise ConfigError(f"discover.max_effects must be a non-negative integer, got {self.max_effects!r}")
        for name in ("acf_lags", "ccf_lags", "ccf_step", "baseline_nfev", "refit_nfev", "null_nfev", "scout_nfev",
                     "grid_points", "rounds", "refit_rounds", "cv_block", "structure_bins"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise ConfigError(f"discover.{name} must be a positive integer, got {v!r}")
        for name in ("fd_rel_step", "jac_rel_step", "rank_rtol", "absorbed_ratio"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0.0 < float(v) < 1.0):
                raise ConfigError(f"discover.{name} must lie in (0, 1), got {v!r}")
        if isinstance(self.glitch_k, bool) or not isinstance(self.glitch_k, (int, float)) or not self.glitch_k >= 0:
            raise ConfigError(f"discover.glitch_k must be a number ≥ 0 (0: off), got {self.glitch_k!r}")
        for name in ("robust_structure", "encompassing", "prediction_error", "beside_generic", "bonferroni"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"discover.{name} must be true or false, got {getattr(self, name)!r}")
        if self.derivatives not in DERIVATIVES:
            raise ConfigError(f"discover.derivatives must be one of {', '.join(DERIVATIVES)}, "
                              f"got {self.derivatives!r}")
        for name in ("fd_tier", "screen_tier"):
            if getattr(self, name) not in FD_TIERS:
                raise ConfigError(f"discover.{name} must be one of {', '.join(FD_TIERS)}, got {getattr(self, name)!r}")
        if not isinstance(self.noise_max_order, int) or isinstance(self.noise_max_order, bool) or \
                self.noise_max_order < 0:
            raise ConfigError(f"discover.noise_max_order must be a non-negative integer, got {self.noise_max_order!r}")
        if not isinstance(self.cv_folds, int) or isinstance(self.cv_folds, bool) or self.cv_folds < 2:
            raise ConfigError(f"discover.cv_folds must be an integer ≥ 2, got {self.cv_folds!r}")
        if isinstance(self.cv_alpha, bool) or not isinstance(self.cv_alpha, (int, float)) \
                or not 0.0 < float(self.cv_alpha) <= 0.5:
            raise ConfigError(f"discover.cv_alpha must lie in (0, 0.5], got {self.cv_alpha!r}")
        if isinstance(self.cv_rcond, bool) or not isinstance(self.cv_rcond, (int, float)) \
                or not 0.0 < float(self.cv_rcond) < 1.0:
            raise ConfigError(f"discover.cv_rcond must lie in (0, 1), got {self.cv_rcond!r}")
        if isinstance(self.unconverged_share, bool) or not isinstance(self.unconverged_share, (int, float)) \
                or not 0.0 <= self.unconverged_share < 1.0:
            raise ConfigError(f"discover.unconverged_share must lie in [0, 1), got {self.unconverged_share!r}")
        if isinstance(self.min_effective_fraction, bool) or not isinstance(self.min_effective_fraction, (int, float)) \
                or not 0.0 <= self.min_effective_fraction < 1.0:
            raise ConfigError("discover.min_effective_fraction must lie in [0, 1), got "
                              f"{self.min_effective_fraction!r}")
        if not isinstance(self.level_min_count, int) or isinstance(self.level_min_count, bool) \
                or self.level_min_count < 0:
            raise ConfigError(f"discover.level_min_count must be a non-negative integer (0: per sample), "
                              f"got {self.level_min_count!r}")
        if not isinstance(self.pair_look, int) or isinstance(self.pair_look, bool) or self.pair_look < 0:
            raise ConfigError(f"discover.pair_look must be a non-negative integer (0: off), got {self.pair_look!r}")
        if isinstance(self.pair_above, bool) or not isinstance(self.pair_above, (int, float)) or self.pair_above < 1:
            raise ConfigError(f"discover.pair_above must be a number ≥ 1 (times the record's noise), "
                              f"got {self.pair_above!r}")
        if isinstance(self.pe_guard_alpha, bool) or not isinstance(self.pe_guard_alpha, (int, float)) \
                or not 0.0 <= self.pe_guard_alpha < 1.0:
            raise ConfigError(f"discover.pe_guard_alpha must lie in [0, 1) (0: off), got {self.pe_guard_alpha!r}")
        if not (isinstance(self.explain_fraction, (int, float)) and 0.0 < float(self.explain_fraction) < 1.0):
            raise ConfigError(f"discover.explain_fraction must lie in (0, 1), got {self.explain_fraction!r}")
        if not (isinstance(self.validation_material, (int, float)) and not isinstance(self.validation_material, bool)
                and float(self.validation_material) >= 1.0):
            raise ConfigError(f"discover.validation_material must be a number ≥ 1, got {self.validation_material!r}")
        for name in ("catch_all_keep", "catch_all_share_min"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and not isinstance(value, bool) and 0.0 <= float(value) < 1.0):
                raise ConfigError(f"discover.{name} must lie in [0, 1), got {value!r}")
        if not (isinstance(self.cogging_whole_tol, (int, float)) and not isinstance(self.cogging_whole_tol, bool)
                and 0.0 <= float(self.cogging_whole_tol) <= 0.5):
            raise ConfigError(f"discover.cogging_whole_tol must lie in [0, 0.5], got {self.cogging_whole_tol!r}")
        if isinstance(self.signature_min_periods, bool) or not isinstance(self.signature_min_periods, (int, float)) \
                or not float(self.signature_min_periods) >= 3.0:
            raise ConfigError("discover.signature_min_periods must be a number >= 3 (the periodic look's own "
                              f"minimum), got {self.signature_min_periods!r}")
        if isinstance(self.cogging_min_periods, bool) or not isinstance(self.cogging_min_periods, (int, float)) \
                or not (float(self.cogging_min_periods) == 0.0 or float(self.cogging_min_periods) >= 3.0):
            raise ConfigError("discover.cogging_min_periods must be 0 (off) or a number >= 3, got "
                              f"{self.cogging_min_periods!r}")
        if not (isinstance(self.ambiguity_alpha, (int, float)) and not isinstance(self.ambiguity_alpha, bool)
                and 0.0 <= float(self.ambiguity_alpha) < 1.0):
            raise ConfigError(f"discover.ambiguity_alpha must lie in [0, 1), got {self.ambiguity_alpha!r}")
        factors = self.stronger_starts
        if isinstance(factors, (int, float)) or not all(
                isinstance(f, (int, float)) and not isinstance(f, bool) and f >= 1 for f in factors):
            raise ConfigError(f"discover.stronger_starts must be a list of numbers ≥ 1, got {factors!r}")
        self.stronger_starts = tuple(float(f) for f in factors)
        factors = self.weaker_starts
        if isinstance(factors, (int, float)) or not all(
                isinstance(f, (int, float)) and not isinstance(f, bool) and 0 < f < 1 for f in factors):
            raise ConfigError(f"discover.weaker_starts must be a list of numbers in (0, 1), got {factors!r}")
        self.weaker_starts = tuple(float(f) for f in factors)
        if not (isinstance(self.reanchor_rtol, (int, float)) and not isinstance(self.reanchor_rtol, bool)
                and np.isfinite(self.reanchor_rtol)):
            raise ConfigError(f"discover.reanchor_rtol must be a number (≤ 0: off), got {self.reanchor_rtol!r}")
        if isinstance(self.edge_widen, bool) or not isinstance(self.edge_widen, (int, float)) \
                or not float(self.edge_widen) > 1.0 or not np.isfinite(self.edge_widen):
            raise ConfigError(f"discover.edge_widen must be a number above 1, got {self.edge_widen!r}")
        if isinstance(self.edge_widenings, bool) or not isinstance(self.edge_widenings, int) \
                or self.edge_widenings < 0:
            raise ConfigError(f"discover.edge_widenings must be a whole number ≥ 0 (0: off), got "
                              f"{self.edge_widenings!r}")
        if isinstance(self.rescreen_points, bool) or not isinstance(self.rescreen_points, int) \
                or not (self.rescreen_points == 0 or self.rescreen_points >= 3):
            raise ConfigError(f"discover.rescreen_points must be 0 (off) or a whole number ≥ 3, got "
                              f"{self.rescreen_points!r}")
        for key in ("rescreen_span", "rescreen_prominence"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (np.isfinite(v) and v > 0):
                raise ConfigError(f"discover.{key} must be a positive number, got {v!r}")
        if isinstance(self.other_starts_above, bool) or not isinstance(self.other_starts_above, (int, float)) \
                or not (self.other_starts_above == 0 or self.other_starts_above >= 1):
            raise ConfigError("discover.other_starts_above must be 0 (off) or a number >= 1 (times the record's "
                              f"noise), got {self.other_starts_above!r}")
        if self.routes not in ("unexplained", "always", "never"):
            raise ConfigError(f"discover.routes must be 'unexplained', 'always' or 'never', got {self.routes!r}")
        if self.max_seconds is not None and (isinstance(self.max_seconds, bool) or not isinstance(
                self.max_seconds, (int, float)) or not 0 < float(self.max_seconds) < float("inf")):
            raise ConfigError(f"discover.max_seconds must be a positive number of seconds or null (no budget), got "
                              f"{self.max_seconds!r}")
        if not (isinstance(self.route_max_ratio, (int, float)) and not isinstance(self.route_max_ratio, bool)
                and (self.route_max_ratio == 0 or self.route_max_ratio > 1)):
            raise ConfigError(f"discover.route_max_ratio must be a number above 1 (0: off), got "
                              f"{self.route_max_ratio!r}")
        if not (isinstance(self.route_rtol, (int, float)) and not isinstance(self.route_rtol, bool)
                and 0.0 <= float(self.route_rtol) < 1.0):
            raise ConfigError(f"discover.route_rtol must lie in [0, 1), got {self.route_rtol!r}")
        for name in ("scout_all", "next_leaders", "backward", "catch_all", "catch_all_calibrated"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"discover.{name} must be true or false, got {getattr(self, name)!r}")
        if self.noise_std is not None and not (np.isfinite(self.noise_std) and self.noise_std > 0):
            raise ConfigError(f"discover.noise_std must be a positive number of metres or null, got {self.noise_std!r}")
        if self.candidates is not None:
            if isinstance(self.candidates, str):
                self.candidates = None if self.candidates == "all" else (self.candidates,)
            if self.candidates is not None:
                names = tuple(str(c) for c in self.candidates)
                unknown = [c for c in names if c not in EFFECTS_BY_NAME]
                if unknown:
                    raise ConfigError(f"discover.candidates: unknown effect(s) {', '.join(unknown)}; "
                                      f"known: {', '.join(EFFECTS_BY_NAME)}")
                self.candidates = names
        return self

    @classmethod
    def from_dict(cls, node: Mapping[str, Any] | None) -> DiscoverSettings:
        """Settings from a config node; unknown keys are a ConfigError."""
        node = dict(node or {})
        known = {f for f in cls.__dataclass_fields__}
        extra = sorted(set(node) - known - {"nominal", "base", "alternatives", "restarts"})
        if extra:
            raise ConfigError(f"discover: unknown setting(s) {', '.join(extra)}; known: {', '.join(sorted(known))}")
        kw = {k: v for k, v in node.items() if k in known}
        for key in ("candidates", "stronger_starts", "weaker_starts"):
            if isinstance(kw.get(key), (list, tuple)):
                kw[key] = tuple(kw[key])
        return cls(**kw).validate()


@dataclass
class DiscoverJobSettings(DiscoverSettings):
    """The ``discover`` node of the discover job: the loop's settings (:class:`DiscoverSettings`) and where the
    nominal fit the loop starts from comes from (read by :mod:`toggle_id.app.discover`)."""

    nominal: str = "ga"  # ga: two-stage RGA + polish first | base: polish from the assigned values (+ base)
    #: overrides of the assigned values: a start of the baseline (beside the GA's) and the reference of the
    #: reported parameters along the exact symmetries
    base: dict[str, float] = field(default_factory=dict)
    #: identification methods whose nominal fits are further routes of the loop (:mod:`.routes`; fitted only when
    #: ``routes`` asks for them; the job's own ``method`` is left out): on cycling records the GA's and the fast
    #: fit's nominal optima can lie in different basins, and an effect refitted from one explains what it cannot
    #: from the other
    alternatives: tuple[str, ...] = ("fast",)
    #: further nominal fits of the job's own method from the seeds after its own (seed + 1, ...): routes only
    #: while no route has explained the record, and only from a baseline lower than every route's so far
    #: (:func:`.routes.more_routes`; the nominal fit of a record that lacks an effect is a multistart problem)
    restarts: int = 2
