"""``scripts/eval_decoder.py``: a decoder's held-out figures per image side, on a small random decoder."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from conftest import load_script

from mnerf_jax.core.watermark_config import ReadingConfig
from mnerf_jax.reader.train import evaluation


def _main(argv: list[str]) -> int:
    return load_script("eval_decoder").main(argv)


def test_batches_hold_about_the_same_pixels_at_every_side() -> None:
    assert evaluation.sized_batch(64) == 32 and evaluation.sized_batch(32) == 128
    assert evaluation.sized_batch(800) == 1 and evaluation.sized_batch(4000) == 1
    for side in (64, 128, 256, 512):
        assert abs(evaluation.sized_batch(side) * side**2 - 32 * 64**2) <= side**2 / 2


def test_eval_decoder_reports_every_side(tmp_path: Path, make_decoder, capsys) -> None:
    decoder = make_decoder(tmp_path / "dec8.npz", 8)
    out = tmp_path / "sizes.json"
    argv = ["--decoder", str(decoder), "--sizes", "16,32", "--images", "3", "--iterations", "1"]
    code = _main([*argv, "--draws", "0", "--json", "--out", str(out), "--read-side", "16"])
    assert code == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed == json.loads(out.read_text())
    assert printed["bits"] == 8 and printed["read_side"] == 16 and list(printed["sizes"]) == ["16px", "32px"]
    for row in printed["sizes"].values():
        informed = row["informed"]["1_iterations"]
        assert 0.0 <= informed["bit_acc_none"] <= 1.0 and informed["bit_acc_low"] is None
        assert informed["psnr_min"] >= printed["target_psnr"] - 1e-3  # every image at ≥ the stated PSNR
        clean = row["clean"]
        assert 0.0 <= clean["bias_mean"] <= clean["bias_max"] <= 0.5 and 0.0 <= clean["ones_mean"] <= 1.0
        assert "encoder" not in row
    # By default the script reads as mnerf extract reads a render.
    assert _main([*argv, "--draws", "0", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["read_side"] == ReadingConfig().max_side
    # The table names every side; bad input is one line.
    assert _main([*argv, "--draws", "0", "--read-side", "0"]) == 0
    table = capsys.readouterr().out
    assert "| 16px |" in table and "| 32px |" in table
    assert _main(["--decoder", str(tmp_path / "absent.npz"), "--sizes", "16"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("eval_decoder: error:")


def test_eval_decoder_reads_an_encoder_writing_for_the_downscaled_read(
    tmp_path: Path, make_decoder, capsys
) -> None:
    import jax

    from mnerf_jax.reader.train import hidden_encoder, recipe

    decoder = make_decoder(tmp_path / "dec8.npz", 8)
    cfg = recipe.DecoderTrainConfig(bits=8, target_psnr=30.0)
    encoder = tmp_path / "encoder.npz"
    hidden_encoder.save_encoder(encoder, hidden_encoder.init_encoder(jax.random.PRNGKey(0), 8), cfg)
    argv = ["--decoder", str(decoder), "--encoder", str(encoder), "--sizes", "16,48", "--images", "2"]
    code = _main([*argv, "--iterations", "1", "--draws", "0", "--read-side", "16", "--json"])
    assert code == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["encoder"] == str(encoder) and printed["target_psnr"] == 30.0
    for row in printed["sizes"].values():
        assert 0.0 <= row["encoder"]["bit_acc_none"] <= 1.0 and row["encoder"]["bit_acc_low"] is None
        assert row["encoder"]["psnr_min"] >= 30.0 - 1e-3
    # An encoder for another message length is refused in one line.
    other = tmp_path / "encoder16.npz"
    enc16 = hidden_encoder.init_encoder(jax.random.PRNGKey(0), 16)
    hidden_encoder.save_encoder(other, enc16, recipe.DecoderTrainConfig(bits=16))
    assert _main(["--decoder", str(decoder), "--encoder", str(other), "--sizes", "16"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "writes 16-bit messages" in err[0]


def test_clean_bit_balance_counts_ones_per_bit(make_decoder, tmp_path: Path) -> None:
    from mnerf_jax.reader import decoder_io

    loaded = decoder_io.load_decoder(make_decoder(tmp_path / "dec8.npz", 8))
    images = np.random.default_rng(0).uniform(0, 1, (6, 16, 16, 3)).astype(np.float32)
    balance = evaluation.clean_bit_balance(loaded.variables, images, loaded.wavelet, batch=4)
    logits = np.asarray(evaluation.dec.decode_logits(loaded.variables, images, loaded.wavelet))
    ones = (logits > 0).mean(axis=0)
    assert balance["ones_mean"] == float(ones.mean())
    assert balance["bias_max"] == float(np.abs(ones - 0.5).max())
