"""The suite sees only what it sets up: a user's git-ignored ``conf/local/default.yaml`` reaches no
test's composition (``conftest.py`` sets ``MFG_LOCAL_CONFIG=none``), and an in-process
``train(cfg)`` leaves the process's floating-point and allocator settings as it found them."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import mfg_lightning.core.config as config_module
from allocator import has_mallinfo2
from conftest import REPO
from mfg_lightning.core.command_line import check_command_line
from mfg_lightning.core.config import CONFIG_DIR, compose

#: A user's own settings, as docs/datasets.md shows them: another data directory and a trainer.
LOCAL = "# @package _global_\npaths:\n  data_dir: /mnt/elsewhere\ntrainer:\n  max_steps: 7\n"


@pytest.fixture
def configs_with_a_local_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A copy of the configs holding a user's ``local/default.yaml``, read by every compose."""
    conf = tmp_path / "conf"
    shutil.copytree(CONFIG_DIR, conf)
    (conf / "local" / "default.yaml").write_text(LOCAL)
    monkeypatch.setattr(config_module, "CONFIG_DIR", str(conf))
    return conf


@pytest.mark.parametrize("name", ["train", "train_flow", "evaluate", "predict", "export"])
def test_a_users_local_config_reaches_no_test(configs_with_a_local_file: Path, name: str) -> None:
    overrides = {"evaluate": ["ckpt_path=x"], "predict": ["ckpt_path=x", "dataset=synthetic"]}
    overrides = overrides.get(name, [])
    cfg = compose(name, overrides)
    assert cfg.paths.data_dir != "/mnt/elsewhere"
    assert "trainer" not in cfg or cfg.trainer.max_steps != 7
    # The command line check composes the same way.
    assert check_command_line(name, overrides, "m").error is None


def test_a_users_local_config_still_reaches_the_user(
    configs_with_a_local_file: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    assert os.environ["MFG_LOCAL_CONFIG"] == "none"  # conftest's, inherited by entry points
    monkeypatch.delenv("MFG_LOCAL_CONFIG")  # as a user's shell has it
    cfg = compose("train")
    assert cfg.paths.data_dir == "/mnt/elsewhere" and cfg.trainer.max_steps == 7
    assert compose("train", ["trainer.max_steps=3"]).trainer.max_steps == 3  # the command wins


TRAIN_IN_PROCESS = """
import json, sys
import torch
from allocator import big_block_from_mmap
from mfg_lightning.core import denormals, host_memory
from mfg_lightning.core.config import compose
import mfg_lightning.run.training as training

def settings():
    # what a training may change in its process: whether the calling thread and every thread of
    # torch's pool flush subnormals, the allocator's settings as recorded, and as a block shows
    return [denormals.calling_thread_flushes(), denormals.every_thread_flushes(),
            list(host_memory.allocator_settings()), big_block_from_mmap()]

before, inside = settings(), []
inner = training._train
training._train = lambda cfg: (inside.append(settings()), inner(cfg))[1]
cfg = compose("train", ["debug=tiny", "trainer.max_steps=2", "test=false", "logger=none",
                        "callbacks=none", f"paths.output_dir={sys.argv[1]}"])
training.train(cfg)
after = settings()
flushes = torch.set_flush_denormal(True)  # whether this CPU can flush at all
torch.set_flush_denormal(False)
print(json.dumps({"before": before, "inside": inside[0], "after": after, "flushes": flushes,
                  "kept": list(host_memory.KEPT)}))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator")
def test_a_training_returns_with_the_process_settings_as_they_were(tmp_path: Path) -> None:
    """An in-process ``train(cfg)`` (a notebook's, a test's) flushes subnormals and keeps freed
    memory while it trains, and sets both back when it returns. In a fresh process, as a
    notebook's: one that trained before may serve a large block from a free chunk its heap
    kept, whatever the settings."""
    if not has_mallinfo2():
        pytest.skip("this C library has no mallinfo2 (glibc 2.33 and later)")
    proc = subprocess.run([sys.executable, "-c", TRAIN_IN_PROCESS, str(tmp_path / "run")],
                          capture_output=True, text=True, cwd=REPO / "tests",
                          timeout=300)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    seen = json.loads(proc.stdout.strip().splitlines()[-1])
    before, inside, after = seen["before"], seen["inside"], seen["after"]
    assert before[0] is False and before[2] != seen["kept"] and before[3] is True
    assert inside[0] is seen["flushes"] and inside[2:] == [seen["kept"], False]
    assert after == before
