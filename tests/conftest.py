"""Shared fixtures: the real scenes under ../shared/data (skipped with a reason where absent), and a tiny
fitted + watermarked procedural run built once per session (``tiny``)."""

from __future__ import annotations

import dataclasses
import fcntl
import importlib.util
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

# Tests run on CPU; keep XLA from grabbing an accelerator if one happens to be present.
os.environ.setdefault("JAX_PLATFORMS", "cpu")
# Compilation dominates the suite. XLA's backend optimisation level 0 (of 3) compiles the tests' own small
# programs fastest, but runs the library's hot programs (renders, train and embedding steps, the decoder:
# those jitted through xla_cpu.jit_cpu_tuned) far slower, and level 1 everywhere compiles the rest slower.
# So: level 0 by default, level 1 for the hot programs (set in pytest_configure through
# xla_cpu.CPU_OPTIONS). Left alone when the user's XLA_FLAGS names a level (the decision is passed to the
# pytest-xdist workers, which inherit the flags set here).
OPT_LEVEL_FLAG = "xla_backend_optimization_level"
_OPT_LEVELS_ENV = "MNERF_TEST_SETS_OPT_LEVELS"
if _OPT_LEVELS_ENV not in os.environ:
    _flags = os.environ.get("XLA_FLAGS", "")
    os.environ[_OPT_LEVELS_ENV] = "0" if OPT_LEVEL_FLAG in _flags else "1"
    if os.environ[_OPT_LEVELS_ENV] == "1":
        os.environ["XLA_FLAGS"] = f"{_flags} --{OPT_LEVEL_FLAG}=0".strip()
SET_OPT_LEVELS = os.environ[_OPT_LEVELS_ENV] == "1"
# Under pytest-xdist every worker has a core of its own: without this, each worker's XLA runs its Eigen
# kernels on a pool as wide as the machine, and the workers' threads contend for the same cores.
EIGEN_THREADS_FLAG = "xla_cpu_multi_thread_eigen"
if os.environ.get("PYTEST_XDIST_WORKER") and EIGEN_THREADS_FLAG not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} --{EIGEN_THREADS_FLAG}=false".strip()

PROJECT_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("MNERF_SHARED_DATA", PROJECT_ROOT.parent / "shared" / "data"))
JAX_CACHE_ENV = "MNERF_TEST_JAX_CACHE"
_CACHE_TO_REMOVE = pytest.StashKey[str]()


def pytest_configure(config: pytest.Config) -> None:
    """One persistent XLA compilation cache for the whole test run, shared by the pytest-xdist workers.

    Many tests compile the same programs (the embedding's phase-2 step with its 14 augmentations is slow to
    compile even on the tiny scene), in both workers and in closures that jit's in-process cache cannot
    reuse. The cache lives in a fresh temporary folder per run (removed at the end), so every run still
    compiles everything once: it saves repeats, it hides nothing. Set ``MNERF_TEST_JAX_CACHE`` to a folder to
    keep it across runs.
    """
    if JAX_CACHE_ENV not in os.environ and not hasattr(config, "workerinput"):
        # The controller (or a run without xdist) makes the folder; the workers inherit the variable.
        folder = tempfile.mkdtemp(prefix="mnerf-jax-cache-")
        os.environ[JAX_CACHE_ENV] = folder
        config.stash[_CACHE_TO_REMOVE] = folder
    import jax

    from mnerf_jax.core import xla_cpu

    if SET_OPT_LEVELS:
        xla_cpu.CPU_OPTIONS[OPT_LEVEL_FLAG] = "1"
    jax.config.update("jax_compilation_cache_dir", os.environ[JAX_CACHE_ENV])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


# pytest-xdist runs with ``--dist loadfile`` (pyproject.toml): each test file goes to one worker, except that
# these files share one worker, as they share the session's tiny runs or the programs compiled for them: the
# tiny watermarked run is built once with no worker waiting on the other's build, and jit's in-process cache
# serves every later test of the group. (``--dist loadgroup`` with ``xdist_group`` marks would say the same,
# but pytest-xdist 3.8 tags the groups through an attribute pytest 9.2 no longer reads.)
XDIST_GROUPS = {
    "test_embed.py": "tiny-watermarked",
    "test_wm_eval.py": "tiny-watermarked",
    "test_wm_cli.py": "tiny-watermarked",
    "test_model_attacks.py": "tiny-watermarked",
    "test_false_claims.py": "tiny-watermarked",
    "test_study.py": "tiny-watermarked",
    "test_cli.py": "tiny-schedule",
    "test_train.py": "tiny-schedule",
}


# Units that take longest, started first (the rest follow by their number of tests, pytest-xdist's own
# order). pytest-xdist hands out the units with most tests first, which leaves a long unit of one or two tests
# (the lego fit) for the end of the run, with the other worker idle. Only an order: a stale entry costs time,
# never a test.
LONGEST_UNITS_FIRST = (
    "tiny-watermarked",
    "test_e2e_lego.py",
    "test_decoder.py",
    "test_decoder_refit.py",
    "tiny-schedule",
    "test_sample_cache.py",
)


@pytest.hookimpl(optionalhook=True)  # a hook of pytest-xdist: unknown (and unused) where it is not installed
def pytest_xdist_make_scheduler(config: pytest.Config, log: object) -> object | None:
    """``--dist loadfile`` with the files of :data:`XDIST_GROUPS` merged into one unit each, the units of
    :data:`LONGEST_UNITS_FIRST` handed out first."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadScopeScheduling

    def rank(scope: str) -> int:
        name = Path(scope).name
        return LONGEST_UNITS_FIRST.index(name) if name in LONGEST_UNITS_FIRST else len(LONGEST_UNITS_FIRST)

    class GroupedFileScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            path = nodeid.split("::", 1)[0]
            return XDIST_GROUPS.get(Path(path).name, path)

        def _assign_work_unit(self, node: object) -> None:
            # The queue is in pytest-xdist's order; a stable sort keeps it within equal ranks.
            ordered = sorted(self.workqueue.items(), key=lambda item: rank(item[0]))
            self.workqueue.clear()
            self.workqueue.update(ordered)
            super()._assign_work_unit(node)

    return GroupedFileScheduling(config, log)


def pytest_unconfigure(config: pytest.Config) -> None:
    folder = config.stash.get(_CACHE_TO_REMOVE, None)
    if folder is not None:
        shutil.rmtree(folder, ignore_errors=True)
        del os.environ[JAX_CACHE_ENV]


@pytest.fixture
def mnerf(capsys: pytest.CaptureFixture) -> Callable[..., tuple[int, str, str]]:
    """``mnerf(*argv)`` runs the command line in this process -> ``(exit status, stdout, stderr)``."""
    from mnerf_jax import cli

    def run(*argv: object) -> tuple[int, str, str]:
        capsys.readouterr()  # only this call's output
        code = cli.main([str(a) for a in argv])
        out = capsys.readouterr()
        return code, out.out, out.err

    return run


@pytest.fixture(scope="session")
def lego_dir() -> Path:
    path = SHARED_DATA / "nerf_synthetic" / "lego"
    if not (path / "transforms_train.json").is_file():
        pytest.skip(f"real NeRF-Synthetic lego not found at {path} (set MNERF_SHARED_DATA)")
    return path


@pytest.fixture(scope="session")
def fern_dir() -> Path:
    path = SHARED_DATA / "nerf_llff_data" / "fern"
    if not (path / "poses_bounds.npy").is_file():
        pytest.skip(f"real LLFF fern not found at {path} (set MNERF_SHARED_DATA)")
    return path


# A tiny schedule with every event, for test_train.py and test_cli.py (their compilations are shared):
# alpha mask + shrink after step 30, upsampling after 38, a second alpha mask + ray filtering after 45.
# The mask threshold is raised so that a field this young already shrinks the box.
TINY_SCHEDULE = [
    "data.procedural_size=32",
    "data.procedural_views=8",
    "train.batch_size=512",
    "train.n_iters=60",
    "train.n_voxel_init=4096",
    "train.n_voxel_final=13824",
    "train.upsample_steps=38",
    "train.alpha_mask_steps=30,45",
    "render.alpha_mask_threshold=1e-3",
    "train.checkpoint_every=12",
    "train.log_every=12",
]


# ------------------------------------------------------------------ a tiny fitted and watermarked run

TINY_FIT = [
    "data.procedural_size=32",
    "data.procedural_views=12",
    "train.n_iters=150",
    "train.batch_size=1024",
    "train.n_voxel_init=27000",
    "train.n_voxel_final=27000",
    "train.upsample_steps=",
    "train.alpha_mask_steps=",
    "train.checkpoint_every=150",
    "model.density_ranks=4,4,4",
    "model.appearance_ranks=8,8,8",
    "model.app_features=12",
    "model.mlp_width=32",
]
TINY_EMBED = [
    "watermark.schedule.patch_size=16",
    "watermark.schedule.phase1_steps=40",
    "watermark.schedule.phase2_steps=40",
    "watermark.checkpoint_every=40",
    "watermark.module.wm_ranks=4,4,4",
    # 80 steps are enough with the fitted field at 0.3x the paper's rates and the uncalibrated random
    # decoder of random_decoder (its large whitening gain: tiny changes flip its bits); the CLI tests need a
    # strong watermark, not a realistic one, and 0.3x reads it while costing less PSNR than 1.0x.
    "watermark.optim.lr_source_scale=0.3",
    # The paper's losses, without the procedural preset's quality budget (the rate above was chosen so).
    "watermark.fidelity.psnr=0",
    # ... and the decoder rate and clean term that rate was chosen with (the defaults are 1e-3, 0.3).
    "watermark.optim.lr_decoder=1e-4",
    "watermark.losses.lambda_clean=0",
    # ... and none of the preset's recipe for the demo's invisibility: a budget ramp, the per-ID weighting,
    # phase 2 without attacks, phase 3 and a time budget (tests/test_decoder_refit.py turns phase 3 on).
    "watermark.fidelity.psnr_start=0",
    "watermark.losses.id_loss_power=0",
    "watermark.augment.prob=0.75",
    "watermark.phase3.steps=0",
    "watermark.phase3.negative_strength=medium",
    "watermark.time_budget.minutes=0",
    # Three of the 14 augmentations, filters that barely move a 32-px view's LL2: phase 2's step compiles
    # faster and the watermark still reads (photometric subsets such as brightness, contrast, saturation
    # leave it at chance: this decoder's whitening gain makes any colour change a large one). test_augment
    # compiles and differentiates the policy over all 14; test_embed checks that the empty default hands the
    # step the whole registry.
    "watermark.augment.names=gaussian_blur,box_blur,sharpness",
    # The paper's path, ray-marched with deferred patches and an adapting source (the procedural preset caches
    # its frozen source; tests/test_sample_cache.py embeds that way).
    "watermark.schedule.cache_source=false",
    "watermark.schedule.jitter=true",
]


# Figures every watermarked evaluation writes to eval-<split>.json (test_wm_cli, test_wm_eval).
EVALUATION_KEYS = (
    "bit_accuracy_mean",
    "bit_accuracy_min",
    "bit_accuracy_png_mean",
    "psnr",
    "psnr_clean_model",
    "ssim",
    "lpips",
    "identification_accuracy",
    "clean_bit_accuracy",
    "num_ids",
    "bits",
    "split",
    "views",
)


@dataclasses.dataclass(frozen=True)
class TinyRuns:
    """``fit``: a fitted 32-px procedural TensoRF; ``decoder``: a random 8-bit decoder file; ``wm``: a 2-ID ×
    8-bit watermarked run of ``fit`` made with ``embed_overrides``; ``seconds``: the embedding's time."""

    root: Path
    fit: Path
    decoder: Path
    wm: Path
    seconds: float
    embed_overrides: tuple[str, ...] = tuple(TINY_EMBED)


def load_script(name: str) -> ModuleType:
    """``scripts/<name>.py`` imported as a module (the scripts are not a package), so that tests call its
    ``main(argv)`` and helpers in-process."""
    spec = importlib.util.spec_from_file_location(name, PROJECT_ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def random_decoder(path: Path, bits: int, images: np.ndarray | None = None) -> Path:
    """A deterministic random-init ``bits``-bit decoder file, whitened on ``images [N, H, W, 3]`` if given
    (no decoder training needed)."""
    import jax
    import jax.numpy as jnp

    from mnerf_jax.reader import decoder, decoder_io, dwt

    variables = decoder.init_decoder(jax.random.PRNGKey(0), bits)
    if images is not None:
        rng = np.random.default_rng(0)
        batch = np.concatenate(
            [
                images,
                images[:, ::-1],
                images[:, :, ::-1],
                np.clip(images + rng.normal(0, 0.05, images.shape), 0, 1),
            ]
        ).astype(np.float32)
        variables = decoder.fit_whitening(variables, [dwt.ll2(jnp.asarray(batch))])
    decoder_io.save_decoder(
        path, variables, {"note": "random init, whitened on the procedural scene (tests)"}
    )
    return path


def build_tiny_runs(root: Path) -> TinyRuns:
    """Fit, make a decoder and embed into ``root`` (about a minute on one core)."""
    from mnerf_jax.cli.fit import fit_run
    from mnerf_jax.core.config import load_config
    from mnerf_jax.data import load_scene
    from mnerf_jax.watermark import embed

    config = load_config("procedural", TINY_FIT)
    fit_run(config, None, root / "fit", evaluate=False, quiet=True)
    scene = load_scene(None, config.data, config.render, ("train",))
    decoder = random_decoder(root / "dec8.npz", 8, scene.split("train").images)
    t0 = time.perf_counter()
    embed.embed(root / "fit", root / "wm", 2, 8, overrides=TINY_EMBED, decoder_path=decoder, progress=False)
    seconds = time.perf_counter() - t0
    (root / "seconds.txt").write_text(f"{seconds!r}\n")
    return TinyRuns(root, root / "fit", decoder, root / "wm", seconds)


@pytest.fixture(scope="session")
def make_decoder() -> Callable[..., Path]:
    """:func:`random_decoder`: ``make_decoder(path, bits, images=None)`` writes a decoder file."""
    return random_decoder


@pytest.fixture(scope="session")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> TinyRuns:
    """The tiny fitted and watermarked runs, built once per test session (shared: tests that write into them
    work on copies or on new names under ``root``).

    Under pytest-xdist (``-n N``) the files that use them share one worker (:data:`XDIST_GROUPS`). Under
    another ``--dist`` mode, where they may not, the first worker to ask builds the runs in the directory the
    workers share, under an exclusive lock, and the others wait for it and reuse them instead of spending
    another minute of the two cores on the same build."""
    base = tmp_path_factory.getbasetemp()
    shared = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    root = shared / "tiny-runs"
    with open(shared / "tiny-runs.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # POSIX; released when the file closes
        done = root / "seconds.txt"
        if done.is_file():
            return TinyRuns(root, root / "fit", root / "dec8.npz", root / "wm", float(done.read_text()))
        if root.exists():
            shutil.rmtree(root)  # a build interrupted before it finished
        root.mkdir()
        return build_tiny_runs(root)
