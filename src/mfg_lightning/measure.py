"""Measure this machine for training: ``python -m mfg_lightning.measure [overrides ...]``.

Times what ``trainer.precision=auto`` and ``model.net.conv_impl=auto`` choose between (every
convolution as native, im2col and channels-last; a training step of the network in float32 and
bf16-mixed where the CPU runs bfloat16 natively) for the training run the same overrides
describe (its network, ``dataset.batch_size``, the thread count of ``trainer``). It prints the
table and this CPU kind's row, and writes the row to ``conf/local/cpu_defaults.yaml``
(git-ignored), which every later training run on this machine reads
(:mod:`mfg_lightning.run.run_choices`). Add the row to ``conf/cpu_defaults.yaml`` to make it
the default of every machine of this kind. Run it on a quiet machine.
"""

from __future__ import annotations

import hydra
import yaml
from omegaconf import DictConfig

from mfg_lightning.core.config import CONFIG_DIR
from mfg_lightning.core.errors import exit_on_unknown_choice, exit_on_user_error
from mfg_lightning.core.machine import cpu_kind
from mfg_lightning.run.machine_profile import measure_run
from mfg_lightning.run.run_choices import write_local_row


@exit_on_unknown_choice
@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="measure")
@exit_on_user_error
def main(cfg: DictConfig) -> None:
    found, row = measure_run(cfg, progress=lambda line: print(f"measuring {line} ...", flush=True))
    print(found.table())
    path = write_local_row(row, cfg.get("write_row_to"))
    print(f"\nmeasured in {found.seconds:.1f} s; this machine's row, written to {path}:\n")
    print(yaml.safe_dump({cpu_kind(): row}, sort_keys=False, width=100))
    print("Add it to conf/cpu_defaults.yaml to make it the default of every machine of its kind.")


if __name__ == "__main__":
    main()
