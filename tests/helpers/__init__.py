"""What several test files share, one module per job; a test imports from the module it needs
(``from helpers.commands import run_main``), and the fixtures live in ``conftest.py``:

- ``paths``: the repository and the committed fixture renders;
- ``tiny``: small inputs (random renders in the AOV layout, tiny shard sets, tiny training configurations);
- ``commands``: the command line run as a user runs it (``kpcn``, in a fresh process), in this process
  (``run_main``), started to be killed (``start_kpcn``), under a launcher (``torchrun``), and the check of its
  one-line errors;
- ``files``: files left byte-identical (checksums) and a full disk (``SmallDisk``);
- ``networks``: the Keras layer contract, random weights, finite losses and gradients;
- ``numerics``: the float32 edges, the feature table's ranges and the hypothesis strategies of float32 renders;
- ``references``: float64 computations written independently of the library (features, PDFs, kernels,
  relSE, form factors, augmentation moves), which the code is held to;
- ``multiscale``: the multiscale tests' tiny compositor and float64 references of the pyramid's operations;
- ``exr_layouts``: EXR files in the layouts other renderers write (Cycles' passes, one part per pass);
- ``browser``: headless Chromium driving ``kpcn view``'s page;
- ``chi_square``: Pearson's chi-square test of drawn counts against expected ones, low cells pooled, with a
  Šidák correction for a family of tests;
- ``compiled``: the library's numba functions compiled into numba's disk cache before the workers start
  (conftest.py), and what a process loaded from that cache or compiled afresh."""

import os

# Keras on torch wherever a helper imports it, conftest.py or not
os.environ.setdefault("KERAS_BACKEND", "torch")
