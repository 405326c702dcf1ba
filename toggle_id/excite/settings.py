"""The numbers of the excite job a user may change (``excite`` node of conf/experiment/excite.yaml)."""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any

from ..effects import ALL_INDEX, EFFECTS_BY_NAME
from ..errors import ConfigError

#: The input families the search knows (:mod:`toggle_id.excite.inputs`).
FAMILIES = ("sweep", "cycling", "multisine", "steps")


@dataclass
class RivalSpec:
    """A rival explanation named in the configuration: the effect ``effect`` switched on with ``params``
    (effect parameter → value; its magnitude must be non-zero) against the nominal model without it — or, with
    ``against``, against the nominal model with that other effect on instead (its parameters are where its fit
    starts; a refit moves them): two effects a record could not tell apart (a discovery's *ambiguous* pair)."""

    effect: str
    params: dict[str, float] = field(default_factory=dict)
    against: RivalSpec | None = None

    @property
    def key(self) -> str:
        """A name for metrics and logs: the effect, or ``A_vs_B``."""
        return self.effect if self.against is None else f"{self.effect}_vs_{self.against.effect}"

    @classmethod
    def from_dict(cls, d: Any, where: str = "excite.rivals") -> RivalSpec:
        if isinstance(d, str):
            raise ConfigError(f"{where}: {d!r} needs its magnitude, e.g. {{effect: {d}, params: {{...}}}}")
        if not isinstance(d, Mapping) or set(d) - {"effect", "params", "against"} or "effect" not in d:
            raise ConfigError(f"{where}: each rival is {{effect: NAME, params: {{NAME: VALUE}}}} (optionally "
                              f"against: {{effect: NAME, params: {{...}}}}), got {d!r}")
        name = d["effect"]
        if name not in EFFECTS_BY_NAME:
            raise ConfigError(f"{where}: unknown effect {name!r}; known: {', '.join(EFFECTS_BY_NAME)}")
        eff = EFFECTS_BY_NAME[name]
        params = dict(d.get("params") or {})
        for k, v in params.items():
            if k not in eff.names:
                raise ConfigError(f"{where}: {k!r} is not a parameter of {name} ({', '.join(eff.names)})")
            p = next(q for q in eff.params if q.name == k)
            try:
                v = float(v)
            except (TypeError, ValueError):
                raise ConfigError(f"{where}: {name}.{k} must be a number, got {v!r}") from None
            if not p.lower <= v <= p.upper:
                raise ConfigError(f"{where}: {name}.{k} = {v:g} is outside its domain [{p.lower:g}, {p.upper:g}]")
            params[k] = v
        mag = eff.magnitude
        if params.get(mag.name, mag.off) == mag.off:
            raise ConfigError(f"{where}: {name} needs a non-zero magnitude {mag.name} ({mag.unit})")
        against = d.get("against")
        if against is not None:
            if isinstance(against, Mapping) and against.get("against") is not None:
                raise ConfigError(f"{where}: {name}.against is one effect, not a chain")
            against = cls.from_dict(against, f"{where}: {name}.against")
            if against.effect == name:
                raise ConfigError(f"{where}: {name} cannot be its own rival (against: {name})")
        return cls(name, params, against)


@dataclass
class ExciteSettings:
    """Numbers of the excite job (conf/experiment/excite.yaml, node ``excite``).

    - Machine limits of a proposed input: ``v_max`` (V, |v_in| ≤ v_max), ``duration`` (s), ``rate_hz`` (Hz);
      ``x_B_min`` (m): slider B must stay above it; ``clamp_margin`` (m): x_B must pass x_B^L by this much to
      count as clamped; ``min_clamp_samples``: samples before the first clamp; ``min_exits``: times the
      slider must leave the clamp again ("into the clamp and back").
    - Search: ``families`` (of :data:`FAMILIES`), ``n_random`` accepted random candidates per family (at most
      ``random_tries`` × ``n_random`` tries), then the best candidate of each of the ``refine_starts`` best families
      refined by bounded Nelder–Mead in the unit cube of the family's parameters (first simplex ``refine_radius``
      wide), ``n_refine`` evaluations in all; ``seed``.
    - Scores: ``refit_top`` candidates (the best by the linearised score) verified by full refits of
      ``refit_nfev`` residual evaluations (``refit_rounds`` restarts); ``rival_nfev``: the fit of rival A to the
      record (``rival_rms_sigma``: a rival whose A or B leaves more than this many σ on the record is reported as
      not explaining it); ``fd_rel_step``: forward-difference step of the refits; ``jac_rel_step``: (log-)step of the
      linearised separation.
    - Rivals: ``rivals`` (:class:`RivalSpec`), ``discovery`` (a discovery.json whose accepted and compensating
      effects and ambiguous pairs become rivals), ``parameters`` (the weak directions of the 15 parameters as a rival),
      ``sv_index`` (the k-th singular value compared, 1-based).
    - Goals: ``separation_target`` (σ) and ``sv_gain_target`` (×) — a candidate's score is the smallest share of
      its goals it meets; ``noise_std_m``: σ (m; None: the simulated record's noise, else the nominal RMS).
    """

    # machine limits of the proposed input
    v_max: float = 0.3              # V: |v_in| <= v_max
    duration: float = 5.0           # s
    rate_hz: float = 1000.0         # Hz: the samples of excitation.csv
    x_B_min: float = 0.008          # m: slider B must stay above this (the stroke's short end)
    clamp_margin: float = 3e-4      # m: x_B must pass x_B^L = 56 mm by this to count as clamped ...
    min_clamp_samples: int = 30     # ... not before this sample ...
    min_exits: int = 1              # ... and leave the clamp again at least this often ("into the clamp and back")
    # the search (seeded: the same seed gives the same candidates and scores)
    families: tuple[str, ...] = FAMILIES  # of FAMILIES (toggle_id/excite/inputs.py FAMILY_PARAMS)
    n_random: int = 6               # random candidates accepted per family (uniform in the family's unit cube) ...
    random_tries: int = 3           # ... in at most this many times as many tries
    refine_starts: int = 2          # local refinement of the best candidate of each of this many best families ...
    n_refine: int = 120             # ... bounded Nelder–Mead, this many evaluations in all ...
    refine_radius: float = 0.15     # ... its first simplex this wide in the unit cube
    seed: int = 0
    # scores
    refit_top: int = 3              # candidates (best first-order score) verified by full refits, + each rival's best
    refit_nfev: int = 30            # residual evaluations of a verifying refit of rival B ...
    refit_rounds: int = 2           # ... restarted while it still improves
    rival_nfev: int = 40            # the fit of rival A (effect on) to the record
    rival_rms_sigma: float = 1.5    # a rival whose A or B leaves more than this many σ on the record is flagged
    fd_rel_step: float = 1e-4       # forward-difference step of the refits
    jac_rel_step: float = 1e-5      # (log-)step of the first-order separation's sensitivities
    # the rivals
    rivals: tuple[RivalSpec, ...] = field(default_factory=tuple)  # effect on (at its magnitude) vs the model without it, or vs another
    discovery: str | None = None    # a discovery.json: its accepted, compensating and ambiguous effects become rivals
    parameters: bool = True         # the 15 parameters' weak directions: the sv_index-th resolved singular value
    sv_index: int = 8
    # goals (a candidate's score is the smallest share of its goals it meets)
    separation_target: float = 3.0  # σ: the RMS difference left after refitting, over the noise
    sv_gain_target: float = 10.0    # ×: the sv_index-th resolved singular value over the record's (or a higher rank)
    noise_std_m: float | None = None  # σ (m); None: data.noise_m for a simulated record, else the nominal fit's RMS

    @classmethod
    def from_dict(cls, d: Mapping | None) -> ExciteSettings:
        d = dict(d or {})
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ConfigError(f"excite: unknown setting(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
        if "families" in d:
            fam = d["families"]
            d["families"] = (fam,) if isinstance(fam, str) else tuple(fam or ())
        if "rivals" in d:
            d["rivals"] = tuple(r if isinstance(r, RivalSpec) else RivalSpec.from_dict(r) for r in (d["rivals"] or ()))
        return cls(**d).validate()

    def validate(self) -> ExciteSettings:
        def number(name: str, lo: float, hi: float, open_lo: bool = True) -> None:
            v = getattr(self, name)
            ok = isinstance(v, (int, float)) and not isinstance(v, bool) and (lo < v if open_lo else lo <= v) and v <= hi
            if not ok:
                raise ConfigError(f"excite.{name} must lie in {'(' if open_lo else '['}{lo:g}, {hi:g}], got {v!r}")

        def whole(name: str, lo: int) -> None:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise ConfigError(f"excite.{name} must be a whole number >= {lo}, got {v!r}")

        number("v_max", 0.0, 10.0)
        number("duration", 0.0, 60.0)
        number("rate_hz", 0.0, 1e5)
        number("x_B_min", 0.0, 0.056, open_lo=False)
        number("clamp_margin", 0.0, 0.01, open_lo=False)
        number("refine_radius", 0.0, 1.0)
        number("fd_rel_step", 0.0, 0.1)
        number("jac_rel_step", 0.0, 0.1)
        number("separation_target", 0.0, 1e6)
        number("rival_rms_sigma", 0.0, 1e6)
        number("sv_gain_target", 0.0, 1e9)
        for name, lo in (("min_clamp_samples", 1), ("min_exits", 0), ("n_random", 1), ("n_refine", 0), ("seed", 0),
                         ("refine_starts", 1), ("random_tries", 1), ("refit_top", 1), ("refit_nfev", 1),
                         ("refit_rounds", 1), ("rival_nfev", 1), ("sv_index", 1)):
            whole(name, lo)
        if self.sv_index > 15:
            raise ConfigError(f"excite.sv_index must be at most 15 (the parameters), got {self.sv_index}")
        if not self.families or any(f not in FAMILIES for f in self.families):
            raise ConfigError(f"excite.families must name some of {', '.join(FAMILIES)}, got {list(self.families)}")
        if round(self.duration * self.rate_hz) < 100:
            raise ConfigError(f"excite: duration × rate_hz must give at least 100 samples, got "
                              f"{self.duration:g} s × {self.rate_hz:g} Hz")
        if not isinstance(self.parameters, bool):
            raise ConfigError(f"excite.parameters must be true or false, got {self.parameters!r}")
        if self.noise_std_m is not None:
            number("noise_std_m", 0.0, 1e-2)
        if self.discovery is not None and not isinstance(self.discovery, str):
            raise ConfigError(f"excite.discovery must be the path of a discovery.json, got {self.discovery!r}")
        for r in self.rivals:
            for k in r.params:
                assert k in ALL_INDEX
        return self
