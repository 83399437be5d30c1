"""kpcn's Python API: read what a renderer wrote, denoise numpy arrays.

    import kpcn
    frame = kpcn.read("shot-00016spp.exr")         # any layout kpcn reads: kpcn, cycles, mitsuba, pbrt, rgb
    print(frame.layout, frame.inputs)             # e.g. "cycles no-variance"
    out = kpcn.denoise(frame, run="runs/default")  # (H, W, 3) float32, from every layer the frame has
    out = kpcn.denoise(colour, albedo=albedo, normal=normal, run="runs/default")  # numpy arrays, as pyoidn
    out = kpcn.denoise(frame_a, pair=frame_b, adapt=60)  # two halves: adapt to them 60 s, denoise their mean

:func:`read` is ``prep.layouts.read``; :func:`denoise` is ``kpcn_keras.api.denoise``, applied with
:class:`InferenceSettings` (``kpcn_keras.settings``: tile, precision, ensemble); it adapts to two halves
for seconds or by :class:`AdaptSettings` (steps, seed). Importing this package
imports neither keras nor torch; the first :func:`denoise` does. What a user can get wrong is a :class:`KpcnError`
with a one-line message (an array :func:`denoise` cannot take: :class:`ArrayError`, also a ``ValueError``).
"""

from prep.errors import ArrayError, KpcnError
from prep.layouts import Frame, read

__all__ = ["AdaptSettings", "ArrayError", "Frame", "InferenceSettings", "KpcnError", "denoise", "read"]


def denoise(*args, **kwargs):
    from kpcn_keras.api import denoise as _denoise

    return _denoise(*args, **kwargs)


denoise.__doc__ = "Denoise numpy arrays: see kpcn_keras.api.denoise."


def __getattr__(name: str):
    if name in ("InferenceSettings", "AdaptSettings"):  # when asked for: importing kpcn imports nothing of kpcn_keras
        from kpcn_keras import settings

        return getattr(settings, name)
    raise AttributeError(f"module 'kpcn' has no attribute {name!r}")
