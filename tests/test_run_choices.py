"""``trainer.precision=auto`` and ``model.net.conv_impl=auto`` made concrete once from the
committed table (mfg_lightning.run.run_choices): each CPU kind's row, the local row winning,
the plain defaults for a kind the table lacks, a GPU, a resume, the config frozen after it is
resolved, and two runs on fresh caches (one beside a busy process) computing bit for bit alike.
Nothing here pins the kernels: the trainings run the defaults."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from hydra.utils import instantiate
from omegaconf import OmegaConf
from omegaconf.errors import ReadonlyConfigError

from conftest import TINY_TRAINING, entry_point_env
from mfg_lightning.core.config import CONFIG_DIR, compose
from mfg_lightning.models.conv import CONV_IMPLS, switchable_layers
from mfg_lightning.run import run_choices
from mfg_lightning.run.run_choices import (
    choice_overrides,
    net_geometry,
    read_table,
    resolve_run_choices,
)
from mfg_lightning.run.training import run_config

TABLE = Path(CONFIG_DIR) / "cpu_defaults.yaml"


def _cfg(tmp_path: Path, *overrides: str):
    return compose("train", [f"paths.output_dir={tmp_path / 'run'}", *overrides])


def test_the_committed_table_has_a_row_per_cpu_kind_for_the_quick_starts_network(
    tmp_path: Path,
) -> None:
    """Intel with AVX-512, bf16 and AMX; AMD with AVX-512 and bf16; AMD with AVX2 only: each row
    names its measurement and holds one implementation per convolution of the network it was
    measured on, the quick start's."""
    rows = read_table(TABLE)
    assert set(rows) == {"amx_bf16", "avx512_bf16", "avx2"}
    cfg = _cfg(tmp_path)
    layers = len(list(switchable_layers(instantiate(cfg.model.net))))
    for kind, row in rows.items():
        assert row["net"] == net_geometry(cfg.model.net), kind
        assert row["precision"] in ("32-true", "bf16-mixed") and row["measured"], kind
        for kernels in row["conv_impl"].values():
            listed = [kernels] * layers if isinstance(kernels, str) else kernels
            assert len(listed) == layers and set(listed) <= set(CONV_IMPLS), kind
    assert rows["avx2"]["precision"] == "32-true" and "bfloat16" not in rows["avx2"]["conv_impl"]


@pytest.fixture
def on_kind(monkeypatch: pytest.MonkeyPatch, tmp_path: Path):
    """Pretend to be a CPU kind, with or without native bfloat16, with a local table under
    ``tmp_path`` (absent unless a test writes it)."""
    local = tmp_path / "local" / "cpu_defaults.yaml"
    monkeypatch.setattr(run_choices, "table_files", lambda: [local, TABLE])

    def set_kind(kind: str, native_bf16: bool) -> Path:
        monkeypatch.setattr(run_choices, "cpu_kind", lambda: kind)
        monkeypatch.setattr(run_choices, "cpu_has_native_bf16", lambda: native_bf16)
        return local

    return set_kind


def test_auto_is_the_row_of_this_cpu_kind(tmp_path: Path, on_kind) -> None:
    rows = read_table(TABLE)
    on_kind("amx_bf16", True)
    cfg = _cfg(tmp_path)
    assert resolve_run_choices(cfg) == "conf/cpu_defaults.yaml row amx_bf16"
    assert cfg.trainer.precision == "bf16-mixed"
    assert list(cfg.model.net.conv_impl) == rows["amx_bf16"]["conv_impl"]["bfloat16"]
    # float32 given: the row's float32 kernels
    cfg = _cfg(tmp_path, "trainer.precision=32-true")
    resolve_run_choices(cfg)
    assert list(cfg.model.net.conv_impl) == rows["amx_bf16"]["conv_impl"]["float32"]
    # another network than the row's: native
    cfg = _cfg(tmp_path, *TINY_TRAINING)
    resolve_run_choices(cfg)
    assert (cfg.trainer.precision, cfg.model.net.conv_impl) == ("bf16-mixed", "native")
    # the row says bf16-mixed, but this CPU emulates bfloat16 (e.g. capped by ONEDNN_MAX_CPU_ISA)
    on_kind("amx_bf16", False)
    cfg = _cfg(tmp_path)
    resolve_run_choices(cfg)
    assert cfg.trainer.precision == "32-true"
    assert list(cfg.model.net.conv_impl) == rows["amx_bf16"]["conv_impl"]["float32"]
    on_kind("avx2", False)
    cfg = _cfg(tmp_path)
    resolve_run_choices(cfg)
    assert (cfg.trainer.precision, cfg.model.net.conv_impl) == ("32-true", "native")


def test_a_kind_missing_from_the_table_gets_the_plain_defaults(tmp_path: Path, on_kind) -> None:
    """32-true and native, even where bfloat16 is native: bf16-mixed only where it was measured
    faster, on the network it was measured on."""
    on_kind("aarch64", True)
    cfg = _cfg(tmp_path)
    assert resolve_run_choices(cfg) == "plain defaults (no row for aarch64)"
    assert (cfg.trainer.precision, cfg.model.net.conv_impl) == ("32-true", "native")
    # a network the rows were not measured on (no switchable convolutions): float32 too
    on_kind("amx_bf16", True)
    cfg = _cfg(tmp_path, "~model.net.conv_impl")
    assert resolve_run_choices(cfg) == "plain defaults (another network)"
    assert cfg.trainer.precision == "32-true"


def test_the_local_row_wins_over_the_committed_one(tmp_path: Path, on_kind) -> None:
    local = on_kind("avx2", False)
    run_choices.write_local_row(
        {"precision": "32-true", "net": net_geometry(_cfg(tmp_path).model.net),
         "conv_impl": {"float32": ["im2col"] * 8}},
        local,
    )  # fmt: skip
    cfg = _cfg(tmp_path)
    assert resolve_run_choices(cfg) == "local/cpu_defaults.yaml row avx2"
    assert list(cfg.model.net.conv_impl) == ["im2col"] * 8


def test_a_gpu_and_concrete_settings_read_no_table(tmp_path: Path, on_kind) -> None:
    on_kind("amx_bf16", True)
    cfg = _cfg(tmp_path, "trainer.accelerator=gpu")
    assert resolve_run_choices(cfg) == "a GPU"
    assert (cfg.trainer.precision, cfg.model.net.conv_impl) == ("32-true", "native")
    impls = "[native,im2col,native,channels_last,native,native,im2col,native]"
    cfg = _cfg(tmp_path, "trainer.precision=32-true", f"model.net.conv_impl={impls}")
    assert resolve_run_choices(cfg) is None


def test_a_resume_takes_what_its_run_began_with(tmp_path: Path, on_kind) -> None:
    """The run's config.yaml beside the checkpoint wins over the table (which may have changed
    since, or be another machine's)."""
    on_kind("amx_bf16", True)
    run = tmp_path / "before"
    (run / "checkpoints").mkdir(parents=True)
    (run / "config.yaml").write_text(yaml.safe_dump(
        {"trainer": {"precision": "32-true"}, "model": {"net": {"conv_impl": ["im2col"] * 8}}}
    ))  # fmt: skip
    cfg = _cfg(tmp_path)
    assert resolve_run_choices(cfg, str(run / "checkpoints" / "last.ckpt")) == (
        "the run resumed from"
    )
    assert cfg.trainer.precision == "32-true" and list(cfg.model.net.conv_impl) == ["im2col"] * 8


def test_the_first_process_hands_its_values_on_the_command_line(tmp_path: Path) -> None:
    """What Lightning's launcher appends to the command line of the processes it starts
    composes to the same values: no environment variable carries them."""
    impls = "[im2col,native,native,native,native,native,native,channels_last]"
    cfg, _ = run_config(_cfg(tmp_path, f"model.net.conv_impl={impls}"))
    handed = choice_overrides(cfg)
    child = compose("train", [f"paths.output_dir={tmp_path / 'run'}", *handed])
    assert child.trainer.precision == cfg.trainer.precision != "auto"
    assert list(child.model.net.conv_impl) == list(cfg.model.net.conv_impl)


def test_the_config_is_not_changed_after_it_is_resolved(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The run's config is resolved once and frozen: a real training (every default callback,
    TensorBoard) runs on it without a change, and config.yaml is that config."""
    from mfg_lightning.run import training

    seen = []

    def spy(cfg, ckpt_path=None):
        seen.append(run_config(cfg, ckpt_path))
        return seen[-1]

    monkeypatch.setattr(training, "run_config", spy)
    tiny = [o for o in TINY_TRAINING if not o.startswith(("logger", "callbacks"))]
    given = compose("train", [*tiny, f"paths.output_dir={tmp_path / 'run'}",
                              f"paths.cache_dir={tmp_path / 'cache'}"])  # fmt: skip
    before = OmegaConf.to_yaml(given)
    training.train(given)
    ((frozen, _),) = seen
    assert OmegaConf.is_readonly(frozen)
    with pytest.raises(ReadonlyConfigError):
        frozen.trainer.precision = "bf16-mixed"
    recorded = OmegaConf.load(tmp_path / "run" / "config.yaml")
    assert recorded == frozen and recorded.trainer.precision != "auto"
    assert OmegaConf.to_yaml(given) == before  # the caller's config is left as it was


def test_unmeasured_auto_precision_is_float32_and_native_bf16_is_read_from_the_cpu(
    monkeypatch,
) -> None:
    """Outside a training run ``auto`` is float32 on any device; whether the CPU has native
    bfloat16, which decides whether a row's bf16-mixed applies, follows torch's checks and
    oneDNN's instruction-set cap."""
    from mfg_lightning.run import precision as mfg_module

    for explicit in ("32-true", "bf16-mixed", "16-mixed", "bf16-true"):
        assert mfg_module.resolve_precision(explicit, "cpu") == explicit
    monkeypatch.setattr(mfg_module, "cpu_has_native_bf16", lambda: True)
    assert mfg_module.resolve_precision("auto", "cpu") == "32-true"
    assert mfg_module.resolve_precision("auto", "gpu") == "32-true"
    monkeypatch.undo()
    assert isinstance(mfg_module.cpu_has_native_bf16(), bool)
    # oneDNN capped below native bfloat16 (an AVX2 machine imitated): float32.
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "avx2")
    assert mfg_module.cpu_has_native_bf16() is False
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX512_CORE_BF16")  # a cap that keeps it
    native = [mfg_module.torch.cpu._is_avx512_bf16_supported(),
              mfg_module.torch.cpu._is_amx_tile_supported()]  # fmt: skip
    assert mfg_module.cpu_has_native_bf16() is any(native)


def test_auto_precision_is_recorded_in_the_run_config(tmp_path: Path) -> None:
    """The default ``trainer.precision=auto`` is made concrete before anything is written: the
    run's config.yaml says what it trained in, its CPU kind's row of conf/cpu_defaults.yaml;
    evaluation defaults to float32."""
    from conftest import tiny_training
    from mfg_lightning.run.precision import cpu_has_native_bf16
    from mfg_lightning.run.run_choices import cpu_row

    assert compose("train").trainer.precision == "auto"
    assert compose("evaluate", ["ckpt_path=x"]).trainer.precision == "32-true"
    run = tiny_training(tmp_path)
    recorded = OmegaConf.load(run / "config.yaml").trainer.precision
    row, source = cpu_row()
    wanted = (row or {}).get("precision", "32-true")
    assert recorded == (wanted if cpu_has_native_bf16() else "32-true")
    info = json.loads((run / "run_info.json").read_text())
    assert info["precision_and_kernels_from"] == source


def _test_metrics(run: Path) -> dict[str, float | None]:
    metrics = json.loads((run / "metrics.json").read_text())["metrics"]
    return {k: v for k, v in metrics.items() if k.startswith("test/")}


@pytest.mark.slow
def test_two_runs_on_fresh_caches_one_beside_a_busy_process_agree_bit_for_bit(
    tmp_path: Path,
) -> None:
    """The defaults (``auto`` both), each run on its own fresh cache, the second with a process
    spinning a CPU-bound loop beside it: the same precision and kernels, the same test metrics
    to the last bit."""
    args = [*TINY_TRAINING, "trainer.max_steps=4", "seed=5"]
    runs = []
    for name in ("quiet", "busy"):
        home = tmp_path / name
        home.mkdir()
        busy = None
        if name == "busy":
            busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
        try:
            command = [sys.executable, "-m", "mfg_lightning.train", *args]
            subprocess.run(
                [*command, f"hydra.run.dir={home / 'run'}"], cwd=home, env=entry_point_env(home),
                check=True, capture_output=True, timeout=600,
            )  # fmt: skip
        finally:
            if busy is not None:
                busy.kill()
                busy.wait()
        runs.append(home / "run")
    configs = [OmegaConf.load(run / "config.yaml") for run in runs]
    assert configs[0].trainer.precision == configs[1].trainer.precision
    assert configs[0].model.net.conv_impl == configs[1].model.net.conv_impl
    quiet, busy = (_test_metrics(run) for run in runs)
    assert quiet == busy and "test/ate" in quiet
