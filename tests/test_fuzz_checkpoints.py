"""Property-based tests (hypothesis) of the checkpoint loader: whole, random, cut short,
garbled and unsafe files (pickles that would run code). A checkpoint that is not loaded is
called corrupt or unsafe, whichever it is, in one line naming the file, and nothing in it
runs."""

from __future__ import annotations

import io
import pickle
import re
import tempfile
from pathlib import Path

import torch
from hypothesis import given
from hypothesis import strategies as st

from fuzz_readers import HEADERS
from mfg_lightning.run.checkpoints import CheckpointError, load_checkpoint

# --------------------------------------------------------------------------------------------
# Checkpoints
# --------------------------------------------------------------------------------------------


class _RunsCode:
    """A pickle payload: unpickling it writes ``marker`` (``Path.write_text``)."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (Path.write_text, (self.marker, "the checkpoint ran code"))


def _checkpoint_bytes(extra: dict | None = None) -> bytes:
    buf = io.BytesIO()
    config = {"net": {"hidden_units": 4, "height": 2, "width": 2}}
    torch.save(
        {"state_dict": {"w": torch.arange(4.0)}, "mfg_model_config": config, **(extra or {})}, buf
    )
    return buf.getvalue()


_CHECKPOINT = _checkpoint_bytes()


@st.composite
def checkpoint_files(draw: st.DrawFn, marker: Path) -> tuple[str, bytes]:
    """``(what it is, bytes)``: ``"whole"``, ``"random"`` bytes, ``"corrupt"`` (a checkpoint
    cut short), ``"garbled"`` (a checkpoint with bytes overwritten: it may still load) or
    ``"unsafe"`` (a pickle, bare or inside a checkpoint, that would write ``marker``)."""
    kind = draw(st.sampled_from(["whole", "random", "truncate", "flip", "pickle", "zip_pickle"]))
    if kind == "whole":
        return "whole", _CHECKPOINT
    if kind == "random":
        return "random", draw(st.binary(min_size=1, max_size=400))
    if kind == "truncate":
        return "corrupt", _CHECKPOINT[: draw(st.integers(1, len(_CHECKPOINT) - 1))]
    if kind == "flip":
        data = bytearray(_CHECKPOINT)
        for _ in range(draw(st.integers(1, 4))):
            data[draw(st.integers(0, len(data) - 1))] = draw(st.integers(0, 255))
        return "garbled", bytes(data)
    if kind == "pickle":
        protocol = draw(st.integers(0, pickle.HIGHEST_PROTOCOL), label="protocol")
        return "unsafe", pickle.dumps({"state_dict": _RunsCode(marker)}, protocol=protocol)
    return "unsafe", _checkpoint_bytes({"payload": _RunsCode(marker)})


@HEADERS
@given(data=st.data())
def test_checkpoints_load_or_are_called_corrupt_or_unsafe_and_nothing_runs(data) -> None:
    """Random bytes were described as a file that "holds Python objects … could run code"."""
    with tempfile.TemporaryDirectory() as tmp:
        marker = Path(tmp) / "marker.txt"
        kind, payload = data.draw(checkpoint_files(marker), label="checkpoint")
        path = Path(tmp) / "model.ckpt"
        path.write_bytes(payload)
        try:
            ckpt = load_checkpoint(path)
        except CheckpointError as err:
            message = str(err)
            assert str(path) in message and "\n" not in message, message
            said = {"corrupt", "unsafe"} & set(re.findall(r"\b(corrupt|unsafe)\b", message))
            if kind == "garbled" and not said:  # it still loads, but lost a key of its own
                assert "not a Lightning checkpoint" in message or "mfg_lightning.train" in message
                return
            assert len(said) == 1, f"neither or both of corrupt and unsafe: {message}"
            # random bytes that happen to pickle a global are unsafe too; a garbled checkpoint
            # is either
            if kind not in ("garbled", "random"):
                assert said == {kind}, f"a {kind} checkpoint called: {message}"
        else:
            assert kind in ("whole", "garbled"), f"a {kind} file was loaded as a checkpoint"
            assert set(ckpt) >= {"state_dict", "mfg_model_config"}
        assert not marker.exists(), "reading the checkpoint ran its code"
