"""Batched extraction, bit accuracy, bad inputs, and ``mnerf extract`` on PNG files."""

from __future__ import annotations

import json
from pathlib import Path

import imageio.v3 as iio
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mnerf_jax import cli
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.reader import decoder as dec
from mnerf_jax.reader import decoder_io, extract


@pytest.fixture(scope="module")
def variables() -> dict:
    return dec.init_decoder(jax.random.PRNGKey(0), 8)


def test_decode_batch_single_and_chunks(variables: dict) -> None:
    images = jax.random.uniform(jax.random.PRNGKey(1), (5, 20, 24, 3))
    logits = extract.decode(variables, images)
    assert logits.shape == (5, 8)
    np.testing.assert_allclose(logits, dec.decode_logits(variables, images), rtol=1e-5, atol=1e-5)
    # Chunks of 2 (the last one padded) give the same logits as one batch.
    np.testing.assert_allclose(extract.decode(variables, images, batch_size=2), logits, rtol=1e-5, atol=1e-5)
    single = extract.decode(variables, images[3])
    assert single.shape == (8,)
    np.testing.assert_allclose(single, logits[3], rtol=1e-5, atol=1e-5)
    # uint8 images are scaled by 1/255.
    as_uint8 = np.round(np.asarray(images) * 255).astype(np.uint8)
    np.testing.assert_allclose(
        extract.decode(variables, as_uint8),
        extract.decode(variables, as_uint8.astype(np.float32) / 255),
        rtol=1e-5,
        atol=1e-5,
    )


def test_chunks_are_even_and_within_the_budgets() -> None:
    assert extract.chunk_size(32, 200, 200) == 11  # 3 calls of 11 (33 decoded), not 13 + 13 + 6 (39)
    assert extract.chunk_size(32, 100, 100) == 32
    assert extract.chunk_size(5, 20, 24, batch_size=2) == 2
    assert extract.chunk_size(3, 4000, 4000) == 1
    for n in range(1, 80):
        for side in (25, 100, 200, 300, 800):
            chunk = extract.chunk_size(n, side, side)
            calls = -(-n // chunk)
            assert chunk <= 32 and (chunk == 1 or chunk * side * side <= extract.PIXEL_BUDGET)
            assert calls * chunk - n < calls  # padding: less than one image a call
            assert calls == -(-n // max(1, min(32, n, extract.PIXEL_BUDGET // side**2)))  # the fewest calls


def test_bits_and_accuracy() -> None:
    logits = jnp.array([[0.3, -0.2, 0.0, 1.0], [-1.0, -2.0, 3.0, 0.1]])
    np.testing.assert_array_equal(extract.bits_from_logits(logits), [[1, 0, 0, 1], [0, 0, 1, 1]])
    acc = extract.bit_accuracy(logits, jnp.array([1, 0, 1, 1]))
    np.testing.assert_allclose(acc, [0.75, 0.75])
    np.testing.assert_allclose(
        extract.bit_accuracy(logits, np.array([[1, 0, 0, 1], [1, 1, 0, 0]])), [1.0, 0.0]
    )
    with pytest.raises(MnerfError, match="gives 4 bits but the message has 3"):
        extract.bit_accuracy(logits, jnp.array([1, 0, 1]))
    assert extract.bits_to_string([1, 0, 1, 1]) == "1011"


@pytest.mark.parametrize(
    "shape, message",
    [
        ((16, 16), "expected an image"),
        ((2, 3, 16, 16, 3), "expected an image"),
        ((16, 16, 4), "3 channels"),
        ((2, 16, 16, 1), "3 channels"),
        ((2, 2, 3), "too small"),
    ],
)
def test_bad_image_shapes(variables: dict, shape: tuple, message: str) -> None:
    with pytest.raises(MnerfError, match=message):
        extract.decode(variables, np.zeros(shape, np.float32))


def test_cli_extract_on_pngs(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    if not decoder_io.shipped_check_path(16).is_file():
        pytest.skip("no shipped 16-bit decoder in this checkout (train it with scripts/train_decoders.sh)")
    loaded = decoder_io.load_shipped_decoder(16)
    with np.load(decoder_io.shipped_check_path(16), allow_pickle=False) as check:
        images = check["images"][:3]
    paths = []
    for i, image in enumerate(images):
        path = tmp_path / f"encoded_{i}.png"
        iio.imwrite(path, image)
        paths.append(str(path))
    # RGBA on a transparent border: composited on white before decoding.
    rgba = np.concatenate([images[0], np.full((*images.shape[1:3], 1), 255, np.uint8)], axis=-1)
    iio.imwrite(tmp_path / "rgba.png", rgba)
    paths.append(str(tmp_path / "rgba.png"))

    assert cli.main(["extract", *paths, "--json"]) == 0  # default: the shipped 16-bit decoder
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [r["image"] for r in rows] == paths
    assert rows[0]["fingerprint"] == loaded.fingerprint and len(rows[0]["logits"]) == 16
    # The command prints what the library decodes from the same (8-bit) pixels.
    expected = extract.bits_from_logits(extract.decode(loaded.variables, images))
    assert [r["bits"] for r in rows[:3]] == [extract.bits_to_string(b) for b in expected]
    np.testing.assert_allclose(
        [r["logits"] for r in rows[:3]], extract.decode(loaded.variables, images), atol=2e-4
    )
    assert rows[3]["bits"] == rows[0]["bits"]  # opaque RGBA = RGB

    assert cli.main(["extract", paths[1], "--decoder", str(decoder_io.shipped_decoder_path(16))]) == 0
    out = capsys.readouterr().out.split()
    assert out == [paths[1], rows[1]["bits"]]

    # Errors are one line on stderr, exit status 2.
    iio.imwrite(tmp_path / "grey.png", images[0][..., 0])
    assert cli.main(["extract", str(tmp_path / "grey.png")]) == 2
    assert "reads RGB (or RGBA) images" in capsys.readouterr().err
    assert (
        cli.main(["extract", paths[0], "--bits", "48", "--decoder", str(decoder_io.shipped_decoder_path(16))])
        == 2
    )
    assert "48 bits are expected" in capsys.readouterr().err
    assert cli.main(["extract", str(tmp_path / "absent.png")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_decode_paths_groups_sizes(tmp_path: Path, variables: dict) -> None:
    rng = np.random.default_rng(0)
    arrays = [rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for h, w in [(20, 20), (24, 16), (20, 20)]]
    paths = []
    for i, a in enumerate(arrays):
        iio.imwrite(tmp_path / f"{i}.png", a)
        paths.append(tmp_path / f"{i}.png")
    logits = extract.decode_paths(variables, paths)
    assert logits.shape == (3, 8)
    for a, row in zip(arrays, logits, strict=True):
        np.testing.assert_allclose(row, extract.decode(variables, a), rtol=1e-5, atol=1e-5)
