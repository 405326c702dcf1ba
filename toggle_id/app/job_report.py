"""What an identification job reports: the model's response, one MLflow child run per stage, the figures and
the console text (used by :mod:`.identify`, :mod:`.table1` and :mod:`.discover`)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import console, figures
from .. import params as P
from ..effects import ALL_INDEX
from ..plant import impulse_force
from ..record import Record
from ..results import IdentificationResult, StageResult
from ..simulate import PRECISE, simulate
from ..tracking import Tracker


def model_response(record: Record, theta: np.ndarray) -> dict[str, np.ndarray]:
    """x_B, i_q and the impulse force F_i of ``theta`` on ``record`` (PRECISE)."""
    sim = simulate(theta[None, :], record, PRECISE)
    x = sim.x_B[0]
    xdot = np.gradient(x, record.t)
    return {"x_B": x, "i_q": sim.i_q[0], "F_i": impulse_force(x, xdot, theta[ALL_INDEX["D"]],
                                                              theta[ALL_INDEX["K_l"]]), "status": sim.status[0]}


def stage_child_run(tracker: Tracker, st: StageResult, truth: np.ndarray | None) -> None:
    """One MLflow child run per stage: its settings, fitness history, parameters, errors and timing."""
    with tracker.run(st.name, tags={"stage": st.name}, nested=True):
        tracker.log_params({"free": ",".join(st.free), "window": f"{st.window[0]}:{st.window[1]}"})
        tracker.log_metric_history("best_fitness", st.history, start_step=1)
        metrics = {"fitness": st.fitness, "fitness_ga": st.fitness_ga, "sse_m2": st.sse, "rmse_m": st.rmse_m,
                   "seconds_ga": st.seconds_ga, "seconds_polish": st.seconds_polish,
                   "converged_generation": st.converged_generation}
        metrics.update({f"param.{n}": float(v) for n, v in zip(st.free, st.x)})
        if truth is not None:
            metrics.update({f"pct_error.{n}": console.pct_error(truth[ALL_INDEX[n]], float(v))
                            for n, v in zip(st.free, st.x)})
        tracker.log_metrics(metrics)
        if st.identifiability:
            tracker.log_dict(st.identifiability, f"identifiability_{st.name}.json")


def write_figures(run_dir: Path, records: list[Record], result: IdentificationResult, tracker: Tracker,
                  label: str, responses: list[dict[str, np.ndarray]]) -> list[str]:
    """Fitness history and the paper's Fig. 7 panels (x_B, difference, impulse force, v_in) as PNGs, from the
    model's ``responses`` (:func:`model_response`) on ``records``.

    Several records (a joint fit): ``response.png`` for the first, ``response_<k>_<name>.png`` for the others.
    """
    clamp = [r["clamp_index"] for r in result.extra.get("records") or []] or [result.clamp_index]
    out = []
    fig = figures.fitness_history({s.name: s.history for s in result.stages if s.history})  # GA stages only
    out.append(figures.save(fig, run_dir / "fitness_history.png"))
    for k, (rec, k_c, resp) in enumerate(zip(records, clamp, responses)):
        t_c = rec.t[k_c] if k_c < rec.n else None
        title = "Measured and model responses" + (f" — {rec.name}" if len(records) > 1 else "")
        fig = figures.response_comparison(rec.t, rec.x_B, {label: resp["x_B"]}, stage_boundary=t_c,
                                          forces={label: resp["F_i"]}, v_in=rec.v_in, title=title)
        name = "response.png" if k == 0 else f"response_{k}_{rec.name}.png"
        out.append(figures.save(fig, run_dir / name))
    for path in out:
        tracker.log_artifact(path, "figures")
    return out


def console_report(result: IdentificationResult, truth: np.ndarray | None) -> str:
    """The paper's Table 1 for this run (assigned, identified, % error) and the identifiability tables."""
    assigned = None if truth is None else {n: float(truth[i]) for i, n in enumerate(P.PARAM_NAMES)}
    text = [console.param_table(list(P.PARAM_NAMES), {result.method: result.params}, assigned)]
    recs = result.extra.get("records") or []
    if recs:
        text.append(f"\njoint fit of {len(recs)} records:")
        text.extend(f"  {r['name']}: {r['n_samples']} samples, clamping at sample {r['clamp_index']}, "
                    f"RMS error {r['rmse_m'] * 1e6:.4g} µm" for r in recs)
    for st in result.stages:
        rep = st.identifiability
        if rep and "param_order" in rep:
            text.append(f"\nidentifiability ({st.name}): rank {rep.get('rank')} of {len(rep['param_order'])}, "
                        f"practical rank {rep.get('practical_rank')}")
            for combo in rep.get("null_combinations") or []:
                text.append(f"  not identifiable from {'these records' if recs else 'this record'}: {combo}")
    text.append(f"\nfitness {result.fitness:.6g}  SSE {result.sse:.4g} m²  RMS error {result.rmse_m * 1e6:.4g} µm  "
                f"time {result.seconds:.1f} s")
    return "\n".join(text)
