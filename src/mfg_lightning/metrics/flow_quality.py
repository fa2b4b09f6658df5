"""A flow estimate's quality pooled pixel by pixel over a split, per named set of pixels: the mean
end-point error (px) and KITTI's Fl outlier rate (%), as a torchmetrics ``Metric`` whose sums are
added up across processes where Lightning and torchmetrics reduce (``compute``)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from torch import Tensor
from torchmetrics import Metric

__all__ = ["PooledFlowQuality"]


class PooledFlowQuality(Metric):
    """Per name of ``names``: the sum of the end-point errors (px), the number of Fl outliers and
    the number of pixels counted, kept as sums (float64) so that batches and processes pool by
    addition (``dist_reduce_fx="sum"``: every pixel counted once, whichever process scored it).

    ``update`` reads nothing back from the device; ``compute`` gives, per name with at least one
    pixel, ``(mean EPE px, Fl outliers %)``.

    An Fl outlier (KITTI 2015) is a pixel whose end-point error exceeds 3 px and 5 % of the exact
    flow's magnitude; the caller computes it (``outlier``) beside the errors.

    Args:
        names: the sets of pixels, in a fixed order (the same on every process: a process may
            see no pixel of some set).
    """

    full_state_update = False

    def __init__(self, names: Sequence[str], **kwargs: object) -> None:
        super().__init__(**kwargs)
        self.names = tuple(names)
        self._index = {name: i for i, name in enumerate(self.names)}
        self.add_state(
            "sums",
            default=torch.zeros(len(self.names), 3, dtype=torch.float64),
            dist_reduce_fx="sum",
        )

    def update(self, epe: Tensor, outlier: Tensor, masks: Mapping[str, Tensor]) -> None:
        """Add a batch's pixels.

        Args:
            epe: ``(B, H, W)`` end-point errors (px).
            outlier: ``(B, H, W)`` bool, the Fl outliers.
            masks: ``(B, H, W)`` bool per name, the pixels of that set (names not in ``names``
                are left out).
        """
        rows, index = [], []
        for name, mask in masks.items():
            if name in self._index:
                rows.append(torch.stack((epe[mask].sum(), outlier[mask].sum().float(),
                                         mask.sum().float())))  # fmt: skip
                index.append(self._index[name])
        if rows:
            at = torch.tensor(index, device=self.sums.device)
            self.sums = self.sums.index_add(0, at, torch.stack(rows).to(self.sums))

    def compute(self) -> dict[str, tuple[float, float]]:
        """``{name: (mean EPE px, Fl outliers %)}`` for every name with a pixel (one host read)."""
        out = {}
        for name, (epe, outliers, n) in zip(self.names, self.sums.tolist(), strict=True):
            if n > 0:
                out[name] = (epe / n, 100.0 * outliers / n)
        return out
