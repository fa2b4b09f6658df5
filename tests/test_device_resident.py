"""``dataset.device_resident``: the training split held on the device, its batches gathered there.

It must be the ordinary loader's batches in the ordinary loader's order (one process and a
process of several), resumed mid-epoch alike, and train to the same weights; a split above its
bound keeps the ordinary loader.
"""

from __future__ import annotations

import logging

import pytest
import torch

from conftest import quiet_trainer
from mfg_lightning.data.device_resident import DeviceResidentLoader
from mfg_lightning.data.resumable_loader import ResumableDataLoader
from mfg_lightning.run.runs import set_baseline
from module_helpers import small_datamodule, small_module


def _same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(
        torch.equal(a[k], b[k]) if isinstance(a[k], torch.Tensor) else a[k] == b[k] for k in a
    )


def _loaders(replicas: int = 1, rank: int = 0) -> tuple[ResumableDataLoader, DeviceResidentLoader]:
    dm = small_datamodule(sequence_length=16, batch_size=3)
    dataset = dm.dataset("train")
    plain = ResumableDataLoader(dataset, seed=dm.seed, batch_size=3, num_replicas=replicas,
                                rank=rank, collate_fn=dm.train_dataloader().collate_fn)  # fmt: skip
    source = torch.utils.data.DataLoader(dataset, batch_size=5, collate_fn=plain.collate_fn)
    resident = DeviceResidentLoader(dataset, source=source, device=torch.device("cpu"),
                                    seed=dm.seed, batch_size=3, num_replicas=replicas, rank=rank,
                                    collate_fn=plain.collate_fn)  # fmt: skip
    return plain, resident


def test_the_batches_are_the_ordinary_loaders_in_its_order() -> None:
    for replicas, rank in ((1, 0), (2, 1)):
        plain, resident = _loaders(replicas, rank)
        assert len(plain) == len(resident) >= 2
        for epoch in (0, 1):
            for loader in (plain, resident):
                loader.order.set_epoch(epoch)
            got, want = list(resident), list(plain)
            assert len(got) == len(want)
            assert all(_same(g, w) for g, w in zip(got, want, strict=True)), (replicas, epoch)
        assert resident.store is not None and resident.store.n == len(plain.dataset)


def test_a_pass_resumed_mid_epoch_gives_the_rest_of_the_batches() -> None:
    _, resident = _loaders()
    resident.order.set_epoch(1)
    seen = iter(resident)
    for _ in range(2):
        next(seen)
    state = resident.state_dict()
    assert state["epoch"] == 1 and state["batches"] == 2
    rest = list(seen)
    _, again = _loaders()
    again.load_state_dict(state)
    resumed = list(again)
    assert len(resumed) == len(rest) and all(
        _same(a, b) for a, b in zip(resumed, rest, strict=True)
    )


def test_training_on_it_gives_the_weights_of_the_ordinary_loader() -> None:
    weights = []
    for resident in (False, True):
        torch.manual_seed(0)
        model = small_module()
        dm = small_datamodule(device_resident=resident)
        set_baseline(model, dm)
        trainer = quiet_trainer(max_steps=6, limit_val_batches=0)
        trainer.fit(model, datamodule=dm)
        assert isinstance(trainer.train_dataloader, DeviceResidentLoader) == resident
        weights.append({k: v.clone() for k, v in model.state_dict().items()})
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])


def test_a_split_above_its_bound_keeps_the_ordinary_loader(caplog) -> None:
    dm = small_datamodule(device_resident=True, device_resident_mb=0.01)
    with caplog.at_level(logging.WARNING, logger="mfg_lightning.data.base"):
        loader = dm.train_dataloader()
    assert not isinstance(loader, DeviceResidentLoader)
    assert "does not fit" in caplog.text and "device_resident_mb=0.01" in caplog.text


def test_a_split_with_unreadable_samples_is_refused_naming_the_count() -> None:
    plain, _ = _loaders()
    dataset = plain.dataset

    class OneUnreadable(torch.utils.data.Dataset):
        def __len__(self) -> int:
            return len(dataset)

        def __getitem__(self, i: int):
            return None if i == 3 else dataset[i]

    holed = OneUnreadable()
    source = torch.utils.data.DataLoader(holed, batch_size=5, collate_fn=plain.collate_fn)
    bad = DeviceResidentLoader(holed, source=source, device=torch.device("cpu"), seed=0,
                               batch_size=3, collate_fn=plain.collate_fn)  # fmt: skip
    with pytest.raises(ValueError, match=r"1 of the \d+ training samples did not load"):
        next(iter(bad))
