"""Reading that survives geometry (reader/geometry_search.py): the candidate grid, the warps that undo a
rotation or a rescale, the best read's Bonferroni correction over candidates × keys, and the shipped 16-bit
decoder reading its rotated and rescaled check images again."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from skimage import transform

from mnerf_jax.core import config, rundir
from mnerf_jax.core.errors import ConfigError, MnerfError
from mnerf_jax.evaluation import attacks as wm_attacks
from mnerf_jax.imaging import attacks as A
from mnerf_jax.reader import decoder_io, keys
from mnerf_jax.reader import geometry_search as G
from mnerf_jax.reader import identification as V

# ------------------------------------------------------------------------------------------ the grid


def test_candidates_put_identity_first_and_count_each_once() -> None:
    assert G.GeometrySearch().candidates() == (G.Candidate(),)
    search = G.GeometrySearch("geometry", scales=(0.75, 1.0), degrees=(15.0, 0.0, 15.0))
    assert search.candidates() == (
        G.Candidate(1.0, 0.0),
        G.Candidate(1.0, 15.0),
        G.Candidate(0.75, 0.0),
        G.Candidate(0.75, 15.0),
    )
    assert [c.label for c in search.candidates()] == [
        "identity",
        "rotation 15°",
        "scale 0.75",
        "scale 0.75, rotation 15°",
    ]
    assert len(G.GeometrySearch("scale", scales=(0.5, 1.5), degrees=(5.0,)).candidates()) == 3
    assert len(G.GeometrySearch("rotation", scales=(0.5,), degrees=(-5.0, 5.0)).candidates()) == 3
    assert G.GeometrySearch("geometry").describe()["candidates"] == 4 * 7  # the default grids
    assert G.Candidate(0.75).output_size(96, 90) == (128, 120)


def test_bad_search_settings_are_refused_in_one_line() -> None:
    cases = [
        (lambda: G.GeometrySearch("spiral"), "unknown geometry search 'spiral'"),
        (lambda: G.GeometrySearch("scale", scales=(0.0,)), "scales are scale factors in"),
        (lambda: G.GeometrySearch("rotation", degrees=(200.0,)), "degrees are angles in"),
        (lambda: G.GeometrySearch("rotation", degrees=()), "degrees are angles in"),
        (lambda: G.parse_numbers("1,x", "--search-scales"), "--search-scales takes comma-separated"),
        (lambda: config.load_config("procedural", ["watermark.reading.search=spiral"]), "search"),
        (lambda: config.load_config("procedural", ["watermark.reading.search_scales=0"]), "search_scales"),
    ]
    for make, message in cases:
        with pytest.raises(MnerfError, match=message) as err:
            make()
        assert "\n" not in str(err.value)
    with pytest.raises(ConfigError):
        config.load_config("procedural", ["watermark.reading.search_degrees=-15,190"])
    reading = config.load_config(
        "procedural", ["watermark.reading.search=rotation", "watermark.reading.search_degrees=-15,15"]
    ).watermark.reading
    assert G.of_config(reading) == G.GeometrySearch("rotation", (0.5, 0.75, 1.5), (-15.0, 15.0))
    assert G.of_config(reading, mode="scale", scales=(0.8,)).candidates() == (G.Candidate(), G.Candidate(0.8))


# ------------------------------------------------------------------------------------------ the warps


@pytest.fixture(scope="module")
def check() -> tuple[np.ndarray, np.ndarray]:
    """The shipped 16-bit decoder's check batch: HiDDeN-encoded 128² images uint8 ``[8, 128, 128, 3]`` and
    their messages ``[8, 16]``."""
    if not decoder_io.shipped_check_path(16).is_file():
        pytest.skip("no shipped 16-bit decoder in this checkout")
    with np.load(decoder_io.shipped_check_path(16), allow_pickle=False) as data:
        return data["images"], data["bits"]


def _rotated(images: np.ndarray, degrees: float) -> np.ndarray:
    """uint8 images rotated anticlockwise by ``degrees`` as the attack library rotates (black corners)."""
    return np.stack([A.to_uint8(transform.rotate(x / 255.0, degrees, order=1)) for x in images])


def test_undo_inverts_a_rotation_and_a_rescale(check) -> None:
    images = check[0][:2]
    x = images.astype(np.float32) / 255.0
    inner = (slice(None), slice(32, 96), slice(32, 96))  # inside the corners a rotation loses
    rotated = _rotated(images, 15.0).astype(np.float32) / 255.0
    right = np.abs(G.undo(rotated, G.Candidate(1.0, 15.0)) - x)[inner].mean()
    wrong = np.abs(G.undo(rotated, G.Candidate(1.0, -15.0)) - x)[inner].mean()
    assert right < 0.01 and wrong > 3 * right
    for scale in (0.75, 1.5):
        rescaled = A.rescale(images, np.random.default_rng(0), scale=scale).astype(np.float32) / 255.0
        undone = G.undo(rescaled, G.Candidate(scale))
        assert undone.shape == x.shape and undone.dtype == np.float32
        assert np.abs(undone - x)[:, 8:-8, 8:-8].mean() < 0.01
    assert np.array_equal(G.undo(x, G.Candidate()), x)  # identity reads the image untouched


# ------------------------------------------------------------------------------- the p-value's correction


@pytest.mark.parametrize("test", ["binomial", "sign_flip"])
def test_the_best_read_claims_clean_images_at_most_at_the_threshold(test: str) -> None:
    """Unwatermarked reads (random logits, independent reads: Bonferroni's worst case) against random keys:
    the best (read, key) pair corrected over C·N is claimed at most at the threshold; corrected over the keys
    alone it would be claimed several times as often."""
    rng = np.random.default_rng(7)
    images, reads, bits, n_keys, threshold = 800, 6, 10, 4, 0.05
    messages = rng.integers(0, 2, (n_keys, bits)).astype(np.uint8)
    ident, chosen = V.identify_best_read(
        rng.standard_normal((images, reads, bits)), messages, threshold, test
    )
    assert ident.reads == reads and ident.comparisons == reads * n_keys and chosen.shape == (images,)
    slack = 3.0 * np.sqrt(threshold * (1 - threshold) / images)
    claimed = float((ident.decision >= 0).mean())
    assert claimed <= threshold + slack
    p = ident.p_value if test == "binomial" else ident.p_value_sign_flip
    keys_only = float((np.minimum(1.0, n_keys * p) < threshold).mean())
    assert keys_only > 2 * (threshold + slack)


def test_the_best_read_is_the_smallest_p_value_and_identity_wins_ties() -> None:
    messages = np.array([[1, 0, 1, 1, 0, 0, 1, 0], [0, 1, 1, 0, 1, 0, 0, 1]], np.uint8)
    signs = 2.0 * messages - 1.0
    logits = np.stack(
        [
            np.stack([signs[0] * [1, 1, 1, 1, 1, 1, -1, -1], signs[0], -signs[0]]),
            np.stack([signs[1], signs[1], signs[1] * 0.5]),  # three reads of equal agreement
        ]
    )
    ident, chosen = V.identify_best_read(logits, messages, threshold=0.5)
    np.testing.assert_array_equal(chosen, [1, 0])
    np.testing.assert_array_equal(ident.best_id, [0, 1])
    np.testing.assert_allclose(ident.p_value, 2.0**-8)
    np.testing.assert_allclose(ident.p_corrected, 3 * 2 * 2.0**-8)
    assert ident.min_attainable_p == pytest.approx(6 / 256)
    with pytest.raises(ValueError, match=r"\[B, C, L\]"):
        V.identify_best_read(logits[0], messages)


# ---------------------------------------------------------------------------- the shipped decoder's reads


@pytest.fixture(scope="module")
def decoder() -> decoder_io.LoadedDecoder:
    return decoder_io.load_shipped_decoder(16)


def _accuracy(logits: np.ndarray, messages: np.ndarray) -> np.ndarray:
    return ((np.asarray(logits) > 0) == (messages > 0)).mean(axis=-1)


def _search(decoder, images, messages, search) -> tuple[G.SearchRead, np.ndarray]:
    """The search's kept reads of ``images`` against every check message, and every read's logits."""
    every = G.search_logits(decoder.variables, images, search, decoder.wavelet)
    return G.identify(every, messages, search.candidates(), threshold=0.05, test="binomial"), every


def test_the_search_reads_rotated_and_rescaled_images_again(decoder, check) -> None:
    """Rotated by 15° or left at 75 % of its size, a check image reads at chance; the search undoes the
    right candidate and reads as many bits as the untransformed image's plain read, give or take one."""
    images, messages = check[0][:4], check[1]
    truth = messages[:4]
    plain = _accuracy(
        G.search_logits(decoder.variables, images, G.GeometrySearch(), decoder.wavelet)[:, 0], truth
    )
    cases = {
        "rotation": (
            _rotated(images, 15.0),
            G.GeometrySearch("rotation", degrees=(-15.0, 15.0)),
            G.Candidate(1.0, 15.0),
        ),
        "scale": (
            A.rescale(images, np.random.default_rng(0), scale=0.75),
            G.GeometrySearch("scale", scales=(0.75,)),
            G.Candidate(0.75),
        ),
    }
    for name, (attacked, search, inverse) in cases.items():
        kept, every = _search(decoder, attacked, messages, search)
        unsearched = _accuracy(every[:, 0], truth)
        assert unsearched.mean() <= 0.7, name  # the plain read loses the bits
        assert kept.chosen_candidates() == [inverse] * 4, name
        np.testing.assert_array_equal(kept.identification.best_id, [0, 1, 2, 3])
        assert np.all(_accuracy(kept.logits, truth) >= plain - 1 / 16), name
        reads = len(search.candidates())
        assert kept.identification.reads == reads
        np.testing.assert_allclose(
            kept.identification.p_corrected, np.minimum(1.0, reads * 8 * kept.identification.p_value)
        )


def test_the_search_keeps_the_plain_read_of_an_untransformed_image(decoder, check) -> None:
    images, messages = check[0][:4], check[1]
    search = G.GeometrySearch("geometry", scales=(0.75,), degrees=(15.0,))
    kept, every = _search(decoder, images, messages, search)
    plain = _accuracy(every[:, 0], messages[:4])
    searched = _accuracy(kept.logits, messages[:4])
    assert all(
        c.is_identity or s >= p for c, s, p in zip(kept.chosen_candidates(), searched, plain, strict=True)
    )
    assert sum(c.is_identity for c in kept.chosen_candidates()) >= 3


# ---------------------------------------------------------------------- mnerf extract and mnerf attack


@pytest.fixture(scope="module")
def check_run(tmp_path_factory, check) -> Path:
    """A watermarked run's reading files without a field: the shipped decoder, the 8 check messages as its
    keys, the whole image read; its 'evaluation' holds each ID's check image as its one view (and a clean
    render), what ``mnerf extract --run`` and ``mnerf attack`` read."""
    import imageio.v3 as iio

    run = tmp_path_factory.mktemp("check_run")
    cfg = config.load_config("procedural", ["watermark.reading.window=0", "watermark.reading.max_side=0"])
    rundir.write_run_files(run, cfg, data=None, kind=rundir.WATERMARK_KIND)
    shutil.copy(decoder_io.shipped_decoder_path(16), run / "decoder.npz")
    messages = check[1]
    keys.save_keys(run, keys.KeySet(messages, keys.min_pairwise_hamming(messages), seed=0))
    for k, image in enumerate(check[0]):
        (run / "eval-test" / f"id{k}").mkdir(parents=True)
        iio.imwrite(run / "eval-test" / f"id{k}" / "v0.png", image)
    (run / "eval-test" / "clean").mkdir()
    iio.imwrite(run / "eval-test" / "clean" / "v0.png", np.full((128, 128, 3), 200, np.uint8))
    (run / "eval-test.json").write_text(json.dumps({"view_names": ["v0"], "num_ids": 8, "step": 0}))
    return run


def test_extract_searches_with_a_run_only(check_run, check, tmp_path, mnerf) -> None:
    import imageio.v3 as iio

    path = tmp_path / "rotated.png"
    iio.imwrite(path, _rotated(check[0][3:4], 15.0)[0])
    code, out, err = mnerf("extract", path, "--search", "rotation")
    assert code == 2 and "--search needs --run" in err and len(err.strip().splitlines()) == 1
    code, out, err = mnerf(
        "extract",
        path,
        "--run",
        check_run,
        "--json",
        "--search",
        "rotation",
        "--search-degrees=-15,15",
        "--threshold",
        "0.05",
    )
    assert code == 0, err
    record = json.loads(out)
    assert record["candidate"] == {"scale": 1.0, "degrees": 15.0} and record["reads"] == 3
    assert record["id"] == 3 and record["p_corrected"] == pytest.approx(min(1.0, 24 * record["p_value"]))
    # 3 reads × 8 keys: the smallest corrected p-value is 3.7e-4, so a threshold of 1e-4 names nothing.
    code, out, err = mnerf(
        "extract",
        path,
        "--run",
        check_run,
        "--search",
        "rotation",
        "--search-degrees=-15,15",
        "--threshold",
        "1e-4",
    )
    assert code == 0 and "no image can be named" in err
    assert "read as rotation 15°, corrected over 3 reads" in out and "no watermark" in out
    code, out, err = mnerf(
        "extract", path, "--run", check_run, "--search-scales", "0.5,x", "--search", "scale"
    )
    assert code == 2 and "--search-scales takes comma-separated numbers" in err


def test_attack_rows_are_read_with_and_without_the_search(check_run, mnerf) -> None:
    code, out, err = mnerf(
        "attack",
        "--run",
        check_run,
        "--attacks",
        "rotate15",
        "--search",
        "rotation",
        "--search-degrees=-15,15",
        "--quiet",
    )
    assert code == 0, err
    assert "S: named" in out and "rotation search (3 candidates" in out
    result = json.loads((check_run / "eval-test-attacks.json").read_text())
    assert result["search"]["candidates"] == 3
    row = result["attacks"]["rotate15"]
    assert row["bit_accuracy_mean"] <= 0.7
    assert row["search"]["bit_accuracy_mean"] >= result["attacks"]["none"]["bit_accuracy_mean"] - 1 / 16
    assert sum(row["search"]["candidates_kept"].values()) == 8
    assert "false_claim_rate" in row["search"]
    assert result["mean_over_attacks_search"]["bit_accuracy_mean"] == row["search"]["bit_accuracy_mean"]
    # Without a search the rows are the search's plain read (its first candidate), and nothing else.
    plain = wm_attacks.evaluate_attacks(check_run, names=["rotate15"])
    assert plain["search"] is None and "search" not in plain["attacks"]["rotate15"]
    for name in ("none", "rotate15"):
        for key in ("bit_accuracy_mean", "identification_accuracy", "false_claim_rate"):
            assert plain["attacks"][name][key] == pytest.approx(result["attacks"][name][key]), (name, key)
