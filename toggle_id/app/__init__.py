"""The application layer: the jobs of ``python -m jobs.run``, each a function ``run_<job>(cfg, run_dir,
project_root) -> Path`` of a plain (Hydra-free) configuration that returns the path of its report.

Every job reads the same way: settings (validated before any work) -> build (the records, the tracker, the
evaluator) -> run the library function -> report (result files written atomically into the run directory, MLflow).

- :mod:`.common`: what the jobs share — the configuration's checks and dotted access, ``identify()``'s arguments
  from a config, the evaluator and the Ray session, the MLflow tracker, the config as JSON and as MLflow
  parameters, the published report;
- :mod:`.records`: the record(s) a job works on, from its ``data`` node (simulated from a truth, or read);
- :mod:`.job_report`: what an identification reports (model response, stage child runs, figures, console text);
- :mod:`.identify` (``job: identify``), :mod:`.table1`, :mod:`.study` (``job: identifiability``),
  :mod:`.discover`, :mod:`.emps`, :mod:`.excite`: one job each.

The library below never imports this package (``tests/test_architecture.py`` checks it); ``jobs/run.py`` maps a
job name to its function here. The package's ``__init__`` imports nothing, so a job loads only what it uses.
"""
