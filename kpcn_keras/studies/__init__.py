"""The studies: commands that measure the denoiser rather than being it.

A study trains, denoises and times the library's pieces to answer one question, and writes a dated report
(``reports/<name>.{json,md,png}``, through :mod:`prep.studies.report`): ``compare`` (every configuration
under one training budget), ``bench`` (what accuracy costs in time, with ``bench_stages`` and
``bench_report``), ``resample_study`` (error-based resampling against variance sampling), ``stage_costs``
and ``plain_torch`` (what each stage of training and inference costs, against plain torch), ``fresh_clone``
(``make train`` timed from a fresh clone: ``make time-train``). Their
configurations and tables are in :mod:`kpcn_keras.studies.config`.

The library (every other module of ``kpcn_keras``) never imports a study; only the command line
(``kpcn_keras.cli``) does, inside the study's command.
"""
