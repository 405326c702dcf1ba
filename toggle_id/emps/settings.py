"""The numbers of the EMPS job a user may change (``emps`` node of conf/experiment/emps.yaml): the one home of
their defaults. :func:`toggle_id.app.emps.emps_settings` checks them and resolves the paths."""
from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class EmpsSimSettings:
    """The closed-loop simulator (:func:`toggle_id.emps.simulate_emps`)."""

    eps: float = 1e-4        # m/s, smoothing of sign(q̇) as tanh(q̇/eps)
    h_lambda: float = 0.5    # RK4 step bound h·λ (λ = stiffness of the friction law)
    n_sub_max: int = 5000    # most RK4 substeps per 1 ms sample before a row counts as a solver failure
    pulse_gain: float = 1.0  # V per unit of a record's pulses_N, added to the controller output before the 10 V
    #                          saturation: ν = sat(law + gain·pulse), force gtau·ν (0: leave the pulses out)


@dataclass
class EmpsSettings:
    """The ``emps`` node: where the records are, the discovery loop's levels and budgets, the simulator."""

    data_dir: str | None = None   # directory holding DATA_EMPS.mat (estimation) and DATA_EMPS_PULSES.mat
    #                               (validation); None: $TOGGLE_ID_EMPS_DIR if set. Then the official loader's cache
    #                               ~/.nonlinear_benchmarks/EMPS/ (and its subfolders). Each file's sha256 is checked.
    path: str | None = None       # your own estimation record instead (.csv t,vir,qm,qg[,pulses_N] or .mat); no hash
    validate: bool = True         # predict the validation record (validation.path, else the benchmark's
    #                               DATA_EMPS_PULSES.mat when found); nothing is ever fitted on it
    samples: int | None = None    # None: the whole estimation record; N: its first N samples (1 kHz)
    candidates: list[str] | None = None  # effects to try, None: all of toggle_id.emps.EFFECTS
    #                               (coulomb_friction, offset, stribeck_friction, asymmetric_friction)
    alpha: float = 0.01           # level of the prewhitened F-test an added effect must pass; it must also lower the
    #                               prewhitened BIC and, significantly (cv_alpha), the cross-validated whitened SSE
    #                               (as the toggle plant's effects)
    max_effects: int | None = None  # None: no limit on the number of effects added
    max_corr: float = 0.99        # largest |correlation| of a new parameter with the others (identifiability gate)
    noise_max_order: int = 8      # largest order of the AR noise model fitted (Yule-Walker, order by BIC) to the
    #                               larger model's residual of each comparison; 0: white noise assumed
    cv_block: int = 100           # samples per block of the time-block cross-validation (100 ms at 1 kHz)
    cv_folds: int = 5             # folds the blocks are dealt to in turn
    cv_alpha: float = 0.5         # level of the one-sided test the drop of the cross-validated SSE must pass
    #                               against the noise's spread of it (0.5: any drop; discovery.stats.out_of_sample)
    bonferroni: bool = True       # a round chooses among the m candidates it refits: their F-tests at alpha / m
    structure_bins: int = 12      # bins per signal of the structure test of the final position residual (position,
    #                               position signed by the direction of motion and velocity tested; drive force,
    #                               controller output and time shown; toggle_id.discovery.localise)
    structure_alpha: float = 0.01  # its level, Bonferroni-corrected over the tested signals
    backward: bool = True         # backward elimination of the accepted effects (toggle_id.discovery.engine)
    explain_fraction: float = 0.5  # with structure left, an accepted effect that removed less than this share of
    #                                the structure energy is listed as compensating, not added
    ambiguity_alpha: float = 0.05  # two effects that pass the same round and that the record cannot tell apart
    #                                (Vuong's test at this level) are reported as ambiguous, neither as added (0: off)
    glitch_k: float = 8.0         # glitches of the measurement: a sample of the nominal fit's residual off all four
    #                               straight lines through its neighbours by more than this many robust σ, its
    #                               neighbours not, is left out of every fit and test (toggle_id.residuals.glitches;
    #                               0: no look)
    solver: str = "polish"        # polish (toggle_id.polish, log space for M) | scipy (least_squares trf)
    max_nfev: int = 50            # residual evaluations per output-error fit
    reference_fit: bool = True    # also fit the benchmark's own structure (M, Fv, Fc, offset) by output error
    sim: EmpsSimSettings = field(default_factory=EmpsSimSettings)
