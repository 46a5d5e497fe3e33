"""The evaluation's attack library (imaging.attacks, imaging.attack_suites) and the report of its scores
(evaluation.attack_report): small numpy images, no watermarked run (mnerf attack end to end:
test_wm_eval.py)."""

from __future__ import annotations

import numpy as np
import pytest

from mnerf_jax.evaluation import attack_report
from mnerf_jax.imaging import attack_suites as S
from mnerf_jax.imaging import attacks as A
from mnerf_jax.imaging import training_attacks as T
from mnerf_jax.imaging.attacks import AttackError

NUMPY_ATTACKS = [name for name in S.SUITES["all"] if S.ATTACKS[name].family != "paper"]
# The attacks that leave the image at another size, and that size for a 24 x 36 image.
RESIZED = {
    "crop_centre80": (21, 32),
    "crop_centre60": (19, 28),
    "crop_centre40": (15, 23),
    "crop_random80": (21, 32),
    "crop_random60": (19, 28),
    "crop_random40": (15, 23),
    "rescale50": (12, 18),
    "rescale75": (18, 27),
    "rescale150": (36, 54),
    "crop_random40+brightness2+jpeg10": (15, 23),
}


def _images(b: int = 2, h: int = 24, w: int = 36, seed: int = 0, texture: float = 0.05) -> np.ndarray:
    """Smooth colour gradients with a little texture (uniform per value, ± ``texture``), uint8
    ``[b, h, w, 3]`` within 30..225 (no clipping at small changes)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w] / max(h, w)
    base = np.stack([x, y, 1 - (x + y) / 2], -1)[None] * 0.6 + 0.2
    tex = rng.uniform(-texture, texture, (b, h, w, 3))
    return np.round((base + tex + 0.05 * np.arange(b)[:, None, None, None]) * 255 * 0.85).astype(np.uint8)


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(float) - b.astype(float)) ** 2)
    return float("inf") if mse == 0 else 10 * np.log10(255.0**2 / mse)


# ------------------------------------------------------------------------------------ every attack


@pytest.mark.parametrize("name", NUMPY_ATTACKS)
def test_every_attack_takes_and_gives_uint8_images(name) -> None:
    attack = S.ATTACKS[name]
    x = _images()
    if attack.unavailable:
        with pytest.raises(AttackError, match="cannot run here"):
            attack(x, 0)
        return
    before = x.copy()
    out = attack(x, 0)
    assert out.dtype == np.uint8 and out.ndim == 4 and out.shape[0] == 2 and out.shape[-1] == 3
    assert out.shape[1:3] == RESIZED.get(name, (24, 36))
    np.testing.assert_array_equal(x, before)  # the input is left alone
    # The same seed draws the same parameters: the same output.
    np.testing.assert_array_equal(attack(x, 0), out)


def test_attacks_refuse_anything_but_uint8_rgb_batches() -> None:
    with pytest.raises(AttackError, match="uint8"):
        A.jpeg(_images().astype(np.float32) / 255, np.random.default_rng(0), quality=50)
    with pytest.raises(AttackError, match="shape"):
        A.flip(_images()[0], np.random.default_rng(0))
    with pytest.raises(AttackError, match="shape"):
        A.flip(np.zeros((1, 3, 8, 3), np.uint8), np.random.default_rng(0))


# ---------------------------------------------------------------------------------------- properties


@pytest.mark.parametrize("area", S.CROP_AREAS)
def test_a_crop_keeps_the_stated_area_and_the_pixels_it_keeps(area) -> None:
    x = _images(h=60, w=90)
    for random in (False, True):
        out = A.crop(x, np.random.default_rng(1), area=area, random=random)
        h, w = out.shape[1:3]
        assert h * w / (60 * 90) == pytest.approx(area, abs=0.02)
        assert h / 60 == pytest.approx(w / 90, abs=0.02)  # the aspect kept
        for src, cut in zip(x, out, strict=True):  # a window of the original, not resampled
            found = [
                (t, s)
                for t in range(60 - h + 1)
                for s in range(90 - w + 1)
                if np.array_equal(src[t : t + h, s : s + w], cut)
            ]
            assert found
            if not random:
                assert found == [((60 - h) // 2, (90 - w) // 2)]


def test_rotation_by_zero_and_jpeg_at_quality_100_are_near_identity() -> None:
    x = _images()
    rng = np.random.default_rng(0)
    assert np.abs(A.rotate(x, rng, degrees=0).astype(int) - x).max() <= 1
    # Pillow's JPEG halves the chroma resolution (4:2:0) at every quality: near identity where the colour
    # is smooth, as in a render.
    smooth = _images(texture=0.0)
    assert _psnr(A.jpeg(smooth, rng, quality=100), smooth) > 40.0
    assert _psnr(A.jpeg(x, rng, quality=10), x) < _psnr(A.jpeg(x, rng, quality=90), x)
    # A real rotation moves pixels; its corners are black.
    turned = A.rotate(x, rng, degrees=30)
    assert _psnr(turned, x) < 25.0 and (turned[:, 0, 0] == 0).all()


def test_rescaling_and_back_keeps_the_size() -> None:
    x = _images(h=23, w=37)  # odd sides
    for scale in (*S.SCALES, 0.25):
        back = A.rescale(x, np.random.default_rng(0), scale=scale, back=True)
        assert back.shape == x.shape
        left = A.rescale(x, np.random.default_rng(0), scale=scale)
        assert left.shape[1:3] == (round(23 * scale), round(37 * scale))
    # Up and back down loses less than down and back up.
    up = A.rescale(x, np.random.default_rng(0), scale=1.5, back=True)
    down = A.rescale(x, np.random.default_rng(0), scale=0.5, back=True)
    assert _psnr(up, x) > _psnr(down, x)


def test_flip_translate_and_greyscale_do_what_they_say() -> None:
    x = _images()
    rng = np.random.default_rng(0)
    np.testing.assert_array_equal(A.flip(x, rng), x[:, :, ::-1])
    np.testing.assert_array_equal(A.flip(x, rng, vertical=True), x[:, ::-1])
    grey = A.greyscale(x, rng)
    assert (grey[..., 0] == grey[..., 1]).all() and (grey[..., 1] == grey[..., 2]).all()
    moved = A.translate(x, np.random.default_rng(3), fraction=0.1)
    # 10 % of 24 x 36: 2 rows and 4 columns of black, and the rest the image shifted.
    for src, dst in zip(x, moved, strict=True):
        black_rows = np.flatnonzero((dst == 0).all(axis=(1, 2)))
        black_cols = np.flatnonzero((dst == 0).all(axis=(0, 2)))
        assert len(black_rows) == 2 and len(black_cols) == 4
        dy = 2 if black_rows[0] == 0 else -2
        dx = 4 if black_cols[0] == 0 else -4
        np.testing.assert_array_equal(np.roll(src, (dy, dx), axis=(0, 1))[2:-2, 4:-4], dst[2:-2, 4:-4])


def test_gaussian_noise_has_the_stated_sigma_in_unit_range() -> None:
    x = np.full((2, 64, 64, 3), 128, np.uint8)
    noisy = A.gaussian_noise(x, np.random.default_rng(0), sigma=0.05)
    assert np.std((noisy.astype(float) - 128) / 255) == pytest.approx(0.05, rel=0.05)
    pepper = A.salt_and_pepper(x, np.random.default_rng(0), amount=0.05)
    assert np.isin(pepper[pepper != 128], (0, 255)).all()
    assert np.mean(pepper != 128) == pytest.approx(0.05, abs=0.01)


def test_motion_kernels_are_lines_that_sum_to_one() -> None:
    flat = A.motion_kernel(5, 0.0)
    assert flat.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(flat[2], 0.2)  # the middle row, evenly
    assert A.motion_kernel(5, 90.0)[:, 2].sum() == pytest.approx(1.0)
    with pytest.raises(AttackError, match="odd"):
        A.motion_kernel(4, 0.0)


# ------------------------------------------------------------------------------------------- seeds


@pytest.mark.parametrize("name", ["crop_random60", "rotate15", "translate5", "hue0.1", "motion_blur5"])
def test_seeds_make_draws_deterministic_and_the_same_for_every_id(name) -> None:
    attack = S.ATTACKS[name]
    id0, id1 = _images(seed=0), _images(seed=1)
    # Each ID's renders of the views, attacked one ID at a time (as mnerf attack does): per view, the same
    # parameters whatever the images, so a shift of the input by a constant shifts the output alike.
    out0 = attack(id0, 7).astype(int)
    shifted = attack(np.clip(id0.astype(int) + 10, 0, 255).astype(np.uint8), 7).astype(int)
    interior = (slice(None), slice(6, -6), slice(9, -9))  # away from fills and borders
    assert np.abs((shifted - out0)[interior] - 10).max() <= 2
    np.testing.assert_array_equal(attack(id1, 7), attack(id1, 7))
    assert len({attack(id0, seed).tobytes() for seed in range(8)}) > 1  # other seeds, other draws
    # Draws are per image in batch order: the first view alone meets what it met in the batch.
    np.testing.assert_array_equal(attack(id0[:1], 7), attack(id0, 7)[:1])


def test_noise_draws_are_the_same_for_every_id() -> None:
    attack = S.ATTACKS["gaussian_noise0.01"]
    id0, id1 = _images(seed=0), _images(seed=1)
    noise0 = attack(id0, 3).astype(int) - id0
    noise1 = attack(id1, 3).astype(int) - id1
    assert np.abs(noise0 - noise1).max() <= 1  # one grey level of rounding
    assert np.abs(noise0).max() > 3


def test_paper_rows_draw_as_mnerf_attack_always_has() -> None:
    import jax

    from mnerf_jax.imaging import augment

    x = _images()
    row = S.ATTACKS["rgb_shift@high"]
    key = jax.random.fold_in(jax.random.PRNGKey(5), augment.AUGMENTATION_NAMES.index("rgb_shift"))
    expected = A.to_uint8(np.asarray(augment.apply("rgb_shift", key, x / np.float32(255), "high")))
    np.testing.assert_array_equal(row(x, 5), expected)
    # The plain name with a strength (--attacks rgb_shift --strength high) is the same row, named plainly.
    (plain,) = S.resolve(["rgb_shift"], "high")
    assert plain.name == "rgb_shift"
    np.testing.assert_array_equal(plain(x, 5), expected)


# ---------------------------------------------------------------------------------------- composition


def test_pairs_compose() -> None:
    x = _images()
    a, b = S.ATTACKS["crop_random60"], S.ATTACKS["gaussian_noise0.02"]
    pair = S.compose(a, b)
    assert pair.name == "crop_random60+gaussian_noise0.02" and len(pair.stages) == 2
    np.testing.assert_array_equal(pair(x, 4), b(a(x, 4), 4))
    # Named with "+", the same composition; and the registry's paper pairs are compositions of its rows.
    (named,) = S.resolve(["crop_random60+gaussian_noise0.02"])
    np.testing.assert_array_equal(named(x, 4), pair(x, 4))
    paper_pair = S.ATTACKS["brightness@low+rgb_shift@low"]
    low = [S.ATTACKS["brightness@low"], S.ATTACKS["rgb_shift@low"]]
    np.testing.assert_array_equal(paper_pair(x, 2), low[1](low[0](x, 2), 2))


def test_unknown_and_repeated_names_are_refused() -> None:
    with pytest.raises(AttackError, match="sepia.*--list"):
        S.resolve(["jpeg90", "sepia"])
    with pytest.raises(AttackError, match="named twice"):
        S.resolve(["jpeg90", "jpeg90"])
    with pytest.raises(AttackError, match="unknown attack suite 'nope'"):
        S.suite("nope")
    with pytest.raises(AttackError, match="strength"):
        S.augmentation_attack("jpeg", "extreme")


# ------------------------------------------------------------------------------------------ suites


def test_suites_list_what_the_issue_asks_for() -> None:
    suites = S.SUITES
    assert set(suites) == {"codecs", "geometric", "photometric", "regen", "peers", "paper", "all"}
    assert {f"jpeg{q}" for q in (90, 70, 50, 30, 10)} <= set(suites["codecs"])
    assert sum(n.startswith("webp") for n in suites["codecs"]) >= 3
    geometric = set(suites["geometric"])
    for area in (80, 60, 40):
        assert {f"crop_centre{area}", f"crop_random{area}"} <= geometric
    assert {"rotate5", "rotate15", "rotate30", "flip_h", "flip_v"} <= geometric
    for scale in (50, 75, 150):
        assert {f"rescale{scale}", f"rescale{scale}_back"} <= geometric
    assert any(n.startswith("translate") for n in geometric)
    photometric = " ".join(suites["photometric"])
    for kind in (
        "brightness",
        "contrast",
        "saturation",
        "hue",
        "gamma",
        "greyscale",
        "gaussian_noise",
        "salt_pepper",
        "gaussian_blur",
        "median",
        "motion_blur",
    ):
        assert kind in photometric, kind
    assert suites["peers"] == (
        "gaussian_noise0.1",
        "rotate30",
        "rescale75",
        "gaussian_blur0.1",
        "crop_random40",
        "jpeg50",
        "jpeg10",
        "brightness2",
        "crop_random40+brightness2+jpeg10",
    )
    regen = set(suites["regen"])
    assert {
        "jpeg5",
        "webp5",
        "rescale25_back",
        "denoise_tv0.1",
        "denoise_bilateral",
        "denoise_wavelet",
    } <= regen
    # paper: the 14 augmentations at three strengths, then every pair at low.
    assert len(suites["paper"]) == 14 * 3 + 14 * 13 // 2
    assert "jpeg@high" in suites["paper"] and "brightness@low+jpeg@low" in suites["paper"]
    assert set(suites["all"]) == {n for name, rows in suites.items() if name != "all" for n in rows}
    assert all(name in S.ATTACKS for name in suites["all"])
    listing = S.listing()
    assert "peers (9 attacks)" in listing and "crop_random40+brightness2+jpeg10" in listing


def test_webp_rows_run_or_say_why_not() -> None:
    for name in ("webp90", "webp5"):
        attack = S.ATTACKS[name]
        if A.WEBP_SUPPORTED:
            assert attack.unavailable is None
        else:
            assert "WebP" in attack.unavailable


# ---------------------------------------------------------------------------------- the regen hook


HOOK = """
import numpy as np
def regen(images):
    if images.dtype != np.uint8 or images.shape != (2, 24, 36, 3):
        raise TypeError(f"called with {images.dtype} {images.shape}")
    return images[:, ::2, ::2].copy()
def floats(images):
    return images / 255.0
def fewer(images):
    return images[:1]
def broken(images):
    raise RuntimeError("out of memory")
"""


def test_the_regen_hook_is_called_with_uint8_and_a_bad_return_is_refused(tmp_path) -> None:
    path = tmp_path / "myregen.py"
    path.write_text(HOOK)
    x = _images()
    attack = S.hook_attack(f"{path}:regen")
    assert attack.name == "regen:myregen.py:regen" and attack.family == "hook"
    assert str(path) in attack.description
    out = attack(x, 0)
    # Called with the uint8 batch (it refuses anything else); another size back is fine.
    assert out.shape == (2, 12, 18, 3) and out.dtype == np.uint8
    with pytest.raises(AttackError, match="dtype float64, not uint8"):
        S.hook_attack(f"{path}:floats")(x, 0)
    with pytest.raises(AttackError, match="returned 1 images for 2"):
        S.hook_attack(f"{path}:fewer")(x, 0)
    with pytest.raises(AttackError, match="raised RuntimeError: out of memory"):
        S.hook_attack(f"{path}:broken")(x, 0)


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("myregen", "MODULE:FUNCTION"),
        ("myregen:", "MODULE:FUNCTION"),
        ("no_such_module_here:regen", "cannot import no_such_module_here"),
        ("missing.py:regen", "does not exist"),
        ("numpy:no_such_function", "has no function no_such_function"),
    ],
)
def test_bad_regen_specs_are_refused_in_one_line(spec, message) -> None:
    with pytest.raises(AttackError, match=message) as err:
        S.hook_attack(spec)
    assert "\n" not in str(err.value)


def test_a_hook_file_may_define_dataclasses(tmp_path) -> None:
    path = tmp_path / "withclass.py"
    path.write_text(
        "import dataclasses\n@dataclasses.dataclass\nclass Model:\n    scale: int = 1\n"
        "def regen(images):\n    return images[:, :: Model().scale]\n"
    )
    x = _images()
    np.testing.assert_array_equal(S.hook_attack(f"{path}:regen")(x, 0), x)


def test_the_command_lists_the_suites_and_needs_a_run(mnerf) -> None:
    code, out, _ = mnerf("attack", "--list")
    assert code == 0 and "peers (9 attacks)" in out and "jpeg90" in out
    code, _, err = mnerf("attack")
    assert code == 2 and "--run" in err


def test_an_importable_module_is_a_hook_too() -> None:
    attack = S.hook_attack("numpy:ascontiguousarray")
    x = _images()
    np.testing.assert_array_equal(attack(x, 0), x)


# ---------------------------------------------------------------------------- decoding other sizes


def test_the_decoder_reads_odd_non_square_images() -> None:
    """Crops and rescales left at their size reach the decoder as they are: the DWT takes odd sides and the
    decoder pools over any size, through the read window too."""
    import jax

    from mnerf_jax.reader import decoder, extract, read_window

    variables = decoder.init_decoder(jax.random.PRNGKey(0), 8)
    x = S.ATTACKS["crop_random60"](_images(h=38, w=61), 0)  # 29 x 47
    assert x.shape[1:3] == (29, 47)
    logits = np.asarray(extract.decode(variables, x, read=read_window.ReadOptions(window=0.8)))
    assert logits.shape == (2, 8) and np.isfinite(logits).all()


# ------------------------------------------------------------------------------------------ report


def _fake_result(names: list[str], claims: bool, skipped: dict | None = None) -> dict:
    row = {
        "bit_accuracy_mean": 0.75,
        "bit_accuracy_min": 0.5,
        "identification_accuracy": 1.0,
        "verified_identification_accuracy": 0.5,
    }
    if claims:
        row["false_claim_rate"] = 0.25
    return {
        "suite": "x",
        "strength": None,
        "views": 2,
        "num_ids": 2,
        "order": ["none", *names],
        "attacks": {n: dict(row) for n in ["none", *names]},
        "skipped": skipped or {},
        "false_claims_measured": claims,
        "mean_over_attacks": dict(row),
    }


def test_the_table_shows_false_claims_only_when_measured_and_says_what_was_skipped() -> None:
    with_claims = attack_report.format_table(_fake_result(["jpeg90", "rotate5"], True))
    lines = with_claims.splitlines()
    assert "false claims" in lines[0] and lines[1].startswith("none") and lines[2].startswith("jpeg90")
    assert lines[1].rstrip().endswith("25.00%") and lines[-1].startswith("mean of attacks")
    without = attack_report.format_table(_fake_result(["jpeg90"], False, {"webp90": "no WebP"}))
    assert "false claims" not in without and "webp90" in without and "skipped: no WebP" in without
    # A file written before the order was recorded: the augmentations' order, "none" first.
    old = _fake_result(["jpeg", "brightness"], False)
    del old["order"]
    assert attack_report.attack_order(old) == ["none", "brightness", "jpeg"]


def test_the_plot_lays_long_suites_down_the_page(tmp_path) -> None:
    import imageio.v3 as iio

    short = attack_report.attacks_plot(tmp_path / "short.png", {"run": _fake_result(["a", "b"], True)})
    many = [f"attack{i}" for i in range(attack_report.HORIZONTAL_FROM + 5)]
    long = attack_report.attacks_plot(tmp_path / "long.png", {"run": _fake_result(many, True)})
    short_h, short_w = iio.imread(short).shape[:2]
    long_h, long_w = iio.imread(long).shape[:2]
    assert short_w > short_h and long_h > long_w


@pytest.mark.parametrize("name", sorted(T.TRAINING_ATTACKS))
def test_every_training_attack_keeps_the_size_and_8_bits_and_changes_the_image(name) -> None:
    # Phase 3 stacks its attacked images into one array: every attack it draws keeps the image's shape.
    images = _images(b=3, texture=0.2)
    first = T.apply(name, images[:1], np.random.default_rng(4))
    again = T.apply(name, images[:1], np.random.default_rng(4))
    assert first.shape == images[:1].shape and first.dtype == np.uint8
    np.testing.assert_array_equal(first, again)
    assert np.abs(first.astype(int) - images[:1]).max() > 0


def test_training_attacks_are_drawn_image_by_image_from_the_generator() -> None:
    images = _images(b=6, texture=0.2)
    one = T.random_attacks(images, np.random.default_rng(9))
    np.testing.assert_array_equal(one, T.random_attacks(images, np.random.default_rng(9)))
    other = T.random_attacks(images, np.random.default_rng(10))
    assert one.shape == images.shape and one.dtype == np.uint8
    assert not np.array_equal(one, other)
    assert all(np.abs(a.astype(int) - x).max() > 0 for a, x in zip(one, images, strict=True))
    with pytest.raises(AttackError, match="uint8"):
        T.random_attacks(images.astype(np.float32), np.random.default_rng(0))


def test_training_attacks_span_the_peers_protocol() -> None:
    # The parameters drawn reach the peers' settings (JPEG 10 and 50, σ = 0.1 noise, brightness × 2,
    # rotation 30°, rescaling to 75 %), so that the reader trains on what it is measured under.
    rng = np.random.default_rng(0)
    drawn = {name: [sample(rng) for _ in range(4000)] for name, (_, _, sample) in T.TRAINING_ATTACKS.items()}
    assert min(drawn["jpeg"]) <= 10 and max(drawn["jpeg"]) >= 90
    assert max(drawn["gaussian_noise"]) >= 0.1 and max(drawn["brightness"]) >= 2.0
    assert min(drawn["brightness"]) <= 0.55 and max(drawn["rotate"]) >= 29.0
    assert min(drawn["rescale"]) <= 0.55 and max(drawn["rescale"]) >= 1.45
