"""kpcn's Python API: read what a renderer wrote, denoise numpy arrays.

    import kpcn
    frame = kpcn.read("shot-0016spp.exr")          # any layout kpcn reads: kpcn, cycles, mitsuba, pbrt, rgb
    print(frame.layout, frame.inputs)             # e.g. "cycles no-variance"
    out = kpcn.denoise(frame.layers["default"], albedo=frame.layers["albedo"], normal=frame.layers["normal"],
                       run="runs/default")         # (H, W, 3) float32

:func:`read` is ``prep.layouts.read``; :func:`denoise` is ``kpcn_keras.api.denoise``. Importing this package
imports neither keras nor torch; the first :func:`denoise` does.
"""

from prep.layouts import Frame, read

__all__ = ["Frame", "denoise", "read"]


def denoise(*args, **kwargs):
    from kpcn_keras.api import denoise as _denoise

    return _denoise(*args, **kwargs)


denoise.__doc__ = "Denoise numpy arrays: see kpcn_keras.api.denoise."
