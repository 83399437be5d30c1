import numpy as np
import pytest
from helpers.references import moved
from helpers.tiny import random_aovs

from kpcn_keras import augment
from kpcn_keras.augment import (
    ALL,
    DX,
    DY,
    IDENTITY,
    Augmentation,
    augment_colour,
    augment_features,
    augment_spatial,
    draw,
    moved_box,
)
from prep import features

COLOUR_LAYERS = ("diffuse", "specular", "albedo", "default")


def transformed_aovs(aovs: dict, aug: Augmentation) -> dict:
    """The render of the augmented scene: every layer's pixels moved, the RGB of colour layers permuted."""
    return {name: moved(image[..., list(aug.colour)] if name in COLOUR_LAYERS else image, aug.spatial)
            for name, image in aovs.items()}


def some_colours():
    return [(0, 1, 2), (2, 0, 1), (1, 0, 2)]


@pytest.mark.parametrize("shape", [(9, 9, 29), (2, 8, 8, 29), (7, 5, 29)])
def test_every_augmentation_is_undone_bit_for_bit_by_its_inverse(shape):
    f = np.random.default_rng(0).normal(size=shape).astype(np.float32)
    for aug in ALL:
        once = augment_features(f, aug)
        assert not np.shares_memory(once, f)
        np.testing.assert_array_equal(augment_features(once, aug.inverse()), f)
        assert augment_features(once, aug.inverse()).tobytes() == f.tobytes()
        c = f[..., :3]
        assert augment_colour(augment_colour(c, aug), aug.inverse()).tobytes() == np.ascontiguousarray(c).tobytes()
        assert aug.inverse().inverse() == aug


def test_only_the_identity_leaves_a_patch_unchanged():
    f = np.random.default_rng(1).normal(size=(6, 6, 27)).astype(np.float32)
    for aug in ALL:
        assert (aug == IDENTITY) == np.array_equal(augment_features(f, aug), f)


@pytest.mark.parametrize("shape", [(9, 9), (7, 12)])
def test_a_moved_box_holds_the_moved_pixels_of_the_box(shape):
    x = np.random.default_rng(2).normal(size=(*shape, 2))
    rng = np.random.default_rng(5)
    for spatial in range(8):
        aug = Augmentation(spatial)
        for _ in range(20):
            y0, y1 = sorted(rng.choice(shape[0] + 1, 2, replace=False))
            x0, x1 = sorted(rng.choice(shape[1] + 1, 2, replace=False))
            b0, b1, c0, c1 = moved_box((y0, y1, x0, x1), shape, aug)
            np.testing.assert_array_equal(augment_spatial(x, aug)[b0:b1, c0:c1], augment_spatial(x[y0:y1, x0:x1], aug))
            moved_shape = augment_spatial(x, aug).shape[:2]
            assert moved_box((b0, b1, c0, c1), moved_shape, aug.inverse()) == (y0, y1, x0, x1)


@pytest.mark.parametrize("branch", features.BRANCHES)
@pytest.mark.parametrize("spatial", range(8))
def test_features_of_the_augmented_render_equal_the_augmented_features(branch, spatial):
    aovs = random_aovs(9, 9, seed=spatial)
    for colour in some_colours():
        aug = Augmentation(spatial, colour)
        got = augment_features(features.branch_features(aovs, branch), aug)
        want = features.branch_features(transformed_aovs(aovs, aug), branch)
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("spatial", range(8))
def test_features_commute_on_non_square_renders(spatial):
    aovs = random_aovs(7, 11, seed=3)
    aug = Augmentation(spatial, (2, 1, 0))
    got = augment_features(features.branch_features(aovs, "specular"), aug)
    want = features.branch_features(transformed_aovs(aovs, aug), "specular")
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)


def test_extra_channels_are_only_moved():
    rng = np.random.default_rng(2)
    f = rng.normal(size=(2, 8, 8, 30)).astype(np.float32)
    for aug in ALL:
        got = augment_features(f, aug)[..., 27:]
        want = augment.augment_spatial(f[..., 27:], Augmentation(aug.spatial))
        np.testing.assert_array_equal(got, want)
        assert np.sort(got, axis=None).tobytes() == np.sort(f[..., 27:], axis=None).tobytes()


def test_flip_x_of_the_dx_block_is_a_sign_changing_involution():
    f = np.random.default_rng(4).normal(size=(8, 8, 27)).astype(np.float32)
    flip = Augmentation(augment.FLIP_X)
    once = augment_features(f, flip)
    assert flip.inverse() == flip
    np.testing.assert_array_equal(augment_features(once, flip), f)
    assert np.abs(once[..., DX]).sum() == pytest.approx(np.abs(f[..., DX]).sum(), rel=1e-6)
    np.testing.assert_array_equal(np.sort(np.abs(once[..., DX]), axis=None), np.sort(np.abs(f[..., DX]), axis=None))
    np.testing.assert_array_equal(once[:, 0, DX], -f[:, 6, DX])
    np.testing.assert_array_equal(once[:, 7, DX], -f[:, 7, DX])  # the shifted-in column
    np.testing.assert_array_equal(once[..., DY], f[:, ::-1, DY])  # plain mirror, no sign


@pytest.mark.parametrize("branch", features.BRANCHES)
def test_augmented_colour_targets_equal_the_colour_of_the_augmented_render(branch):
    aovs = random_aovs(9, 9, seed=5)
    for aug in ALL:
        got = augment_colour(features.branch_colour(aovs, branch), aug)
        want = features.branch_colour(transformed_aovs(aovs, aug), branch)
        np.testing.assert_array_equal(got, want)


def test_colour_permutation_leaves_normals_depth_and_relvar_alone():
    f = np.random.default_rng(6).normal(size=(5, 5, 27)).astype(np.float32)
    got = augment_features(f, Augmentation(0, (2, 0, 1)))
    untouched = [i for i, n in enumerate(features.FEATURE_NAMES) if "normal" in n or "depth" in n or "relvar" in n]
    np.testing.assert_array_equal(got[..., untouched], f[..., untouched])
    np.testing.assert_array_equal(got[..., [0, 1, 2]], f[..., [2, 0, 1]])
    np.testing.assert_array_equal(got[..., DY][..., 6:9], f[..., DY][..., [8, 6, 7]])


def test_draw_is_deterministic_and_covers_all_48():
    a = [draw(np.random.default_rng(7)) for _ in range(3)]
    assert a[0] == a[1] == a[2]
    rng1, rng2 = np.random.default_rng(8), np.random.default_rng(8)
    seq1 = [draw(rng1) for _ in range(2000)]
    assert seq1 == [draw(rng2) for _ in range(2000)]
    assert set(seq1) == set(ALL) and len(ALL) == 48


@pytest.mark.parametrize("call, needle", [
    (lambda: augment_features(np.zeros((4, 4, 26)), IDENTITY), "(4, 4, 26)"),
    (lambda: augment_features(np.zeros((4, 27)), IDENTITY), "(4, 27)"),
    (lambda: augment_colour(np.zeros((4, 4, 4)), IDENTITY), "(4, 4, 4)"),
    (lambda: augment_features(np.zeros((4, 4, 27)), 3), "got 3"),
    (lambda: Augmentation(8), "got 8"),
    (lambda: Augmentation(-1), "got -1"),
    (lambda: Augmentation(True), "got True"),
    (lambda: Augmentation(0, (0, 0, 1)), "(0, 0, 1)"),
])
def test_invalid_input_raises_value_error_echoing_the_value(call, needle):
    with pytest.raises(ValueError) as err:
        call()
    assert needle in str(err.value)


def test_dtype_is_kept():
    f = np.arange(4 * 4 * 28, dtype=np.float64).reshape(4, 4, 28)
    assert augment_features(f, Augmentation(7, (1, 2, 0))).dtype == np.float64
    assert augment_features(f, Augmentation(7, (1, 2, 0))).shape == (4, 4, 28)
