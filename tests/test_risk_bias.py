"""The study of the adaptation guard's estimate (``kpcn_keras.studies.risk_bias``): its terms are the guard's own
figures and add up to the true change against the clean image."""

import numpy as np
import pytest

from kpcn_keras.config import DEFAULT_MODEL, MODELS_DIR
from kpcn_keras.run import Run
from kpcn_keras.serving import Serving
from kpcn_keras.settings import AdaptSettings
from kpcn_keras.studies import risk_bias
from prep.inputs import InputSet


@pytest.fixture(scope="module")
def terms():
    plain = Serving(Run(MODELS_DIR / DEFAULT_MODEL)).plain(InputSet(split=False, variance=False))
    a, b, clean = risk_bias.synthetic_pair("gamma", seed=3, size=96)
    settings = AdaptSettings(steps=30, seed=1, learning_rate=1e-2, crop=64, check_every=10)
    found = risk_bias.frame_terms(plain, a, b, clean, settings)
    assert found is not None, "no checkpoint chosen: the test frame no longer trains"
    return found


def test_the_first_term_and_the_estimate_at_the_halves_are_the_guards_own_estimated_change(terms):
    guard = terms["guard"]
    estimated = terms["first"]["mean"] + terms["estimate e=1"]["mean"]
    assert estimated == pytest.approx(guard["best"] - guard["initial"], rel=1e-4, abs=1e-9)


def test_the_first_term_and_the_true_covariance_term_add_up_to_the_true_change(terms):
    assert terms["first"]["mean"] + terms["true"]["mean"] == pytest.approx(terms["change"]["mean"], rel=1e-9,
                                                                            abs=1e-12)
    assert terms["miss e=1"]["mean"] == pytest.approx(terms["estimate e=1"]["mean"] - terms["true"]["mean"])


def test_the_mixes_run_from_one_render_to_the_other_through_their_mean():
    a, b, _ = risk_bias.synthetic_pair("gaussian", seed=0, size=8)
    for k in a:
        np.testing.assert_allclose(risk_bias.mix(a, b, 1.0)[k], a[k])
        np.testing.assert_allclose(risk_bias.mix(a, b, -1.0)[k], b[k])
        np.testing.assert_allclose(risk_bias.mix(a, b, 0.0)[k], (a[k].astype(np.float64) + b[k]) / 2, rtol=1e-6)
