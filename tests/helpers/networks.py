"""Networks under test: the contract every custom Keras layer keeps, random weights, finite losses and
gradients."""

from pathlib import Path

import numpy as np


def randomise(model, seed: int = 0, scale: float = 0.3) -> None:
    """Replace every weight (the zero-initialised head too) by random values; BN variances stay positive."""
    rng = np.random.default_rng(seed)
    new = []
    for w in model.weights:
        shape = tuple(w.shape)
        if "variance" in w.path:
            new.append(rng.uniform(0.5, 1.5, size=shape))
        else:
            new.append(rng.normal(size=shape) * scale)
    model.set_weights([v.astype(np.float32) for v in new])


def check_keras_layer(make, shapes, tmp_path: Path, batch: int = 2, seed: int = 0) -> None:
    """The contract every custom Keras layer of kpcn keeps (after keras' own ``run_layer_test``), for the
    layer ``make()`` builds, on inputs of the per-sample ``shapes`` (one tuple per input):

    - serialisation: ``serialize_keras_object`` -> ``deserialize_keras_object`` without custom objects
      (the registration) and ``from_config(get_config())`` give a layer of the same type and config;
    - shape inference: ``compute_output_shape`` is the shape of the real output, and a symbolic call keeps
      unknown sizes unknown with the channels inferred;
    - saving: a model around it (a trainable 1x1 convolution on the first input, then the layer) saved and
      loaded gives the same layer types and bit-identical outputs;
    - a training step: finite loss and gradients, the convolution before the layer moves (the gradient
      passes through the layer), the layer's own trainable weights move and its frozen ones do not."""
    import keras
    import torch

    def to_np(x):
        return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)

    def one(xs):
        return xs if len(xs) > 1 else xs[0]

    layer = make()
    for clone in (keras.saving.deserialize_keras_object(keras.saving.serialize_keras_object(layer)),
                  type(layer).from_config(layer.get_config())):
        assert type(clone) is type(layer) and clone.get_config() == layer.get_config(), type(layer).__name__

    rng = np.random.default_rng(seed)
    x = [rng.uniform(0.0, 1.0, size=(batch, *s)).astype(np.float32) for s in shapes]
    got = to_np(make()(one(x)))
    assert tuple(make().compute_output_shape(one([a.shape for a in x]))) == got.shape, type(layer).__name__
    symbolic = make()(one([keras.KerasTensor((None, None, None, s[-1])) for s in shapes]))
    assert tuple(symbolic.shape) == (None, None, None, got.shape[-1]), (type(layer).__name__, symbolic.shape)

    inputs = [keras.Input(shape=(None, None, s[-1])) for s in shapes]
    pre = keras.layers.Conv2D(shapes[0][-1], 1, name="pre")
    layer = make()
    model = keras.Model(one(inputs), layer(one([pre(inputs[0]), *inputs[1:]])))
    before = to_np(model(one(x)))
    model.save(tmp_path / "layer.keras")
    loaded = keras.models.load_model(tmp_path / "layer.keras")
    assert [type(la) for la in loaded.layers] == [type(la) for la in model.layers]
    np.testing.assert_array_equal(to_np(loaded(one(x))), before)

    weights = {id(w): to_np(w.value).copy() for w in model.weights}
    frozen = {id(w) for w in model.non_trainable_weights}
    out = model(one([torch.tensor(a) for a in x]), training=True)
    loss = ((out - torch.tensor(before + 0.5)) ** 2).mean() + sum(model.losses)
    grads = torch.autograd.grad(loss, [w.value for w in model.trainable_weights])
    assert torch.isfinite(loss) and all(torch.isfinite(g).all() for g in grads), type(layer).__name__
    model.compile(optimizer=keras.optimizers.SGD(0.1), loss="mse")
    assert np.isfinite(model.train_on_batch(one(x), before + 0.5))
    for w in model.weights:
        moved = not np.array_equal(weights[id(w)], to_np(w.value))
        assert moved == (id(w) not in frozen), (type(layer).__name__, w.path, moved)


def finite_loss_and_gradients(model, x, gt, noisy):
    """SMAPE and asymmetric SMAPE of ``model`` (a keras.Model) in training mode, with their gradients;
    asserts all finite. Returns the output (a torch tensor)."""
    import torch

    from kpcn_keras.losses import SMAPE, AsymmetricSMAPE

    out = model(torch.as_tensor(x), training=True)
    gt_t = torch.as_tensor(gt)
    losses = {
        "smape": SMAPE()(gt_t, out),
        "asymmetric": AsymmetricSMAPE(2.0)(torch.as_tensor(np.concatenate([gt, noisy], axis=-1)), out),
    }
    variables = [w.value for w in model.trainable_weights]
    for name, loss in losses.items():
        assert torch.isfinite(loss), (name, loss)
        grads = torch.autograd.grad(loss, variables, retain_graph=True, allow_unused=True)
        for w, g in zip(model.trainable_weights, grads):
            assert g is None or torch.isfinite(g).all(), f"{name}: non-finite gradient of {w.path}"
    return out
