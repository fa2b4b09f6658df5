"""Training rates, the measurement under most sections: samples per second through the Lightning
Trainer (:func:`lightning_rate`, :func:`training_epochs`) and through a bare PyTorch loop written
here (:func:`bare_step_fn`, :func:`bare_rate`) whose options are the candidate speed-ups, and
the two step by step in one process (:func:`paired_steps`)."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Iterator
from typing import Any

import torch

from .measure import build_model


class InMemory:
    """The same pre-collated batches, cycled for ``length`` steps (an iterable Lightning takes
    as a train dataloader without wrapping it in a sampler)."""

    def __init__(self, batches: list[dict], length: int) -> None:
        self.batches, self.length = batches, length

    def __iter__(self) -> Iterator[dict]:
        return (self.batches[i % len(self.batches)] for i in range(self.length))

    def __len__(self) -> int:
        return self.length


def steady_rate(stamps: list[float], warmup: int, batch_size: int) -> float:
    """Samples per second from the end-of-step timestamps, after ``warmup`` steps: the batch
    over the median step time. On a shared machine a step that another process stalls takes
    several times its usual time; a total over the steps counts every stall, the median ignores
    the few there are (the machine profile's rule, :mod:`mfg_lightning.run.machine_profile`, is
    robust the same way)."""
    times = [b - a for a, b in zip(stamps[warmup - 1 : -1], stamps[warmup:], strict=True)]
    return batch_size / statistics.median(times)


def quiet_trainer(stamp: Any, **limits: Any) -> Any:
    """A one-CPU ``lightning.Trainer`` that trains and does nothing else (no logger,
    checkpoints, progress bar, summary or validation), ``stamp`` its one callback; ``limits``:
    its ``max_steps``, ``max_epochs``, ``precision``."""
    import lightning as L

    return L.Trainer(
        accelerator="cpu", devices=1, logger=False, enable_checkpointing=False,
        enable_progress_bar=False, enable_model_summary=False, num_sanity_val_steps=0,
        limit_val_batches=0, callbacks=[stamp], **limits,
    )  # fmt: skip


def lightning_rate(
    overrides: list[str],
    batches: list[dict] | None,
    warmup: int,
    steps: int,
    precision: str = "32-true",
    loader: Any = None,
    batch_size: int | None = None,
) -> float:
    """Training samples per second through ``lightning.Trainer.fit`` at ``precision``, on the
    in-memory ``batches`` or on ``loader`` (a real DataLoader, its loading included)."""
    import lightning as L

    stamps: list[float] = []

    class Stamp(L.Callback):
        def on_train_batch_end(self, *args: Any, **kwargs: Any) -> None:
            stamps.append(time.perf_counter())

    model, _ = build_model(overrides)
    trainer = quiet_trainer(Stamp(), max_steps=warmup + steps, precision=precision)
    data = loader if loader is not None else InMemory(batches, warmup + steps)
    trainer.fit(model, train_dataloaders=data)
    return steady_rate(stamps, warmup, batch_size or batches[0]["flow"].shape[0])


def training_epochs(
    overrides: list[str], data: Any, warmup: int, epochs: int = 2
) -> tuple[float, float]:
    """Training samples per second (Lightning, float32) on ``data`` (a DataModule: its training
    loader; else an iterable of batches) in the first epoch (after ``warmup`` steps) and in the
    ``epochs - 1`` after it together (their first step included)."""
    import lightning as L

    stamps: list[tuple[int, float, int]] = []

    class Stamp(L.Callback):
        def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx) -> None:
            stamps.append((trainer.current_epoch, time.perf_counter(), batch["flow"].shape[0]))

    model, _ = build_model(overrides)
    trainer = quiet_trainer(Stamp(), max_epochs=epochs, max_steps=-1)
    if isinstance(data, L.LightningDataModule):
        trainer.fit(model, datamodule=data)
    else:
        trainer.fit(model, train_dataloaders=data)
    first = [s for s in stamps if s[0] == 0]
    later = [s for s in stamps if s[0] >= 1]
    rate1 = sum(n for _, _, n in first[warmup:]) / (first[-1][1] - first[warmup - 1][1])
    rate2 = sum(n for _, _, n in later) / (later[-1][1] - first[-1][1])
    return rate1, rate2


def patch_first_conv(net: Any, how: str) -> None:
    """A candidate for the first convolution (2 input channels) under bf16 autocast, patched
    onto this network instance only: ``"fp32"`` runs it in float32 outside autocast (its output
    cast to bfloat16 once for the next layer); ``"pad8"`` zero-pads its input channels and
    weights to 8 (the same numbers: the padded channels are zeros)."""
    import torch.nn.functional as F

    conv = net.encoder[0]

    if how == "fp32":

        def forward(x):
            with torch.autocast("cpu", enabled=False):
                y = conv._conv_forward(x.float(), conv.weight, conv.bias)
            return y.to(torch.bfloat16) if torch.is_autocast_enabled("cpu") else y

    elif how == "pad8":

        def forward(x):
            pad = (0, 0, 0, 0, 0, 8 - x.shape[1])
            return conv._conv_forward(F.pad(x, pad), F.pad(conv.weight, pad), conv.bias)

    else:
        raise ValueError(how)
    conv.forward = forward


def bare_step_fn(
    model: Any,
    channels_last: bool = False,
    compile_net: bool = False,
    autocast: bool = False,
    first_conv: str | None = None,
    conv_impls: dict[str, str] | None = None,
) -> Callable[[dict], None]:
    """One training step written in plain PyTorch, on the module's network, loss and optimiser.

    ``autocast``: the encoder under CPU bf16 autocast, the decoders in float32 (``MFG.decode``
    leaves autocast itself): what the module runs under ``trainer.precision=bf16-mixed``. The
    other options are the candidate speed-ups of the step; all off is the float32 reference.
    ``conv_impls``: an implementation per convolution (its module name → ``native``, ``im2col``
    or ``channels_last``), e.g. what ``model.net.conv_impl=auto`` chose.
    """
    from mfg_lightning.core import geometry
    from mfg_lightning.models.conv import switchable_layers

    net, loss_fn = model.net, model.loss_fn
    layers = dict(switchable_layers(net))
    for name, impl in (conv_impls or {}).items():
        layers[name].impl = impl
    if channels_last:
        net = net.to(memory_format=torch.channels_last)
    if first_conv:
        patch_first_conv(net, first_conv)
    optimizer = model.optimizer_factory(params=net.parameters())
    forward = torch.compile(net) if compile_net else net
    net.train()

    def step(batch: dict) -> None:
        flow, K = batch["flow"], batch["intrinsics"]
        height, width = flow.shape[-2:]
        if channels_last:
            flow = flow.contiguous(memory_format=torch.channels_last)
        t, w = geometry.pose_to_motion(batch["pose"])
        v_t = geometry.translational_field(t, K, height, width)
        v_w = geometry.rotational_field(w, K, height, width)
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
            out = forward(flow)
        terms = loss_fn(out.v_t.float(), out.v_omega.float(), v_t, v_w, out.hidden.float())
        optimizer.zero_grad()
        terms.total.backward()
        optimizer.step()

    return step


def bare_rate(
    overrides: list[str], batches: list[dict], warmup: int, steps: int, **options: Any
) -> float:
    """Training samples per second of :func:`bare_step_fn` (same model build and seed)."""
    model, _ = build_model(overrides)
    step = bare_step_fn(model, **options)
    stamps = []
    for batch in InMemory(batches, warmup + steps):
        step(batch)
        stamps.append(time.perf_counter())
    return steady_rate(stamps, warmup, batches[0]["flow"].shape[0])


def paired_steps(
    overrides: list[str], batches: list[dict], warmup: int, steps: int, precision: str
) -> list[tuple[float, float]]:
    """Lightning's step and the bare loop's, alternated step by step in one process: after each
    Lightning step (``on_train_batch_end``) one bare step of a twin model (same build and seed)
    on the same batch. Returns ``(Lightning s, bare s)`` of every step after ``warmup``.

    A Lightning step's time runs from the end of the bare step before it to its own
    ``on_train_batch_end``: Lightning's loop, hooks, closure and batch fetch included. The two
    of a pair ran milliseconds apart, so a change of the machine's load reaches both: their
    ratio is steady where rates taken whole runs apart are not (on 2 shared cores the
    run-by-run ratio ranged 0.63-1.24 at batch 32). Each model's step starts on caches the
    other's step filled: both pay that alike."""
    import lightning as L

    model, _ = build_model(overrides)
    twin, _ = build_model(overrides)
    bare = bare_step_fn(twin, autocast=precision != "32-true")
    pairs: list[tuple[float, float]] = []
    resumed = [0.0]

    class Alternate(L.Callback):
        """Stamps each Lightning step's end and runs the bare step after it."""

        def on_train_batch_start(
            self, trainer: L.Trainer, module: L.LightningModule, batch: dict, batch_idx: int
        ) -> None:
            if batch_idx == 0:
                resumed[0] = time.perf_counter()

        def on_train_batch_end(
            self, trainer: L.Trainer, module: L.LightningModule, outputs: Any, batch: dict,
            batch_idx: int,
        ) -> None:  # fmt: skip
            ended = time.perf_counter()
            bare(batch)
            done = time.perf_counter()
            if batch_idx > 0 and batch_idx >= warmup:
                pairs.append((ended - resumed[0], done - ended))
            resumed[0] = done

    trainer = quiet_trainer(Alternate(), max_steps=warmup + steps, precision=precision)
    trainer.fit(model, train_dataloaders=InMemory(batches, warmup + steps))
    return pairs
