"""The read window (read_window.py): where it sits, that it follows the object, and what reads through it."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mnerf_jax.core.errors import MnerfError
from mnerf_jax.reader import read_window as rw

SIDE = 48


def object_on_white(top: int, left: int, size: int = 12, side: int = SIDE) -> np.ndarray:
    """A white ``side``² image ``[1, H, W, 3]`` with a dark textured square at (top, left)."""
    image = np.ones((1, side, side, 3), np.float32)
    rng = np.random.default_rng(top * 97 + left)
    image[0, top : top + size, left : left + size] = rng.uniform(0.0, 0.6, (size, size, 3))
    return image


def test_fraction_zero_and_full_side_read_the_whole_image() -> None:
    x = jnp.asarray(object_on_white(3, 5))
    assert rw.read_window(x, 0.0) is x
    assert rw.read_window(x, 1.0) is x  # a square image's full side is the image


def test_window_side_and_bad_fractions() -> None:
    assert rw.window_side(100, 100, 0.72) == 72
    assert rw.window_side(378, 504, 0.5) == 189  # the shorter side
    assert rw.window_side(100, 100, 0.01) == 4  # never below 4 px
    for bad in (-0.5, 1.5):
        with pytest.raises(MnerfError, match="fraction"):
            rw.window_side(100, 100, bad)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(top=st.integers(0, SIDE - 12), left=st.integers(0, SIDE - 12))
def test_the_window_is_centred_on_the_object(top: int, left: int) -> None:
    """The object's centre sits at the window's centre (within a pixel) wherever the window fits in the
    image, and the window always holds the whole object."""
    side = 24
    origin = np.asarray(rw.window_origin(jnp.asarray(object_on_white(top, left)), side, 1.0))[0]
    centre = np.array([top + 5.5, left + 5.5])
    want = np.clip(np.round(centre - (side - 1) / 2), 0, SIDE - side)
    assert np.all(np.abs(origin - want) <= 1)
    assert origin[0] <= top and origin[0] + side >= top + 12
    assert origin[1] <= left and origin[1] + side >= left + 12


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(dy=st.integers(-8, 8), dx=st.integers(-8, 8))
def test_shifting_the_image_shifts_the_window_with_it(dy: int, dx: int) -> None:
    """What the decoder reads is unchanged by a shift of the whole image (the window follows the object)."""
    base = object_on_white(18, 18)
    shifted = np.roll(base, (dy, dx), axis=(1, 2))  # the rolled-in border is white too
    a = np.asarray(rw.read_window(jnp.asarray(base), 0.5))
    b = np.asarray(rw.read_window(jnp.asarray(shifted), 0.5))
    np.testing.assert_array_equal(a, b)


def test_noise_on_the_background_barely_moves_the_window() -> None:
    """The High policy's noise (σ 0.08), clipped to [0, 1]: one-sided on white, yet the window stays."""
    clean = object_on_white(6, 30)
    noisy = np.clip(clean + np.random.default_rng(0).normal(0.0, 0.08, clean.shape), 0.0, 1.0)
    a = np.asarray(rw.window_origin(jnp.asarray(clean), 24, 1.0))
    b = np.asarray(rw.window_origin(jnp.asarray(noisy.astype(np.float32)), 24, 1.0))
    assert np.abs(a - b).max() <= 2


def test_no_backdrop_or_no_object_centres_the_window() -> None:
    blank = jnp.ones((2, SIDE, SIDE, 3))
    centred = np.array([[12, 12], [12, 12]])
    np.testing.assert_array_equal(np.asarray(rw.window_origin(blank, 24, 1.0)), centred)
    x = jnp.asarray(np.concatenate([object_on_white(0, 0), object_on_white(30, 30)]))
    np.testing.assert_array_equal(np.asarray(rw.window_origin(x, 24, None)), centred)
    assert rw.background_of(-1.0) is None and rw.background_of(0.0) == 0.0


def test_gradient_reaches_exactly_the_window_pixels() -> None:
    x = jnp.asarray(object_on_white(4, 28))
    grad = np.asarray(jax.grad(lambda im: jnp.sum(rw.read_window(im, 0.5)))(x))[0, ..., 0]
    top, left = np.asarray(rw.window_origin(x, 24, 1.0))[0]
    want = np.zeros((SIDE, SIDE))
    want[top : top + 24, left : left + 24] = 1.0
    np.testing.assert_array_equal(grad, want)


def test_decode_with_a_window_reads_the_cropped_image(make_decoder, tmp_path) -> None:  # noqa: ANN001
    from mnerf_jax.reader import decoder_io, extract

    loaded = decoder_io.load_decoder(make_decoder(tmp_path / "d.npz", 8))
    x = object_on_white(20, 4)
    top, left = np.asarray(rw.window_origin(jnp.asarray(x), 32, 1.0))[0]
    windowed = extract.decode(loaded.variables, x, loaded.wavelet, read=rw.ReadOptions(window=32 / SIDE))
    cropped = extract.decode(loaded.variables, x[:, top : top + 32, left : left + 32], loaded.wavelet)
    np.testing.assert_allclose(np.asarray(windowed), np.asarray(cropped), atol=1e-5)
    meta = {"read_window": 0.72, "read_background": -1.0}
    assert rw.of_metadata(meta) == rw.ReadOptions(0.72, None) and rw.of_metadata({}) == rw.ReadOptions()
    assert rw.of_metadata({**meta, "read_jitter": 2}) == rw.ReadOptions(0.72, None, jitter=2)


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    top=st.integers(0, SIDE - 12),
    left=st.integers(0, SIDE - 12),
    dy=st.integers(-30, 30),
    dx=st.integers(-30, 30),
)
def test_an_offset_moves_the_window_by_that_much_within_the_image(
    top: int, left: int, dy: int, dx: int
) -> None:
    x = jnp.asarray(object_on_white(top, left))
    origin = np.asarray(rw.window_origin(x, 24, 1.0))[0]
    want = np.clip(origin + [dy, dx], 0, SIDE - 24)
    moved = np.asarray(rw.read_window(x, 0.5, 1.0, jnp.asarray([[dy, dx]])))[0]
    np.testing.assert_array_equal(moved, np.asarray(x)[0, want[0] : want[0] + 24, want[1] : want[1] + 24])


def test_jitter_offsets_cover_the_square_once_centre_first() -> None:
    for radius in range(4):
        offsets = rw.jitter_offsets(radius)
        assert offsets.shape == ((2 * radius + 1) ** 2, 2) and tuple(offsets[0]) == (0, 0)
        assert len({tuple(o) for o in offsets}) == len(offsets) and np.abs(offsets).max(initial=0) == radius
    with pytest.raises(MnerfError, match="radius"):
        rw.jitter_offsets(-1)


def test_a_jittered_read_is_the_mean_over_the_moved_windows(make_decoder, tmp_path) -> None:  # noqa: ANN001
    """extract.decode with a jitter averages the decoder's logits over every moved window (checked against
    the windows cut out by hand), radius 0 is the plain read, and a whole-image read ignores the jitter."""
    from mnerf_jax.reader import decoder_io, extract

    loaded = decoder_io.load_decoder(make_decoder(tmp_path / "d.npz", 8))
    x = np.concatenate([object_on_white(20, 4), object_on_white(3, 30)])
    top_left = np.asarray(rw.window_origin(jnp.asarray(x), 32, 1.0))
    by_hand = []
    for dy, dx in rw.jitter_offsets(2):
        o = np.clip(top_left + [dy, dx], 0, SIDE - 32)
        crops = np.stack([im[a : a + 32, b : b + 32] for im, (a, b) in zip(x, o, strict=True)])
        by_hand.append(np.asarray(extract.decode(loaded.variables, crops, loaded.wavelet)))
    jittered = extract.decode(
        loaded.variables, x, loaded.wavelet, batch_size=4, read=rw.ReadOptions(window=32 / SIDE, jitter=2)
    )
    np.testing.assert_allclose(np.asarray(jittered), np.mean(by_hand, axis=0), atol=1e-5)
    plain = extract.decode(loaded.variables, x, loaded.wavelet, read=rw.ReadOptions(window=32 / SIDE))
    np.testing.assert_allclose(np.asarray(plain), by_hand[0], atol=1e-5)
    assert not np.allclose(np.asarray(jittered), np.asarray(plain), atol=1e-4)
    whole = extract.decode(loaded.variables, x, loaded.wavelet)
    np.testing.assert_array_equal(
        np.asarray(extract.decode(loaded.variables, x, loaded.wavelet, read=rw.ReadOptions(jitter=2))),
        np.asarray(whole),
    )


def test_extract_with_a_run_decoder_file_reads_its_recorded_window(make_decoder, tmp_path) -> None:  # noqa: ANN001
    """`mnerf extract --decoder WMRUN/decoder.npz` reads the window the embedding recorded in the file."""
    import argparse

    import imageio.v3 as iio

    from mnerf_jax import cli
    from mnerf_jax.cli import extract as extract_cmd
    from mnerf_jax.reader import decoder_io, extract

    plain = decoder_io.load_decoder(make_decoder(tmp_path / "plain.npz", 8))
    path = tmp_path / "run_decoder.npz"
    decoder_io.save_decoder(
        path, plain.variables, {"read_window": 0.5, "read_background": 1.0, "read_jitter": 1}
    )
    image = (object_on_white(30, 2)[0] * 255).astype(np.uint8)
    iio.imwrite(tmp_path / "view.png", image)
    # The command's own parser, so the arguments are those a user gives.
    args = cli.build_parser("extract").parse_args(
        ["extract", str(tmp_path / "view.png"), "--decoder", str(path)]
    )
    records, _ = extract_cmd.extract_records(args)
    want = extract.decode(
        plain.variables, image[None], plain.wavelet, read=rw.ReadOptions(window=0.5, jitter=1)
    )[0]
    # The records round logits to 4 decimals; this small random decoder's logits are ~1e-2.
    np.testing.assert_allclose(records[0]["logits"], np.asarray(want), atol=6e-5)
    centred = extract.decode(plain.variables, image[None], plain.wavelet, read=rw.ReadOptions(window=0.5))[0]
    whole = extract.decode(plain.variables, image[None], plain.wavelet)[0]
    for other in (centred, whole):
        assert np.abs(np.asarray(want) - np.asarray(other)).max() > 1.5e-4
    # --read-jitter overrides the file's jitter.
    records, _ = extract_cmd.extract_records(argparse.Namespace(**{**vars(args), "read_jitter": 0}))
    np.testing.assert_allclose(records[0]["logits"], np.asarray(centred), atol=6e-5)


# ----------------------------------------------------------------------------- reading at a fixed side


@given(h=st.integers(8, 300), w=st.integers(8, 300), max_side=st.sampled_from([0, 16, 64]))
@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_downscaled_keeps_images_up_to_the_side_and_shrinks_longer_ones(
    h: int, w: int, max_side: int
) -> None:
    x = jnp.zeros((1, h, w, 3))
    if not max_side or max(h, w) <= max_side:
        assert rw.downscaled(x, max_side) is x
    else:
        oh, ow = jax.eval_shape(lambda a: rw.downscaled(a, max_side), x).shape[1:3]  # no compilation
        assert oh % 4 == 0 and ow % 4 == 0 and 4 <= min(oh, ow) and max(oh, ow) <= max_side + 2
        scale = max_side / max(h, w)
        for side, new in ((h, oh), (w, ow)):  # the aspect ratio kept to the nearest 4 px (at least 4)
            assert abs(new - max(side * scale, 4)) <= 2


def test_a_read_at_a_fixed_side_does_not_depend_on_the_images_size(make_decoder, tmp_path) -> None:  # noqa: ANN001
    # The same smooth picture at 64² and at 256² (each pixel repeated 4×4) reads the same at max_side 64:
    # the downscaled 256² image is the 64² one up to the resampling filter's blur.
    from mnerf_jax.reader import decoder_io, extract

    loaded = decoder_io.load_decoder(make_decoder(tmp_path / "dec8.npz", 8))
    coarse = np.random.default_rng(0).uniform(0, 1, (2, 8, 8, 3)).astype(np.float32)
    small = np.asarray(jax.image.resize(coarse, (2, 64, 64, 3), "linear"))  # a smooth picture
    large = np.repeat(np.repeat(small, 4, axis=1), 4, axis=2)
    np.testing.assert_allclose(np.asarray(rw.downscaled(jnp.asarray(large), 64)), small, atol=3e-2)
    at_64 = np.asarray(
        extract.decode(loaded.variables, small, loaded.wavelet, read=rw.ReadOptions(max_side=64))
    )
    np.testing.assert_array_equal(at_64, np.asarray(extract.decode(loaded.variables, small, loaded.wavelet)))
    read_large = np.asarray(
        extract.decode(loaded.variables, large, loaded.wavelet, read=rw.ReadOptions(max_side=64))
    )
    assert np.mean(np.sign(read_large) == np.sign(at_64)) >= 0.9
    # The gradient passes the resampling (the embedding writes through it).
    grad = jax.grad(lambda x: jnp.sum(rw.read_window(x, 0.5, 1.0, max_side=16)))(jnp.asarray(large[:1]))
    assert float(jnp.abs(grad).sum()) > 0


def test_runs_embedded_before_max_side_existed_read_at_full_size(tmp_path) -> None:  # noqa: ANN001
    from mnerf_jax.core import rundir
    from mnerf_jax.core.watermark_config import ReadingConfig

    assert rw.of_metadata({"read_window": 0.5}).max_side == 0  # a decoder file without the setting
    assert rw.of_metadata({"read_max_side": 64}).max_side == 64
    assert rw.of_config(ReadingConfig()).max_side == 64
    old = {"watermark": {"reading": {"window": 0.72}}}
    assert rundir.with_full_size_reads(old)["watermark"]["reading"] == {"window": 0.72, "max_side": 0}
    assert rundir.with_full_size_reads({"watermark": {"read_window": 0.5}})["watermark"]["read_max_side"] == 0
    new = {"watermark": {"reading": {"max_side": 32}}}
    assert rundir.with_full_size_reads(new) == new
    with pytest.raises(MnerfError, match="max_side"):
        ReadingConfig(max_side=4)
