"""The data order of a resumable run: each epoch's order depends on the seed and the epoch
alone, and a loader restored from a checkpoint's state continues it mid-epoch, at an epoch's
end, and under DDP (each process its share; another number of processes starts the epoch
again)."""

from __future__ import annotations

import pytest
import torch

from mfg_lightning.data.resumable_loader import EpochShuffleSampler, ResumableDataLoader

pytestmark = pytest.mark.slow


def _ids(loader: ResumableDataLoader) -> list[list[int]]:
    return [batch.tolist() for batch in loader]


def _flat(batches: list[list[int]]) -> list[int]:
    return [i for batch in batches for i in batch]


def test_epoch_order_depends_on_seed_and_epoch_only_and_resumes_mid_epoch() -> None:
    data = torch.arange(18)
    loader = ResumableDataLoader(data, seed=5, batch_size=4)
    epochs = []
    for epoch in range(3):
        loader.order.set_epoch(epoch)
        epochs.append(_ids(loader))
    assert all(sorted(_flat(e)) == list(range(18)) for e in epochs)  # permutations
    assert epochs[0] != epochs[1] != epochs[2]
    assert _ids(ResumableDataLoader(data, seed=6, batch_size=4)) != epochs[0]

    # Stop after 3 batches of epoch 1, save, restore into a new loader (a new process).
    loader.order.set_epoch(1)
    it = iter(loader)
    seen = [next(it).tolist() for _ in range(3)]
    state = loader.state_dict()
    assert state == {"epoch": 1, "batches": 3, "samples": 18, "processes": 1, "length": 5,
                     "batch_size": 4, "dataset": "Tensor",
                     "sampler": "EpochShuffleSampler(seed=5)"}  # fmt: skip
    resumed = ResumableDataLoader(data, seed=5, batch_size=4)
    resumed.load_state_dict(state)
    assert resumed.state_dict() == state  # saved again before iterating: still the same place
    resumed.order.set_epoch(1)  # what Lightning does at the start of the epoch
    assert seen + _ids(resumed) == epochs[1]
    assert len(resumed) == 5  # the epoch's length, as Lightning counts its batches
    resumed.order.set_epoch(2)  # the next epoch starts from its beginning
    assert _ids(resumed) == epochs[2]


def test_an_order_saved_at_the_end_of_an_epoch_resumes_with_the_next_one() -> None:
    data = torch.arange(10)
    loader = ResumableDataLoader(data, seed=0, batch_size=5)
    loader.load_state_dict({"epoch": 0, "batches": 2, "samples": 10})
    loader.order.set_epoch(1)
    sampler = EpochShuffleSampler(10, 0)
    assert _flat(_ids(loader)) == sampler.permutation(1).tolist()


def test_under_ddp_each_process_takes_its_share_of_the_order_and_resumes_it_mid_epoch() -> None:
    data, processes = torch.arange(19), 2  # 19: the last round is padded
    loaders = [
        ResumableDataLoader(data, seed=5, batch_size=3, num_replicas=processes, rank=r)
        for r in range(processes)
    ]
    shares = []
    for loader in loaders:
        loader.order.set_epoch(1)
        shares.append(_ids(loader))
    assert [len(share) for share in shares] == [len(loader) for loader in loaders] == [4, 4]
    # positions r, r + 2, ... of the epoch's one permutation, padded with its first index
    permutation = EpochShuffleSampler(19, 5).permutation(1).tolist()
    padded = [*permutation, permutation[0]]
    assert [_flat(share) for share in shares] == [padded[0::2], padded[1::2]]

    # Stopped after 2 batches of each process (the checkpoint holds rank 0's state, the same as
    # rank 1's), resumed by 2 new processes: each continues its own share.
    states = []
    for loader in loaders:
        it = iter(loader)
        [next(it) for _ in range(2)]
        states.append(loader.state_dict())
    assert states[0] == states[1] == {"epoch": 1, "batches": 2, "samples": 19, "processes": 2,
                                      "length": 4, "batch_size": 3, "dataset": "Tensor",
                                      "sampler": "EpochShuffleSampler(seed=5)"}  # fmt: skip
    for rank, share in enumerate(shares):
        resumed = ResumableDataLoader(data, seed=5, batch_size=3, num_replicas=2, rank=rank)
        resumed.load_state_dict(states[0])
        resumed.order.set_epoch(1)
        assert share[:2] + _ids(resumed) == share
    # Another number of processes: the interrupted epoch starts again, whole.
    other = ResumableDataLoader(data, seed=5, batch_size=3, num_replicas=3, rank=0)
    other.load_state_dict(states[0])
    other.order.set_epoch(1)
    assert _flat(_ids(other)) == permutation[0::3]
