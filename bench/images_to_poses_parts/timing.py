"""What ``bench/images_to_poses.py`` times: one :func:`mfg_lightning.run.prediction.predict`
call (:func:`time_predict`), and one pass over a folder with each stage timed alone
(:func:`time_stages`), the MFG's stages and the classical method's (:data:`CLASSICAL`), with
the functions the predict path calls."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

#: The classical row: its name in the accuracy tables and OpenCV's robust estimator.
CLASSICAL = ("essential matrix + MAGSAC++ (OpenCV)", "USAC_MAGSAC")
MFG_STAGES = ("read", "flow", "network", "recovery", "composition")
CLASSICAL_STAGES = ("read", "flow", "method", "composition")
STAGE_NOTES = {
    "read": "PNG decode, resize to the input (its cache written once), grey; each frame twice, "
    "as the loader decodes it (source of one pair, target of the other)",
    "flow": "the estimator (DIS on the grey frames; the learned network on the RGB ones), "
    "resized to the input (its cache write: the rest)",
    "network": "the module's forward, in batches of the predict loader",
    "recovery": "closed-form (t, ω) from the fields",
    "method": "frame by frame on the same flows",
    "composition": "motions → camera-to-world poses",
}


def time_predict(cfg: Any) -> float:
    """Seconds of one :func:`mfg_lightning.run.prediction.predict` call."""
    from mfg_lightning.run.prediction import predict

    start = time.perf_counter()
    predict(cfg)
    return time.perf_counter() - start


@dataclass
class Stages:
    """Seconds per stage over one pass of the folder's pairs."""

    pairs: int
    mfg: dict[str, float] = field(default_factory=dict)
    classical: dict[str, float] = field(default_factory=dict)


def time_stages(cfg: Any) -> Stages:
    """One pass over the folder of ``cfg``, each stage timed alone with the functions the
    predict path calls (``bench/images_to_poses.py``'s docstring, item 2); the flow and RGB
    caches are those of ``cfg``, empty, as for :func:`time_predict`."""
    import numpy as np
    import torch
    from hydra.utils import instantiate

    from mfg_lightning.core import geometry
    from mfg_lightning.data import transforms
    from mfg_lightning.data.sample import sanitize_flow
    from mfg_lightning.models.mfg import validate_top_k
    from mfg_lightning.motion.baselines import essential_matrix_motion
    from mfg_lightning.run.checkpoints import module_from_checkpoint
    from mfg_lightning.run.prediction import PredictedSequence

    module = module_from_checkpoint(cfg.ckpt_path, top_k=validate_top_k(cfg.model.get("top_k")))
    module.eval()
    datamodule = instantiate(cfg.dataset)
    dataset = datamodule.dataset("predict")
    clock = time.perf_counter
    read = flow_s = 0.0
    flows, valids = [], []
    for seq, src, tgt in dataset.samples:  # the loader's order: frames 0 → 1, 1 → 2, …
        start = clock()
        _, gray0 = dataset._decode(seq, src)
        _, gray1 = dataset._decode(seq, tgt)
        read += clock() - start
        start = clock()
        flow = dataset._estimate(seq, src, tgt, gray0, gray1)
        flow_s += clock() - start
        flow_t, valid, _ = sanitize_flow(
            transforms.flow_to_tensor(flow), torch.from_numpy(np.isfinite(flow).all(axis=2))
        )
        flows.append(flow_t)
        valids.append(valid)
    seq = dataset.samples[0][0]
    K = dataset.intrinsics(seq)
    frames = np.array([src for _, src, _ in dataset.samples])
    stages = Stages(len(flows))
    network = recovery = 0.0
    t_all, w_all = [], []
    batch = int(datamodule.eval_batch_size)
    with torch.inference_mode():
        for i in range(0, len(flows), batch):
            x = torch.stack(flows[i : i + batch])
            k = torch.stack([K] * x.shape[0])  # as the loader collates it
            start = clock()
            out = module(x)
            network += clock() - start
            start = clock()
            t, w = geometry.recover_motion(out.v_t, out.v_omega, k)
            recovery += clock() - start
            t_all.append(t.double())
            w_all.append(w.double())
    start = clock()
    PredictedSequence(frames, torch.cat(t_all), torch.cat(w_all), None).trajectory()
    compose_mfg = clock() - start
    method = 0.0
    t_c, w_c = [], []
    for flow_t, valid in zip(flows, valids, strict=True):
        start = clock()
        t, w = essential_matrix_motion(flow_t[None], K, valid[None], method=CLASSICAL[1])
        method += clock() - start
        t_c.append(t)
        w_c.append(w)
    start = clock()
    PredictedSequence(frames, torch.cat(t_c), torch.cat(w_c), None).trajectory()
    compose_classical = clock() - start
    stages.mfg = {"read": read, "flow": flow_s, "network": network, "recovery": recovery,
                  "composition": compose_mfg}  # fmt: skip
    stages.classical = {"read": read, "flow": flow_s, "method": method,
                        "composition": compose_classical}  # fmt: skip
    return stages
