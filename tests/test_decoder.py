"""HiDDeN decoder: shapes, whitening, weights I/O, shipped decoders, and a short training run."""

from __future__ import annotations

import dataclasses
import json
import zipfile
from pathlib import Path

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mnerf_jax.core.errors import MnerfError
from mnerf_jax.reader import decoder as dec
from mnerf_jax.reader import decoder_io, dwt, read_window
from mnerf_jax.reader.train import checkpoint as decoder_checkpoint
from mnerf_jax.reader.train import hidden_encoder, informed, recipe, stages
from mnerf_jax.reader.train import steps as decoder_steps


@pytest.fixture(scope="module")
def small_decoder() -> dict:
    """A 16-bit decoder with non-trivial BatchNorm statistics (as after training)."""
    variables = dec.init_decoder(jax.random.PRNGKey(0), 16)

    @jax.jit
    def perturb(stats: dict) -> dict:
        leaves, tree = jax.tree.flatten(stats)
        keys = jax.random.split(jax.random.PRNGKey(1), len(leaves))
        return jax.tree.unflatten(
            tree, [a + 0.2 * jax.random.uniform(k, a.shape) for a, k in zip(leaves, keys, strict=True)]
        )

    return {"params": variables["params"], "batch_stats": perturb(variables["batch_stats"])}


@pytest.mark.parametrize("bits", [8, 16, 32, 48])
def test_shapes(bits: int) -> None:
    # Shapes only (no compilation): the architecture for every supported message length.
    variables = jax.eval_shape(lambda: dec.init_decoder(jax.random.PRNGKey(bits), bits))
    assert dec.architecture(variables) == (bits, 64, 8)
    params = variables["params"]
    assert params["block_0"]["conv"]["kernel"].shape == (3, 3, 3, 64)
    assert all(params[f"block_{i}"]["conv"]["kernel"].shape == (3, 3, 64, 64) for i in range(1, 8))
    assert params["block_8"]["conv"]["kernel"].shape == (3, 3, 64, bits)
    assert params["linear"]["kernel"].shape == params["whiten"]["kernel"].shape == (bits, bits)
    assert variables["batch_stats"]["block_3"]["bn"]["var"].shape == (64,)
    ll2 = jax.ShapeDtypeStruct((2, 9, 7, 3), jnp.float32)
    assert jax.eval_shape(dec.apply_ll2, variables, ll2).shape == (2, bits)
    logits, stats = jax.eval_shape(dec.apply_ll2_train, variables, ll2)
    assert logits.shape == (2, bits)
    assert jax.tree.structure(stats) == jax.tree.structure(variables["batch_stats"])
    images = jax.ShapeDtypeStruct((3, 100, 100, 3), jnp.float32)  # LL2 25×25, as a 100² render
    assert jax.eval_shape(dec.decode_logits, variables, images).shape == (3, bits)


def test_forward_values(small_decoder: dict) -> None:
    fresh = dec.init_decoder(jax.random.PRNGKey(0), 16)
    np.testing.assert_array_equal(fresh["params"]["whiten"]["kernel"], np.eye(16))  # identity at init
    images = jax.random.uniform(jax.random.PRNGKey(2), (2, 36, 28, 3))
    ll2 = dwt.ll2(images)
    assert ll2.shape == (2, 9, 7, 3)
    logits = dec.decode_logits(small_decoder, images)  # takes the LL2 itself
    np.testing.assert_allclose(logits, dec.apply_ll2(small_decoder, ll2), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(dec.apply_ll2(fresh, ll2), dec.apply_ll2(fresh, ll2, whiten=False), atol=1e-6)
    # Eval mode uses the running statistics: changing them changes the output; train mode ignores them.
    shifted = {
        "params": small_decoder["params"],
        "batch_stats": jax.tree.map(lambda a: a + 1.0, small_decoder["batch_stats"]),
    }
    assert not np.allclose(dec.apply_ll2(shifted, ll2), dec.apply_ll2(small_decoder, ll2))
    np.testing.assert_allclose(
        dec.apply_ll2_train(shifted, ll2)[0], dec.apply_ll2_train(small_decoder, ll2)[0], rtol=1e-5, atol=1e-5
    )


def test_unsupported_bits() -> None:
    with pytest.raises(MnerfError, match="unsupported message length 12"):
        dec.init_decoder(jax.random.PRNGKey(0), 12)


def test_whitening_gives_identity_covariance(small_decoder: dict) -> None:
    images = jax.random.uniform(jax.random.PRNGKey(3), (160, 24, 24, 3))
    # Some structure so that the raw outputs are correlated, as on real images.
    images = images * jnp.linspace(0.2, 1.0, 160)[:, None, None, None]
    batches = [dwt.ll2(images[i : i + 40]) for i in range(0, 160, 40)]
    raw = np.concatenate([np.asarray(dec.apply_ll2(small_decoder, b, whiten=False)) for b in batches])
    raw_cov = np.cov(raw, rowvar=False, bias=True)
    assert np.abs(raw_cov - np.eye(16)).max() > 0.1  # not white to begin with

    whitened = dec.fit_whitening(small_decoder, batches)
    out = np.concatenate([np.asarray(dec.apply_ll2(whitened, b), np.float64) for b in batches])
    # float32 layer: the raw outputs have a large mean relative to their spread, so allow rounding.
    np.testing.assert_allclose(out.mean(axis=0), 0.0, atol=1e-2)
    np.testing.assert_allclose(np.cov(out, rowvar=False, bias=True), np.eye(16), atol=1e-2)
    # The raw path is untouched by the whitening layer.
    np.testing.assert_allclose(
        dec.apply_ll2(whitened, batches[0], whiten=False), raw[:40], rtol=1e-5, atol=1e-5
    )


def test_whitening_formula_on_correlated_gaussians() -> None:
    rng = np.random.default_rng(0)
    mix = rng.normal(size=(8, 8))
    x = rng.normal(size=(2000, 8)) @ mix.T + rng.normal(size=8)
    w, b = dec.whitening_from_outputs(x)
    y = x @ w.T + b
    np.testing.assert_allclose(y.mean(axis=0), 0.0, atol=1e-10)
    np.testing.assert_allclose(np.cov(y, rowvar=False, bias=True), np.eye(8), atol=1e-8)
    with pytest.raises(MnerfError, match="more images than bits"):
        dec.whitening_from_outputs(x[:5])


def test_batch_norm_calibration_makes_eval_mode_match_train_mode() -> None:
    variables = dec.init_decoder(jax.random.PRNGKey(0), 16)
    ll2 = dwt.ll2(jax.random.uniform(jax.random.PRNGKey(2), (24, 32, 32, 3)))
    train_logits, _ = dec.apply_ll2_train(variables, ll2)
    calibrated = dec.calibrate_batch_norm(variables, ll2)
    np.testing.assert_allclose(dec.apply_ll2(calibrated, ll2), train_logits, rtol=1e-3, atol=1e-4)
    # The params are untouched; only the running statistics moved (away from the init's 0 / 1).
    np.testing.assert_array_equal(
        calibrated["params"]["block_0"]["conv"]["kernel"], variables["params"]["block_0"]["conv"]["kernel"]
    )
    assert float(jnp.abs(calibrated["batch_stats"]["block_3"]["bn"]["mean"]).max()) > 1e-3


def test_fresh_decoder_has_unit_logits_and_a_moderate_whitening_gain() -> None:
    images = np.random.default_rng(0).uniform(0.2, 0.8, (40, 32, 32, 3)).astype(np.float32)
    fresh = decoder_io.fresh_decoder(16, images, max_images=40)
    logits = np.asarray(dec.decode_logits(fresh.variables, jnp.asarray(images)), np.float64)
    np.testing.assert_allclose(np.cov(logits, rowvar=False, bias=True), np.eye(16), atol=1e-2)
    # Uncalibrated BatchNorm left the raw outputs ~1e-3 apart and the whitening kernel ~4e3 (every decoder
    # step then moved the logits by ~1); calibrated, the gain stays moderate.
    assert float(np.abs(fresh.variables["params"]["whiten"]["kernel"]).max()) < 500.0


def test_filterbank_init_sets_the_first_block_to_signed_dct_patterns_and_the_middle_to_identity() -> None:
    variables = dec.init_decoder(jax.random.PRNGKey(3), 16)
    bank = dec.filterbank_init(variables)
    k0 = np.asarray(bank["params"]["block_0"]["conv"]["kernel"]).reshape(27, 64)
    filters = k0[:, :54]
    # Unit filters in ± pairs; the 27 distinct ones (9 patterns × 3 opponent colours) are orthonormal.
    np.testing.assert_allclose(np.linalg.norm(filters, axis=0), 1.0, atol=1e-6)
    np.testing.assert_allclose(filters[:, 0::2], -filters[:, 1::2], atol=0)
    np.testing.assert_allclose(filters[:, 0::2].T @ filters[:, 0::2], np.eye(27), atol=1e-6)
    np.testing.assert_array_equal(
        k0[:, 54:], np.asarray(variables["params"]["block_0"]["conv"]["kernel"]).reshape(27, 64)[:, 54:]
    )
    k1 = np.asarray(bank["params"]["block_1"]["conv"]["kernel"])
    r1 = np.asarray(variables["params"]["block_1"]["conv"]["kernel"])
    identity = np.zeros_like(r1)
    identity[1, 1] = np.eye(64)
    np.testing.assert_allclose(k1, 0.1 * r1 + identity, atol=1e-6)
    for name in ("block_8", "linear", "whiten"):  # left as initialised
        for a, b in zip(
            jax.tree.leaves(bank["params"][name]), jax.tree.leaves(variables["params"][name]), strict=True
        ):
            np.testing.assert_array_equal(a, b)
    assert dec.architecture(bank) == dec.architecture(variables)
    logits = dec.decode_logits(bank, jnp.full((2, 32, 32, 3), 0.5))
    assert logits.shape == (2, 16) and bool(jnp.all(jnp.isfinite(logits)))


def test_save_load_round_trip(tmp_path: Path, small_decoder: dict) -> None:
    path = tmp_path / "d.npz"
    meta = decoder_io.save_decoder(path, small_decoder, {"training": {"note": "unit test"}}, wavelet="haar")
    loaded = decoder_io.load_decoder(path, expect_bits=16)
    assert loaded.bits == 16 and loaded.wavelet == "haar" and loaded.fingerprint == meta["fingerprint"]
    assert loaded.metadata["training"] == {"note": "unit test"}
    assert decoder_io.fingerprint(loaded.variables) == decoder_io.fingerprint(small_decoder)
    for a, b in zip(jax.tree.leaves(loaded.variables), jax.tree.leaves(small_decoder), strict=True):
        np.testing.assert_array_equal(a, b)
    with np.load(path, allow_pickle=False) as data:  # a plain npz: no pickled objects anywhere
        assert all(data[name].dtype != object for name in data.files)


def test_bad_decoder_files(tmp_path: Path, small_decoder: dict) -> None:
    path = tmp_path / "d.npz"
    decoder_io.save_decoder(path, small_decoder)
    with pytest.raises(MnerfError, match="decodes 16-bit messages, but 48 bits are expected"):
        decoder_io.load_decoder(path, expect_bits=48)
    with pytest.raises(MnerfError, match="does not exist"):
        decoder_io.load_decoder(tmp_path / "absent.npz")

    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(MnerfError, match="corrupt or truncated"):
        decoder_io.load_decoder(truncated)

    # Weights changed after saving: the fingerprint no longer matches.
    tampered = tmp_path / "tampered.npz"
    with np.load(path, allow_pickle=False) as data:
        arrays = {name: np.array(data[name]) for name in data.files}
    arrays["params/block_4/conv/kernel"][0, 0, 0, 0] += 1.0
    np.savez(tampered, **arrays)
    with pytest.raises(MnerfError, match="fingerprint"):
        decoder_io.load_decoder(tampered)

    # Metadata that claims 16 bits over the arrays of an 8-bit decoder: wrong shapes.
    eight = dec.init_decoder(jax.random.PRNGKey(5), 8)
    decoder_io.save_decoder(tmp_path / "eight.npz", eight)
    with np.load(tmp_path / "eight.npz", allow_pickle=False) as data:
        arrays = {name: np.array(data[name]) for name in data.files}
    meta = json.loads(arrays["__metadata__"].tobytes())
    meta["bits"] = 16
    arrays["__metadata__"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    np.savez(tmp_path / "lying.npz", **arrays)
    with pytest.raises(MnerfError, match=r"has shape \(8,\), expected \(16,\)"):
        decoder_io.load_decoder(tmp_path / "lying.npz")

    # A zip that is not a decoder file at all.
    with zipfile.ZipFile(tmp_path / "other.npz", "w") as z:
        z.writestr("x.npy", b"garbage")
    with pytest.raises(MnerfError, match="decoder file"):
        decoder_io.load_decoder(tmp_path / "other.npz")


def test_interior_mean_skips_the_margin_and_falls_back_to_the_whole_mean() -> None:
    x = jax.random.normal(jax.random.PRNGKey(4), (2, 12, 10, 5))
    inner = x[:, 3:9, 3:7].mean(axis=(1, 2))
    np.testing.assert_allclose(dec.interior_mean(x, 3), inner, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(dec.interior_mean(x, 0), x.mean(axis=(1, 2)), rtol=1e-5, atol=1e-6)
    # No interior (10 ≤ 2·5): every position.
    np.testing.assert_allclose(dec.interior_mean(x, 5), x.mean(axis=(1, 2)), rtol=1e-5, atol=1e-6)
    traced = jax.jit(dec.interior_mean)(x, jnp.int32(3))  # the margin travels as an array
    np.testing.assert_allclose(traced, x[:, 3:9, 3:7].mean(axis=(1, 2)), rtol=1e-5, atol=1e-6)


def test_pool_margin_of_the_receptive_radius_makes_the_read_shift_invariant() -> None:
    """On a periodic LL2 whose pooled interior holds whole periods, shifting the pattern leaves the logits
    unchanged when the pool skips the padding-affected band, and changes them when it pools everywhere."""
    variables = dec.filterbank_init(dec.init_decoder(jax.random.PRNGKey(0), 16))  # strong local responses
    crops = jax.random.uniform(jax.random.PRNGKey(7), (20, 80, 80, 3))
    variables = dec.calibrate_batch_norm(variables, dwt.ll2(crops[:8]))
    radius = dec.receptive_radius(variables)
    assert radius == 9
    tile = 2.0 * jax.random.uniform(jax.random.PRNGKey(6), (1, 4, 4, 3))
    side = 2 * radius + 5 * 4  # an interior of 5 × 5 periods
    periodic = jnp.tile(tile, (1, side // 4 + 2, side // 4 + 2, 1))
    ll2 = jnp.concatenate([periodic[:, :side, :side], periodic[:, 1 : side + 1, 3 : side + 3]])
    pooled = dec.with_pool_margin(variables, radius)
    assert dec.pool_margin(pooled) == radius and dec.pool_margin(variables) == 0
    logits = dec.apply_ll2(pooled, ll2)
    assert float(jnp.abs(logits).max()) > 1.0
    np.testing.assert_allclose(logits[0], logits[1], rtol=1e-5, atol=1e-5)
    everywhere = dec.apply_ll2(variables, ll2)
    assert float(jnp.abs(everywhere[0] - everywhere[1]).max()) > 1e-2
    train_logits, _ = dec.apply_ll2_train(pooled, ll2)
    assert train_logits.shape == (2, 16)
    whitened = dec.fit_whitening(pooled, [dwt.ll2(crops)])
    assert dec.pool_margin(whitened) == radius
    with pytest.raises(MnerfError, match="margin must be >= 0"):
        dec.with_pool_margin(variables, -1)


def test_pool_margin_is_saved_fingerprinted_and_absent_in_older_files(
    tmp_path: Path, small_decoder: dict
) -> None:
    pooled = dec.with_pool_margin(small_decoder, 9)
    assert decoder_io.fingerprint(pooled) != decoder_io.fingerprint(small_decoder)
    meta = decoder_io.save_decoder(tmp_path / "p.npz", pooled)
    loaded = decoder_io.load_decoder(tmp_path / "p.npz")
    assert meta["pool_margin"] == 9 and dec.pool_margin(loaded.variables) == 9
    assert loaded.fingerprint == decoder_io.fingerprint(pooled)
    # A file from before the setting existed (no pool_margin entry) pools everywhere, fingerprint unchanged.
    decoder_io.save_decoder(tmp_path / "old.npz", small_decoder)
    with np.load(tmp_path / "old.npz", allow_pickle=False) as data:
        arrays = {name: np.array(data[name]) for name in data.files}
    meta = json.loads(arrays["__metadata__"].tobytes())
    del meta["pool_margin"]
    arrays["__metadata__"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    np.savez(tmp_path / "old.npz", **arrays)
    assert dec.pool_margin(decoder_io.load_decoder(tmp_path / "old.npz").variables) == 0
    # The margin edited in the metadata: the fingerprint no longer matches.
    meta["pool_margin"] = 4
    arrays["__metadata__"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    np.savez(tmp_path / "edited.npz", **arrays)
    with pytest.raises(MnerfError, match="fingerprint"):
        decoder_io.load_decoder(tmp_path / "edited.npz")


def test_training_with_a_pool_margin_needs_large_enough_images(tmp_path: Path) -> None:
    cfg = stages.DecoderTrainConfig(bits=8, pool_margin=9)  # 64-px windows: LL2 16 ≤ 18
    with pytest.raises(MnerfError, match="--pool-margin 9 leaves no positions to pool in 64-px"):
        stages.train_decoder(cfg, tmp_path / "run", progress=False)
    assert not (tmp_path / "run" / "checkpoint.msgpack").exists()
    cfg = stages.DecoderTrainConfig(bits=8, pool_margin=9, size=80, informed_sizes=(80,), batch=2)
    assert dec.pool_margin(stages.init_state(cfg)[0]["decoder"]) == 9


@pytest.mark.parametrize("bits", decoder_io.SHIPPED_BITS)
def test_shipped_decoder_reproduces_recorded_accuracy(bits: int) -> None:
    if not decoder_io.shipped_check_path(bits).is_file():
        pytest.skip(f"no shipped {bits}-bit decoder in this checkout (scripts/train_decoders.sh trains it)")
    loaded = decoder_io.load_shipped_decoder(bits)
    assert loaded.bits == bits and loaded.metadata["whitened"] is True
    recorded = loaded.metadata["eval"]
    assert set(recorded["heldout"]) == {"64px", "128px", "256px"}
    with np.load(decoder_io.shipped_check_path(bits), allow_pickle=False) as check:
        images, message = check["images"], check["bits"]
    assert images.dtype == np.uint8 and message.shape == (images.shape[0], bits)
    logits = dec.decode_logits(loaded.variables, jnp.asarray(images, jnp.float32) / 255.0, loaded.wavelet)
    acc = float(jnp.mean((logits > 0) == (jnp.asarray(message) > 0)))
    # Float differences between machines may flip a bit whose logit is ~0: allow two of them.
    assert abs(acc - recorded["check_batch_bit_acc"]) <= 2.0 / message.size
    # Unwatermarked images decode to (near) random bits through the whitened decoder.
    clean = stages.heldout_images(len(images), images.shape[1])
    clean_acc = float(
        jnp.mean((dec.decode_logits(loaded.variables, jnp.asarray(clean)) > 0) == (jnp.asarray(message) > 0))
    )
    assert 0.3 < clean_acc < 0.7


@pytest.mark.parametrize("bits", decoder_io.SHIPPED_BITS)
def test_shipped_encoder_writes_what_its_decoder_reads_at_any_size(bits: int) -> None:
    """The encoder shipped beside each decoder, on held-out images and messages at its 35.5 dB: read at its
    training side (64²) and, writing for the downscaled read, at 256² (docs/decoders.md has the figures)."""
    path = decoder_io.shipped_encoder_path(bits)
    if path is None:
        pytest.skip(f"no shipped {bits}-bit encoder in this checkout (scripts/train_decoders.sh trains it)")
    enc_vars, cfg = hidden_encoder.load_encoder(path)
    loaded = decoder_io.load_shipped_decoder(bits)
    assert cfg.bits == bits
    messages = stages.heldout_messages(12, bits)
    for side in (64, 256):
        images = stages.heldout_images(12, side)
        encoded = hidden_encoder.encode_batch(cfg, enc_vars, images, messages, max_side=64)
        logits = dec.decode_logits(loaded.variables, read_window.downscaled(jnp.asarray(encoded), 64))
        assert float(jnp.mean((logits > 0) == (jnp.asarray(messages) > 0))) >= 0.9


def test_shipped_decoder_missing_bits() -> None:
    with pytest.raises(MnerfError, match="no shipped decoder for 12 bits"):
        decoder_io.shipped_decoder_path(12)


def test_short_training_run_learns(tmp_path: Path) -> None:
    """A tiny run of every stage: the informed stage lifts accuracy clearly above chance, the joint and
    fine-tuning steps run, whitening is fitted, files are written and load."""
    cfg = stages.DecoderTrainConfig(
        bits=8,
        informed_steps=60,
        informed_sizes=(32,),
        informed_start_psnr=20.0,
        steps=10,
        finetune_steps=10,
        size=32,
        crop_margin=0,
        batch=16,
        lr=3e-3,
        warmup_steps=10,
        clean_fraction=1.0,
        start_psnr=20.0,
        target_psnr=20.0,
        whiten_images=64,
        eval_images=64,
        eval_sizes=(32,),
        eval_augment_draws=0,
        eval_informed_iterations=(1,),
        check_images=4,
    )
    metrics = stages.train_decoder(cfg, tmp_path, progress=False, checkpoint_every=40)
    # 64 held-out images × 8 bits: chance is 0.5 ± 0.022. The informed embedding through the whitened
    # decoder must be clearly above it; the joint steps, whitening and the encoder steps are exercised,
    # not judged.
    heldout = metrics["heldout"]["32px"]
    by_gradient = heldout["informed"]["1_iterations"]
    assert by_gradient["bit_acc_none"] > 0.6, heldout
    assert by_gradient["psnr_min"] >= 20.0 - 1e-3 and by_gradient["bit_acc_low"] is None
    assert 0.0 <= heldout["bit_acc_none"] <= 1.0 and heldout["bit_acc_low"] is None
    assert heldout["psnr_min"] >= 20.0 - 1e-3
    loaded = decoder_io.load_decoder(tmp_path / "decoder.npz", expect_bits=8)
    assert loaded.metadata["whitened"] is True
    assert json.loads((tmp_path / "metrics.json").read_text())["fingerprint"] == loaded.fingerprint
    encoder, saved_cfg = hidden_encoder.load_encoder(tmp_path / "encoder.npz")
    assert saved_cfg == cfg
    with np.load(tmp_path / "check.npz", allow_pickle=False) as check:
        stored, message = check["images"], check["bits"]
    again = hidden_encoder.encode_batch(cfg, encoder, stages.heldout_images(4, 32), message)
    np.testing.assert_array_equal(np.round(again * 255).astype(np.uint8), stored)  # the encoder round-trips
    with pytest.raises(MnerfError, match="pass --resume"):
        stages.train_decoder(cfg, tmp_path, progress=False)
    # The checkpoint refuses other settings.
    other = stages.DecoderTrainConfig(**{**cfg.to_dict(), "batch": 8})
    with pytest.raises(MnerfError, match="other settings"):
        stages.train_decoder(other, tmp_path, resume=True, progress=False)

    # An encoder trained anew for the finished decoder: the decoder is copied as it is (same fingerprint, its
    # training record kept) and the figures are re-measured with the new encoder. (Its sides taken in turn
    # are side_and_batch's, asserted at the end: a second side here would only compile the step again.)
    refit = dataclasses.replace(
        cfg,
        informed_steps=0,
        steps=0,
        finetune_steps=4,
        eval_sizes=(32,),
        decoder_from=str(tmp_path / "decoder.npz"),
    )
    with pytest.raises(MnerfError, match="--informed-steps 0 --steps 0"):
        stages.train_decoder(dataclasses.replace(refit, steps=2), tmp_path / "bad", progress=False)
    with pytest.raises(MnerfError, match="decodes 8-bit messages, but 16 bits"):
        stages.train_decoder(dataclasses.replace(refit, bits=16), tmp_path / "bad16", progress=False)
    assert not (tmp_path / "bad16").exists()  # refused before anything is written
    again_metrics = stages.train_decoder(refit, tmp_path / "refit", progress=False)
    assert again_metrics["fingerprint"] == loaded.fingerprint
    assert set(again_metrics["heldout"]) == {"32px"}
    record = decoder_io.load_decoder(tmp_path / "refit" / "decoder.npz").metadata["training"]
    assert record["config"]["informed_steps"] == 60
    assert record["encoder_refit"]["config"]["finetune_steps"] == 4
    assert [stages.side_and_batch(refit, (32, 48), i)[0] for i in range(3)] == [32, 48, 32]

    # An encoder for a reader that downscales to 32 pixels (watermark.reading.max_side): its batches keep
    # ``batch`` images at every side, and its check batch reads as recorded through that read.
    for_read = dataclasses.replace(
        refit, read_side=32, finetune_sizes=(64,), finetune_steps=2, eval_sizes=(64,)
    )
    assert stages.side_and_batch(for_read, (64,), 0, for_read.read_side) == (64, 16)
    assert stages.side_and_batch(for_read, (64,), 0) == (64, 4)
    read_metrics = stages.train_decoder(for_read, tmp_path / "for_read", progress=False)
    assert read_metrics["fingerprint"] == loaded.fingerprint and set(read_metrics["heldout"]) == {"64px"}
    with np.load(tmp_path / "for_read" / "check.npz", allow_pickle=False) as check:
        stored, message = check["images"], check["bits"]
    assert stored.shape[1:3] == (64, 64)
    seen = read_window.downscaled(jnp.asarray(stored, jnp.float32) / 255.0, for_read.read_side)
    read_acc = float(jnp.mean((dec.decode_logits(loaded.variables, seen) > 0) == (jnp.asarray(message) > 0)))
    assert abs(read_acc - read_metrics["check_batch_bit_acc"]) <= 2.0 / message.size
    # Started from that encoder, a run of no steps keeps it exactly; one of another architecture is refused.
    source = tmp_path / "for_read" / "encoder.npz"
    kept = dataclasses.replace(for_read, finetune_steps=0, encoder_from=str(source))
    stages.train_decoder(kept, tmp_path / "kept", progress=False)
    chex.assert_trees_all_equal(
        hidden_encoder.load_encoder(tmp_path / "kept" / "encoder.npz")[0],
        hidden_encoder.load_encoder(source)[0],
    )
    with pytest.raises(MnerfError, match="channels"):
        stages.train_decoder(
            dataclasses.replace(kept, encoder_channels=16), tmp_path / "bad_enc", progress=False
        )


def test_informed_step_with_a_margin_reads_windows_and_updates_the_decoder() -> None:
    """With ``informed_margin`` the decoder reads a smaller random window of each encoded image; the step
    still updates the decoder, with finite metrics, and keeps its pooling margin (1: LL2 windows of 4²)."""
    cfg = stages.DecoderTrainConfig(
        bits=8, size=16, informed_margin=4, batch=2, informed_steps=4, informed_sizes=(16,), pool_margin=1
    )
    state, (_, _, tx_inf, _) = stages.init_state(cfg)
    step = decoder_steps.make_informed_step(cfg, tx_inf, augmented=False)
    arrays = {k: state[k] for k in decoder_checkpoint.ARRAY_KEYS}
    before = jax.tree.map(np.asarray, arrays["decoder"]["params"])
    images = jnp.asarray(stages.heldout_images(2, 20))
    bits = jnp.asarray(stages.heldout_messages(2, 8))
    for i in range(2):  # the learning rate warms up from 0 at the first step
        arrays, metrics = step(arrays, images, bits, jax.random.PRNGKey(i), jnp.float32(25.0))
        assert all(np.isfinite(float(v)) for v in metrics.values()) and float(metrics["skipped"]) == 0.0
    after = arrays["decoder"]["params"]
    moved = jax.tree.map(lambda a, b: float(np.abs(np.asarray(a) - b).max()), after, before)
    assert max(jax.tree.leaves(moved)) > 0.0
    assert dec.pool_margin(arrays["decoder"]) == 1


def test_finetune_step_with_a_learning_decoder_keeps_its_whitening_and_statistics() -> None:
    """Stage 4 with ``finetune_decoder_lr``: the encoder and the decoder's weights move; the whitening layer
    and BatchNorm running statistics (what the encoder writes for) stay as they were."""
    cfg = stages.DecoderTrainConfig(
        bits=8,
        size=16,
        batch=2,
        finetune_steps=4,
        clean_fraction=1.0,
        finetune_decoder_lr=1e-3,
        finetune_decoder_start=0.5,
    )
    assert recipe.finetune_decoder_start_step(cfg) == 2 and stages.decoder_learned(cfg)
    frozen = dataclasses.replace(cfg, finetune_decoder_lr=0.0)
    assert recipe.finetune_decoder_start_step(frozen) == 4
    assert not stages.decoder_learned(frozen)
    state, (_, tx_ft, _, tx_ft_dec) = stages.init_state(cfg)
    step = decoder_steps.make_finetune_step(cfg, tx_ft, tx_ft_dec)
    arrays = {k: state[k] for k in decoder_checkpoint.ARRAY_KEYS}
    before = jax.tree.map(np.asarray, {"encoder": arrays["encoder"], "decoder": arrays["decoder"]})
    images = jnp.asarray(stages.heldout_images(2, 16))
    bits = jnp.asarray(stages.heldout_messages(2, 8))
    for i in range(2):  # the learning rates warm up from 0 at the first step
        arrays, metrics = step(arrays, images, bits, jax.random.PRNGKey(i), jnp.float32(35.5))
        assert float(metrics["skipped"]) == 0.0 and np.isfinite(float(metrics["loss"]))
    moved = lambda a, b: max(
        float(np.abs(np.asarray(x) - y).max())
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True)
    )
    assert moved(arrays["encoder"]["params"], before["encoder"]["params"]) > 0.0
    assert moved(arrays["decoder"]["params"]["block_3"], before["decoder"]["params"]["block_3"]) > 0.0
    assert moved(arrays["decoder"]["params"]["whiten"], before["decoder"]["params"]["whiten"]) == 0.0
    assert moved(arrays["decoder"]["batch_stats"], before["decoder"]["batch_stats"]) == 0.0


def test_recentring_the_whitening_standardises_each_logit_and_keeps_the_rotation(small_decoder: dict) -> None:
    ll2 = [jax.random.uniform(jax.random.PRNGKey(i), (32, 8, 8, 3)) * 4.0 for i in range(2)]
    shifted = dec.set_whitening(small_decoder, np.eye(16) * 2.0, np.full(16, 0.7))
    centred, report = dec.recentre_whitening(shifted, ll2)
    logits = np.concatenate([np.asarray(dec.apply_ll2(centred, x)) for x in ll2])
    np.testing.assert_allclose(logits.mean(axis=0), 0.0, atol=1e-4)
    np.testing.assert_allclose(logits.std(axis=0), 1.0, rtol=1e-4)
    before = np.concatenate([np.asarray(dec.apply_ll2(shifted, x)) for x in ll2])  # each logit only moves
    np.testing.assert_allclose(logits, (before - before.mean(0)) / before.std(0), atol=5e-3)  # and scales
    assert report["max_abs_mean"] == pytest.approx(np.abs(before.mean(0)).max(), rel=1e-3)
    assert report["max_std_ratio"] == pytest.approx(before.std(0).max(), rel=1e-3)
    assert 0.0 < report["max_abs_corr"] < 1.0


def test_checkpoint_round_trip(tmp_path: Path) -> None:
    cfg = stages.DecoderTrainConfig(bits=8)
    state, _ = stages.init_state(cfg)
    state["step"], state["whitened"], state["elapsed_s"] = 17, True, 3.5
    decoder_checkpoint.save_checkpoint(tmp_path / "c.msgpack", state, cfg)
    template = jax.tree.map(jnp.zeros_like, {k: state[k] for k in decoder_checkpoint.ARRAY_KEYS})
    template.update(step=0, whitened=False, elapsed_s=0.0, whitening_report=state["whitening_report"])
    restored = decoder_checkpoint.load_checkpoint(tmp_path / "c.msgpack", template, cfg)
    assert (restored["step"], restored["whitened"], restored["elapsed_s"]) == (17, True, 3.5)
    for a, b in zip(jax.tree.leaves(restored["opt"]), jax.tree.leaves(state["opt"]), strict=True):
        np.testing.assert_array_equal(a, b)
    (tmp_path / "bad.msgpack").write_bytes(b"\x00\x01garbage")
    with pytest.raises(MnerfError, match="unreadable"):
        decoder_checkpoint.load_checkpoint(tmp_path / "bad.msgpack", template, cfg)


def test_non_finite_gradient_skips_the_step() -> None:
    old = {"w": jnp.ones(3), "opt": jnp.zeros(2)}
    new = {"w": jnp.full(3, 2.0), "opt": jnp.ones(2)}
    kept = decoder_steps._unless_finite({"g": jnp.array([0.1, jnp.nan])}, new, old)
    np.testing.assert_array_equal(kept["w"], old["w"])
    np.testing.assert_array_equal(kept["opt"], old["opt"])
    taken = decoder_steps._unless_finite({"g": jnp.array([0.1, 0.2])}, new, old)
    np.testing.assert_array_equal(taken["w"], new["w"])


def test_informed_embedding_follows_the_decoder_gradient() -> None:
    """With a linear decoder (logit i = mean(x · P_i)) the informed residual is the signed sum of the P_i:
    every bit reads right, the PSNR is the target, and the result stays in [0, 1]."""
    key_p, key_x = jax.random.split(jax.random.PRNGKey(3))
    patterns = jax.random.normal(key_p, (8, 16, 16, 3))
    images = 0.25 + 0.5 * jax.random.uniform(key_x, (4, 16, 16, 3))
    logits_of = lambda x: jnp.einsum("bhwc,lhwc->bl", x - 0.5, patterns) / (16 * 16 * 3)
    bits = jnp.asarray(stages.heldout_messages(4, 8))
    for iterations in (1, 3):
        encoded = informed.informed_embed(logits_of, images, bits, psnr=25.0, iterations=iterations)
        assert float(encoded.min()) >= 0.0 and float(encoded.max()) <= 1.0
        psnr = -10 * jnp.log10(jnp.mean((encoded - images) ** 2, axis=(1, 2, 3)))
        np.testing.assert_allclose(psnr, 25.0, atol=1e-3)  # no pixel is clipped here
        shift = logits_of(encoded) - logits_of(images)
        np.testing.assert_array_equal(np.asarray(shift > 0), np.asarray(bits > 0.5))
    # A mask confines the residual to its pixels at the same whole-image PSNR.
    mask = jnp.zeros((4, 16, 16, 1)).at[:, 4:12, 4:12].set(1.0)
    encoded = informed.informed_embed(logits_of, images, bits, psnr=25.0, iterations=2, mask=mask)
    assert float(jnp.abs((encoded - images) * (1.0 - mask)).max()) == 0.0
    psnr = -10 * jnp.log10(jnp.mean((encoded - images) ** 2, axis=(1, 2, 3)))
    np.testing.assert_allclose(psnr, 25.0, atol=1e-3)


def test_encoder_respects_psnr() -> None:
    cfg = stages.DecoderTrainConfig(bits=16, target_psnr=35.5)
    enc = hidden_encoder.init_encoder(jax.random.PRNGKey(0), 16)
    images = jnp.asarray(stages.heldout_images(4, 48))
    bits = jnp.asarray(stages.heldout_messages(4, 16))
    encoded, _ = hidden_encoder.encode(enc, images, bits, cfg)
    assert encoded.shape == images.shape
    assert float(encoded.min()) >= 0.0 and float(encoded.max()) <= 1.0
    mse = jnp.mean((encoded - images) ** 2, axis=(1, 2, 3))
    assert float(jnp.min(-10 * jnp.log10(mse))) >= 35.5 - 1e-3
    assert stages.psnr_schedule(stages.DecoderTrainConfig(steps=100), 0) == 20.0
    assert stages.psnr_schedule(stages.DecoderTrainConfig(steps=100), 99) == 35.5


def test_encoder_for_a_downscaling_reader_writes_only_what_the_reader_sees() -> None:
    """With ``max_side``, the residual lies in the span of the read's adjoint (no energy the read cannot
    see), keeps the PSNR at any size, and equals the plain encoder's when the image is not downscaled."""
    cfg = stages.DecoderTrainConfig(bits=16, target_psnr=35.5)
    enc = hidden_encoder.init_encoder(jax.random.PRNGKey(0), 16)
    bits = jnp.asarray(stages.heldout_messages(2, 16))
    grey = jnp.full((2, 48, 48, 3), 0.5, jnp.float32)  # no clipping: the residual is the encoder's own
    encoded, _ = hidden_encoder.encode(enc, grey, bits, cfg, max_side=16)
    residual = np.asarray(encoded - grey, np.float64)
    assert np.all(-10 * np.log10(np.mean(residual**2, axis=(1, 2, 3))) >= 35.5 - 1e-3)

    def read(x: jax.Array) -> jax.Array:
        return dwt.ll2(read_window.downscaled(x[None], 16), cfg.wavelet)[0].ravel()

    rows = np.asarray(jax.jacrev(read)(grey[0]), np.float64).reshape(-1, grey[0].size)  # [48, 6912]
    for r in residual.reshape(2, -1):
        coeffs = np.linalg.lstsq(rows.T, r, rcond=None)[0]
        assert np.linalg.norm(rows.T @ coeffs - r) <= 1e-4 * np.linalg.norm(r)
    # The plain encoder's residual is not confined so: the downscaled read sees less than the whole image.
    plain = np.asarray(hidden_encoder.encode(enc, grey, bits, cfg)[0] - grey, np.float64).reshape(2, -1)
    coeffs = np.linalg.lstsq(rows.T, plain[0], rcond=None)[0]
    assert np.linalg.norm(rows.T @ coeffs - plain[0]) > 0.1 * np.linalg.norm(plain[0])
    same = hidden_encoder.encode(enc, grey, bits, cfg, max_side=48)[0]
    np.testing.assert_array_equal(
        np.asarray(same), np.asarray(hidden_encoder.encode(enc, grey, bits, cfg)[0])
    )


def test_unknown_decoder_init_is_refused_before_anything_is_written(tmp_path: Path) -> None:
    cfg = stages.DecoderTrainConfig(bits=8, decoder_init="gabor")
    with pytest.raises(MnerfError, match="--decoder-init must be one of random, filterbank"):
        stages.train_decoder(cfg, tmp_path / "run", progress=False)
    assert not (tmp_path / "run" / "checkpoint.msgpack").exists()


def test_encoder_size_comes_from_the_command_line_and_is_checked(tmp_path: Path, mnerf) -> None:
    code, _, err = mnerf("train-decoder", "--bits", "8", "--out", tmp_path / "run", "--encoder-channels", "0")
    assert code == 2 and "--encoder-channels must be ≥ 1" in err and not (tmp_path / "run").exists()
    cfg = stages.DecoderTrainConfig(bits=8, encoder_channels=8, encoder_depth=1)
    encoder = stages.init_state(cfg)[0]["encoder"]
    kernels = [
        leaf.shape
        for path, leaf in jax.tree_util.tree_leaves_with_path(encoder["params"])
        if "kernel" in jax.tree_util.keystr(path)
    ]
    assert len(kernels) == 1 + 2 + 1 and kernels[0][-1] == 8  # depth 1, two blocks after the message, 1×1 out


def test_checkpoint_from_before_decoder_init_existed_reads_as_random(tmp_path: Path) -> None:
    import flax.serialization

    cfg = stages.DecoderTrainConfig(bits=8, decoder_init="random")
    state, _ = stages.init_state(cfg)
    path = tmp_path / "c.msgpack"
    decoder_checkpoint.save_checkpoint(path, state, cfg)
    payload = flax.serialization.msgpack_restore(path.read_bytes())
    config = json.loads(payload["config"])
    del config["decoder_init"], config["pool_margin"]  # as a checkpoint written before the fields existed
    payload["config"] = json.dumps(config)
    path.write_bytes(flax.serialization.msgpack_serialize(payload))
    assert decoder_checkpoint.load_checkpoint(path, state, cfg)["step"] == 0
    other = stages.DecoderTrainConfig(bits=8, decoder_init="filterbank")
    with pytest.raises(MnerfError, match="decoder_init: random -> filterbank"):
        decoder_checkpoint.load_checkpoint(path, state, other)
