"""The float32 edges the numerics are held at: the extreme values, the documented ranges of the feature table,
features at their ends, and the hypothesis strategies of float32 images and renders."""

import numpy as np
from hypothesis import HealthCheck
from hypothesis import strategies as st

from prep import exr as _exr
from prep.colour import LOG_COLOUR_MAX, REL_EPS
from prep.features import NUM_FEATURES

F32_MAX = float(np.finfo(np.float32).max)
F32_TINY = float(np.finfo(np.float32).smallest_subnormal)
F32_EPS = float(np.finfo(np.float32).eps)
HALF_MAX = float(np.finfo(np.float16).max)
# The largest relative variance a float32 render can give: a depth variance of float32 max at a miss
# (d = 0) in an image whose largest depth is the smallest subnormal (depth scale 1 / F32_TINY).
RELVAR_BOUND = float(np.log1p(F32_MAX / F32_TINY**2 / REL_EPS))
# (first channel, stop, lowest, highest): the table of prep/features.py, each bound derived from the
# module's constants or from the clip range its formula names.
FEATURE_RANGES = [
    (0, 3, 0.0, LOG_COLOUR_MAX),  # colour
    (3, 6, -LOG_COLOUR_MAX, LOG_COLOUR_MAX),  # dx colour
    (6, 9, -2.0, 2.0),  # dx normal: normal clipped to [-1, 1]
    (9, 12, -1.0, 1.0),  # dx albedo: albedo clipped to [0, 1]
    (12, 13, -1.0, 1.0),  # dx depth: depth scaled to [0, 1]
    (13, 16, -LOG_COLOUR_MAX, LOG_COLOUR_MAX),  # dy of the same
    (16, 19, -2.0, 2.0),
    (19, 22, -1.0, 1.0),
    (22, 23, -1.0, 1.0),
    (23, 27, 0.0, RELVAR_BOUND),  # relative variances
]


def extreme_features(shape, seed: int) -> np.ndarray:
    """Features with every channel at the low end, the high end of its documented range, or 0."""
    rng = np.random.default_rng(seed)
    x = np.empty(tuple(shape) + (NUM_FEATURES,), np.float32)
    for first, stop, lo, hi in FEATURE_RANGES:
        x[..., first:stop] = rng.choice([lo, hi, 0.0], size=tuple(shape) + (stop - first,))
    return x


PROPERTY = dict(deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])


SPECIAL_F32 = [0.0, F32_TINY, float(np.float32(1e-30)), 1.0, HALF_MAX, float(np.float32(1e20)), F32_MAX]


@st.composite
def float32_images(draw, shape, signed=True):
    """An image whose magnitudes are log-uniform over a drawn range of decades (subnormal to float32 max),
    with a few special values (0, the smallest subnormal, half max, float32 max) at drawn pixels."""
    size = int(np.prod(shape))
    kind = draw(st.sampled_from(["spread", "spread", "spread", "constant", "zero"]))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    if kind == "zero":
        return np.zeros(shape, np.float32)
    lo = draw(st.integers(-46, 38))
    hi = draw(st.integers(lo, 39))
    magnitude = np.minimum(10.0 ** rng.uniform(lo, hi, shape if kind == "spread" else ()), F32_MAX)
    image = np.broadcast_to(magnitude, shape).copy()
    if signed and draw(st.booleans()):
        image *= rng.choice([-1.0, 1.0], shape)
    specials = draw(st.lists(st.tuples(st.integers(0, size - 1), st.sampled_from(SPECIAL_F32), st.booleans()),
                             max_size=4))
    flat = image.reshape(-1)
    for index, value, negative in specials:
        flat[index] = -value if (negative and signed) else value
    return image.astype(np.float32)


@st.composite
def renders(draw, max_side=12):
    h = draw(st.integers(1, max_side))
    w = draw(st.integers(1, max_side))
    aovs = {name: draw(float32_images((h, w, 3))) for name in _exr.RGB_LAYERS}
    aovs.update({name: draw(float32_images((h, w))) for name in _exr.SCALAR_LAYERS})
    return aovs
