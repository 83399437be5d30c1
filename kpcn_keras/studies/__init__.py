"""The lab: studies and cost probes that measure the library rather than being it, all in this one package.

A study trains, denoises and times the library's pieces to answer one question, and writes a dated report
(``reports/<name>.{json,md,png}``, through :mod:`kpcn_keras.studies.report`, the one writer of the studies'
reports). The commands of ``kpcn``: ``compare`` (every configuration under one training budget), ``bench``
(what accuracy costs in time, with ``bench_stages``, ``bench_report``, ``data_costs``: features, EXR decoding and
shard layouts, ``network_costs``: kernel application and a training step against plain torch, ``plain_torch``),
``render_bench`` (``kpcn bench render``: the path tracer), ``resample_study`` (error-based resampling against
variance sampling), ``inputs_study``, ``quality`` (with ``frames``); and ``fresh_clone`` (``make train`` timed
from a fresh clone: ``make time-train``). Their configurations and tables are in
:mod:`kpcn_keras.studies.config`.

The probes run as ``python -m kpcn_keras.studies.<name>`` (each module's docstring has its usage): ``arch_costs``,
``denoise_costs``, ``slope_map_costs``, ``train_throughput`` (what a network, a denoise, a λ map and a training
step cost), ``error_tail``, ``frame_curve``, ``remodulation`` (where a frame's error is), ``blender_report``
(``make blender-report``: kpcn beside Blender's own denoiser), ``view_screenshot`` (``kpcn view``'s page in
headless Chromium, driven by :mod:`kpcn_keras.studies.browser`) and ``render_blender_pairs`` (the Blender pairs of
``kpcn inputs-study --pairs``, run by Blender's Python).

Importing this package imports nothing; a study imports keras or torch only where it needs them (``kpcn bench
render`` never does). The library (``prep`` and every other module of ``kpcn_keras``) never imports a study;
only the command line (``kpcn_keras.cli``, ``kpcn_keras.parser``) does, inside the study's command.
"""
