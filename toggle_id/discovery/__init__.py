"""Model discovery: find what the model lacks, add it, and say how sure we are.

The loop (:func:`discover`, :mod:`.loop`) is the engine's (:func:`.engine.run_loop`, which the EMPS plant runs
too) over the toggle plant (:mod:`.toggle_plant`); it works on one record and the extended parameter vector of
:mod:`toggle_id.effects`; it never names an effect — it reads the library, so adding an effect is adding a kernel
term and an :class:`~toggle_id.effects.Effect` entry.

1. *Baseline* (:mod:`.model`): the nominal fit is polished on the whole record (PRECISE tier, log space, one
   parameter held per exact symmetry of x_B, :mod:`.gauge`), from every start; the best is the baseline. The
   polishes' Jacobians and the sensitivities come from :mod:`.derivatives` (finite differences, or forward
   sensitivities with ``discover.derivatives=analytic``).
2. *Noise model* (:mod:`.noise`): an AR(p) model of the residual. Every statistic is computed on prewhitened
   residuals and sensitivities, so coloured noise (a closed loop, an encoder) does not pass for an effect; the
   loop's fits minimise the residual prewhitened by the AR model of the current residual less what the states
   express (prediction-error fits, ``discover.prediction_error``; least squares where that model is white).
3. *Scores and scouts* (:mod:`.scoring`, :mod:`.refit`; one iteration of them and of the refits: :mod:`.forward`):
   the score (LM) test and a magnitude grid of every candidate up to its feasible bound at two linearisation points
   (the fit, and the nominal start with the effects so far), and a short refit (scout) of *every* candidate from its
   best grid start — threshold and periodic effects are silent at "off" but not at their magnitude.
4. *Refits and verdicts* (:mod:`.validation`, :mod:`.stats`): candidates are refitted in the order of their scouts,
   and no effect is accepted while a candidate whose scout explains more has not been refitted. A refit is judged
   under the noise model of its own residual (both models refitted the prediction-error way when it is coloured):
   prewhitened F-test and BIC, time-block cross-validation, and the prediction of a validation record when one is
   given. A nominal re-polish from the refit guards against a better nominal optimum. The candidate the score
   test ranks first is always refitted, whatever its scout. The best supported candidate joins the model; a rival
   that the record cannot tell from it (Vuong's test) is kept beside it as a tie; repeat.
5. *Backward elimination* (:mod:`.engine`): an accepted effect the others make unnecessary is dropped. Ties
   (:mod:`.ties`): one found while an effect was still missing is judged again on the final model; one Vuong's
   test leaves, by the model with both effects (an effect needed beside its rival, and not the reverse, is
   named); one still left, on a second record when there is one.
6. *What is left* (:mod:`.residual`, :mod:`.localise`): a structure test of the prewhitened residual against
   functions of position, velocity, current and input. When structure is left the result is *unexplained*, the
   report says where the residual concentrates, and an effect that removed less than ``explain_fraction`` of the
   structure energy is listed as *compensating* (it lowers the error but does not explain it), not as added; so
   is one that a generic force on slider B, any function of its speed and position, or a generic error of the
   position reading makes unnecessary (:mod:`.catchall`: stand-ins for physics outside the library).
7. *Routes* (:mod:`.routes`): before saying structure is left, the loop runs again from the other nominal fits it
   was given (the job gives the fast fit beside the GA's) — on a cycling record the nominal model has several
   optima far apart, and an effect refitted from one explains what it cannot from another; the route whose model
   the record supports is reported (Vuong's test; then explained, then fewer parameters).
8. *Report* (:mod:`.report`): parameters at the representative nearest the reference along the exact symmetries
   (force-type magnitudes are determined only relative to the mechanism's scale), the three lists with their
   evidence, figures. The job ``python -m jobs.run +experiment=discover`` (nominal fit, this loop, MLflow,
   ``discovery.json``) is :func:`toggle_id.app.discover.run_discover`.
"""
from __future__ import annotations

from .loop import discover
from .derivatives import sensitivities
from .model import Fit, Model, Projector, fit_free
from .report import DiscoveryResult
from .scoring import _magnitude_grid, score_candidates
from .settings import DiscoverSettings
from .stats import f_test

__all__ = ["DiscoverSettings", "DiscoveryResult", "Fit", "Model", "Projector", "discover", "f_test", "fit_free",
           "score_candidates", "sensitivities", "_magnitude_grid"]
