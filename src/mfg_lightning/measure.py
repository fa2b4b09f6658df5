"""Measure this machine for training: ``python -m mfg_lightning.measure [overrides ...]``.

Times what ``trainer.precision=auto`` and ``model.net.conv_impl=auto`` choose from (every
convolution as native, im2col and channels-last; a training step of the network in float32 and
bf16-mixed where the CPU runs bfloat16 natively) for the training run the same overrides
describe (its network, ``dataset.batch_size``, the thread count of ``trainer``), prints a
progress line per part and the table, and replaces the file under
``<paths.cache_dir>/machine/`` that every later training run of that shape reads
(:mod:`mfg_lightning.run.machine_profile`). A training run measures by itself only where no such
file exists; run this on a quiet machine to measure on purpose, e.g. after a busy first run
recorded the defaults.
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from mfg_lightning.core.config import CONFIG_DIR
from mfg_lightning.core.errors import exit_on_unknown_choice, exit_on_user_error
from mfg_lightning.run.run_choices import measure_machine


@exit_on_unknown_choice
@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="measure")
@exit_on_user_error
def main(cfg: DictConfig) -> None:
    profile, path = measure_machine(
        cfg, again=True, progress=lambda line: print(f"measuring {line} ...", flush=True)
    )
    print(profile.table())
    print(
        f"measured in {profile.seconds:.1f} s; kept in {path}"
        if path
        else "not kept (paths.cache_dir=null)"
    )


if __name__ == "__main__":
    main()
